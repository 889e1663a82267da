"""The identity of a run folder: which scene (by content) and which result-changing settings.

``RUN/run.json`` records the scene's path, a fingerprint of its files' content and the settings that
change results. A later ``projo4d run`` into the same folder

* with the same identity resumes (every step skips what it finished);
* with another scene, changed scene files or other result-changing settings is refused in one line
  that offers ``--resume`` (continue what is there, with its own settings), ``--overwrite`` (start
  again) or a new folder, so results of another scene or curriculum are never printed.

Settings that do not change results (``out``, ``device``, ``threads``, ``checkpoint_every``,
``report_cameras``) are not part of the identity. CPU and GPU runs are not bit-identical, but
moving a run to another device to finish it is allowed on purpose.

A folder made by ``projo4d stage0`` (stage 0 only) records the scene and only the settings stage 0
depends on (:data:`STAGE0_SETTINGS`, ``"stage": "stage0"`` in ``run.json``). A later ``projo4d run``
into it whose stage-0 settings agree takes the folder over (its stage 0 is reused, the full
identity is recorded); one whose stage-0 settings differ is refused like any other run.
``projo4d stage0`` into a folder of a whole run checks the stage-0 settings only and leaves the
run's records alone.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Optional

from toolkit.atomic import write_json
from toolkit.run_validation import SettingsError

__all__ = ["RUN_FILE", "scene_fingerprint", "run_identity", "claim_run_folder", "recorded_identity", "recorded_settings",
           "RUN_ARTIFACTS", "STAGE0_SETTINGS"]

RUN_FILE = "run.json"
#: settings that never change results (excluded from the identity)
NEUTRAL_SETTINGS = frozenset({"scene", "out", "device", "threads", "checkpoint_every", "report_cameras", "refine_grid",
                              "refine_iterations"})
#: the settings stage 0 depends on (the identity of a folder that ran only stage 0)
STAGE0_SETTINGS = ("cameras", "downscale", "geometry", "n_train", "renderer", "seed", "stage0")
#: what a run folder may hold (``--overwrite`` removes exactly these)
RUN_ARTIFACTS = ("run.json", "settings.json", "world.json", "stage0", "continuum", "physics_input.pt", "physics", "evaluation",
                 "report", "summary.json", "refined")


def scene_fingerprint(root: str | Path) -> str:
    """A digest of every non-hidden file under ``root``: relative path, size and content (BLAKE2b-128).

    Copying or moving the scene keeps it; editing, adding or removing a file changes it.
    """
    root = Path(root)
    h = hashlib.blake2b(digest_size=16)
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root)
        if any(part.startswith(".") for part in rel.parts):
            continue
        h.update(str(rel.as_posix()).encode() + b"\0" + str(path.stat().st_size).encode() + b"\0")
        with path.open("rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def run_identity(settings, stage: str = "run") -> dict:
    """The identity of a :class:`~toolkit.run_settings.RunSettings`: scene fingerprint and settings.

    ``stage="stage0"``: only the :data:`STAGE0_SETTINGS`, marked ``"stage": "stage0"``.
    """
    d = asdict(settings)
    identity = {
        "scene": str(Path(settings.scene).resolve()),
        "scene_fingerprint": scene_fingerprint(settings.scene),
        "settings": {k: v for k, v in sorted(d.items()) if k not in NEUTRAL_SETTINGS},
    }
    return _stage0_part(identity) if stage == "stage0" else identity


def _stage0_part(identity: dict) -> dict:
    """``identity`` reduced to the scene and the :data:`STAGE0_SETTINGS`."""
    settings = identity.get("settings", {})
    return {"scene": identity.get("scene"), "scene_fingerprint": identity.get("scene_fingerprint"), "stage": "stage0",
            "settings": {k: settings.get(k) for k in STAGE0_SETTINGS}}


def recorded_identity(out: str | Path) -> Optional[dict]:
    """The identity a run folder recorded (``run.json``: scene, scene fingerprint, settings), or None."""
    path = Path(out) / RUN_FILE
    if not path.is_file():
        return None
    try:
        identity = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return identity if isinstance(identity, dict) else None


def recorded_settings(out: str | Path) -> Optional[dict]:
    """The full settings a run folder recorded (``settings.json``), or None."""
    path = Path(out) / "settings.json"
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _differences(old: dict, new: dict) -> list[str]:
    out = []
    if old.get("scene_fingerprint") != new["scene_fingerprint"]:
        if old.get("scene") == new["scene"]:
            out.append(f"the files of scene {new['scene']} changed since the run started")
        else:
            out.append(f"scene {old.get('scene')} in the folder, {new['scene']} asked")
    a, b = old.get("settings", {}), new["settings"]
    for key in sorted(set(a) | set(b)):
        if json.dumps(a.get(key), sort_keys=True) != json.dumps(b.get(key), sort_keys=True):
            out.append(f"{key}: {a.get(key)!r} in the folder, {b.get(key)!r} asked")
    return out


def claim_run_folder(settings, mode: str = "auto", stage: str = "run") -> str:
    """Check ``settings.out`` against ``settings`` and prepare it; returns ``"new"`` or ``"resume"``.

    Args:
        mode: ``"auto"`` (resume the same run, refuse another), ``"resume"`` (there must be a run,
            and the settings must be its own) or ``"overwrite"`` (remove the run that is there).
        stage: ``"run"`` (the whole pipeline) or ``"stage0"`` (stage 0 only: the identity is the
            scene and :data:`STAGE0_SETTINGS`; a whole run in the folder is checked on those only
            and its records are kept). A whole run into a stage-0-only folder compares the stage-0
            settings and then records its full identity.

    Raises:
        SettingsError: the folder holds another run (the message lists what differs and the three
            ways on), is not a run folder, or there is nothing to resume. Nothing is written then.
    """
    if mode not in ("auto", "resume", "overwrite"):
        raise SettingsError("mode", mode, "expected 'auto', 'resume' or 'overwrite'")
    if stage not in ("run", "stage0"):
        raise SettingsError("stage", stage, "expected 'run' or 'stage0'")
    out = Path(settings.out)
    identity = run_identity(settings, stage)
    run_file = out / RUN_FILE
    occupied = out.is_dir() and any(out.iterdir())
    if occupied and not run_file.is_file():
        ours = [p.name for p in out.iterdir() if p.name in RUN_ARTIFACTS]
        if not ours:
            raise SettingsError("out", str(out), "this folder is not empty and holds no projo4d run; choose another --out")
        if mode != "overwrite":
            raise SettingsError("out", str(out), "this folder holds a run from a projo4d without run identities; "
                                                 "pass --overwrite to start it again, or choose another --out")
    if mode == "resume" and not run_file.is_file():
        raise SettingsError("out", str(out), "there is no run to resume in this folder (no run.json)")
    if run_file.is_file():
        try:
            old = json.loads(run_file.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise SettingsError("out", str(out), f"{run_file} is unreadable ({err}); pass --overwrite to start again") from None
        partial = stage == "stage0" or old.get("stage") == "stage0"
        diff = _differences(_stage0_part(old), _stage0_part(identity)) if partial else _differences(old, identity)
        if diff and mode != "overwrite":
            head = "; ".join(diff[:4]) + (f"; and {len(diff) - 4} more" if len(diff) > 4 else "")
            what = "stage 0 (run with other stage-0 settings)" if partial else "run"
            raise SettingsError("out", str(out), f"this folder holds another {what} ({head}). To continue that run use "
                                                 f"`projo4d {stage} --resume --out {out}`, to replace it add --overwrite, "
                                                 f"or choose another --out")
        if not diff:
            for tmp in out.rglob(".*.tmp*"):  # what a SIGKILL left mid-write (never read: writes are atomic)
                tmp.unlink(missing_ok=True)
            if stage == "stage0" and old.get("stage") != "stage0":
                return "resume"  # stage 0 of a whole run: its records stay
            if old.get("stage") == "stage0" and stage == "run":
                write_json(run_file, identity)  # the whole run takes the stage-0 folder over
            write_json(out / "settings.json", asdict(settings))
            return "resume"
    if occupied and mode == "overwrite":
        for name in RUN_ARTIFACTS:
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
        for p in out.glob("*.corrupt*"):
            p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    write_json(run_file, identity)
    write_json(out / "settings.json", asdict(settings))
    return "new"

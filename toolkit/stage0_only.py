"""Stage 0 on its own (``projo4d stage0``): the 4D Gaussians of a scene, in a run folder.

:func:`run_stage0` takes the same :class:`~toolkit.run_settings.RunSettings` as
:func:`~toolkit.pipeline.run_pipeline`, checks all of them the same way before any work
(:mod:`toolkit.run_validation`), claims the folder with a stage-0 identity (the scene and
:data:`~toolkit.run_folder.STAGE0_SETTINGS`, see :mod:`toolkit.run_folder`) and runs only stage 0:
``RUN/stage0/last.ckpt``, ``RUN/stage0/gaussians.ply``, logs under ``RUN/stage0/logs`` and
``RUN/stage0/summary.json``. Rerunning resumes from the newest checkpoint; a finished stage 0 is
loaded, not trained again. A later ``projo4d run`` into the same folder with the same stage-0
settings reuses this stage 0 and goes on with the continuum and the physics.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

from toolkit.atomic import write_json
from toolkit.run_validation import SettingsError

__all__ = ["STAGE0_SUMMARY", "run_stage0", "format_stage0_summary"]

#: what :func:`run_stage0` writes next to the checkpoints
STAGE0_SUMMARY = "summary.json"


def run_stage0(settings, mode: str = "auto") -> dict:
    """Run stage 0 of ``settings`` into ``settings.out``; returns (and writes) its summary.

    Args:
        settings: a :class:`~toolkit.run_settings.RunSettings` (``geometry`` must be ``"stage0"``).
        mode: ``"auto"`` (resume the same stage 0, refuse another), ``"resume"`` or ``"overwrite"``
            (see :func:`~toolkit.run_folder.claim_run_folder`).

    Returns:
        ``{"iterations", "n_gaussians", "stage0_s", "last_logged", "opacity_resets_reverted", "coverage", "files"}``:
        iterations done, Gaussians at the end, seconds of this call, the last logged ``train/*``
        metrics (loss, L1, SSIM, PSNR in dB; empty if none were logged), the opacity resets undone
        because they faded most of the model (:mod:`toolkit.scene.opacity_reset`), how much of each
        training frame's masks the Gaussians cover (:func:`toolkit.scene.coverage.coverage_record`,
        with the frames where stage 0 lost the object; None without masks) and the files written.

    Raises:
        SettingsError: a bad setting or a folder holding another run or stage 0 (nothing written).
    """
    from toolkit.checkpointing import graceful_interrupts
    from toolkit.data import load_scene
    from toolkit.pipeline import _device, fit_stage0_step
    from toolkit.run_folder import claim_run_folder
    from toolkit.threads import configure_threads

    s = settings
    if s.geometry != "stage0":
        raise SettingsError("geometry", s.geometry, "projo4d stage0 fits stage 0; 'oracle' geometry has none "
                                                    "(use `projo4d run --geometry oracle`)")
    s.validate()
    claim_run_folder(s, mode, stage="stage0")
    configure_threads(s.threads, device=_device(s.device), name="RunSettings.threads (--threads)")
    run = Path(s.out)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    with graceful_interrupts():
        module, _ = fit_stage0_step(s, load_scene(s.scene), run, timings)
    stage0_dir = run / "stage0"
    summary = {"iterations": int(module.step), "n_gaussians": int(module.gaussians.n),
               "stage0_s": time.perf_counter() - t, "last_logged": last_logged_metrics(stage0_dir / "logs"),
               "opacity_resets_reverted": list(module.reset_guard.reverted),
               "coverage": _coverage(stage0_dir),
               "files": [str(stage0_dir / "last.ckpt"), str(stage0_dir / "gaussians.ply"), str(stage0_dir / "logs")]}
    write_json(stage0_dir / STAGE0_SUMMARY, summary)
    return summary


def _coverage(stage0_dir: Path):
    import json

    from toolkit.pipeline import COVERAGE_FILE

    path = stage0_dir / COVERAGE_FILE
    return json.loads(path.read_text()) if path.is_file() else None


def last_logged_metrics(logs: Path) -> dict:
    """The last row of ``train/*`` metrics in the CSV logs under ``logs`` (``version_K/metrics.csv``,
    newest version last), as ``{name: float}``; ``{}`` when none were logged."""
    def version(p: Path) -> int:
        tail = p.parent.name.rpartition("_")[2]
        return int(tail) if tail.isdigit() else -1

    last: dict = {}
    for path in sorted(logs.glob("version_*/metrics.csv"), key=version):
        with path.open(newline="") as f:
            for row in csv.DictReader(f):
                values = {k: float(v) for k, v in row.items() if k and k.startswith("train/") and v not in ("", None)}
                if "train/loss" in values:
                    last = values
    return last


def format_stage0_summary(summary: dict) -> str:
    """A few lines for the terminal."""
    lines = [f"stage 0: {summary['iterations']} iterations, {summary['n_gaussians']} Gaussians "
             f"({summary['stage0_s']:.1f} s this call)"]
    logged = summary.get("last_logged") or {}
    if logged:
        lines.append(f"last logged (iteration {logged.get('train/iteration', float('nan')):.0f}): "
                     f"loss {logged.get('train/loss', float('nan')):.4f}, PSNR {logged.get('train/psnr', float('nan')):.2f} dB")
    coverage = summary.get("coverage") or {}
    if coverage.get("lost_frames"):
        from toolkit.scene.coverage import lost_object_message

        lines.append("WARNING " + lost_object_message(coverage))
    lines.append("files: " + ", ".join(summary["files"]))
    return "\n".join(lines)

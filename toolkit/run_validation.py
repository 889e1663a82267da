"""Check every setting of a run before any work starts.

:func:`validate_run_settings` reads only the scene's metadata (cameras, frames) and builds the
light objects a run will build later (material, strategy, :class:`~toolkit.mpm.SimConfig`, stage-0
schedule, continuum settings), so a mistake is reported in seconds, not after an hour of stage 0.
Each error is a :class:`SettingsError` naming the field, the value and what is valid; the CLI turns
it into one line and exit code 2. Nothing is written.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any

__all__ = ["SettingsError", "validate_run_settings", "check_plain_fields", "check_device", "parse_device_option"]

#: the most optimizer iterations a curriculum may have in all
_MAX_ITERATIONS = 1_000_000

log = logging.getLogger(__name__)


class SettingsError(ValueError):
    """A run setting is invalid; the message names the field, the value and what is valid."""

    exit_code = 2

    def __init__(self, field: str, value: Any, expected: str):
        self.field, self.value, self.expected = field, value, expected
        super().__init__(f"{field} = {value!r}: {expected}")


def check_refine_iterations(value: Any, field: str = "refine_iterations") -> float:
    """``RunSettings.refine_iterations``: a fraction of the curriculum's iterations in (0, 1]."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise SettingsError(field, value, "a fraction of the curriculum's iterations in (0, 1]")
    return float(value)


def check_device(name: str) -> str:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N`` with that GPU present; returns the resolved device."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return name
    if name == "cuda" or (name.startswith("cuda:") and name[5:].isdigit()):
        if not torch.cuda.is_available():
            raise SettingsError("device", name, "no CUDA device is available here; use 'cpu' or 'auto'")
        index = int(name[5:]) if ":" in name else 0
        if index >= torch.cuda.device_count():
            raise SettingsError("device", name, f"this machine has {torch.cuda.device_count()} CUDA device(s): "
                                                f"cuda:0..cuda:{torch.cuda.device_count() - 1}")
        return name
    raise SettingsError("device", name, "expected 'auto', 'cpu', 'cuda' or 'cuda:N'")


def parse_device_option(parser: Any, name: str) -> str:
    """:func:`check_device` for a command-line script: the resolved device, or ``parser.error``
    (an ``argparse.ArgumentParser``'s: usage and the message, exit status 2) naming the value."""
    try:
        return check_device(name)
    except SettingsError as err:
        parser.error(str(err))


def _check(field: str, value: Any, fn) -> Any:
    """Run ``fn()``; a ValueError/TypeError/KeyError from it becomes a SettingsError on ``field``."""
    try:
        return fn()
    except SettingsError:
        raise
    except (ValueError, TypeError, KeyError) as err:
        msg = (err.args[0] if isinstance(err, KeyError) and err.args else str(err)) or type(err).__name__
        raise SettingsError(field, value, msg) from None


def _writable(out: Path) -> None:
    probe = out
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise SettingsError("out", str(out), f"{probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise SettingsError("out", str(out), f"{probe} is not writable")


def check_plain_fields(s) -> None:
    """The checks of :func:`validate_run_settings` that read nothing but the settings and whether
    the scene folder exists (no torch, no scene contents): a typo is reported at once."""
    if not Path(s.scene).is_dir():
        raise SettingsError("scene", str(s.scene), "this folder does not exist")
    if s.geometry not in ("stage0", "oracle"):
        raise SettingsError("geometry", s.geometry, "expected 'stage0' or 'oracle'")
    if not isinstance(s.downscale, int) or isinstance(s.downscale, bool) or s.downscale < 1:
        raise SettingsError("downscale", s.downscale, "expected an integer >= 1")
    if not isinstance(s.seed, int) or isinstance(s.seed, bool):
        raise SettingsError("seed", s.seed, "expected an integer")
    if not isinstance(s.checkpoint_every, int) or s.checkpoint_every < 0:
        raise SettingsError("checkpoint_every", s.checkpoint_every, "expected an integer >= 0 (0: stage ends only)")
    if not isinstance(s.lambda_geometry, (int, float)) or not s.lambda_geometry >= 0:
        raise SettingsError("lambda_geometry", s.lambda_geometry, "expected a number >= 0")


def validate_run_settings(s) -> dict:
    """Validate a :class:`~toolkit.run_settings.RunSettings` against its scene; raises SettingsError.

    Returns facts the run reuses: ``device``, ``n_train``, ``cameras`` (0-based), ``n_frames``.
    """
    check_plain_fields(s)  # before the heavy imports: a typo is reported at once
    from materials import get_material
    from toolkit.data import load_scene
    from toolkit.data.datamodule import resolve_cameras
    from toolkit.mpm import SimConfig
    from toolkit.scene.continuum import ContinuumConfig

    scene_dir = Path(s.scene)
    device = check_device(str(s.device))
    _writable(Path(s.out))

    scene = _check("scene", str(s.scene), lambda: load_scene(scene_dir))
    cameras = _check("cameras", s.cameras, lambda: resolve_cameras(scene, s.cameras))
    if s.geometry == "stage0" and len(cameras) < 2:
        raise SettingsError("cameras", s.cameras, "stage 0 needs at least 2 fitting cameras (their silhouettes bound "
                                                  f"the body); this selects camera {cameras} alone. Use 'sparse', 'all' "
                                                  "or comma-separated 0-based indices such as '1,5,9'")
    if s.n_train is not None and not (isinstance(s.n_train, int) and 1 <= s.n_train <= scene.n_frames):
        raise SettingsError("n_train", s.n_train, f"expected an integer in [1, {scene.n_frames}] ({scene.name} has "
                                                  f"{scene.n_frames} frames)")
    from toolkit.pipeline import resolve_curriculum, training_frames

    n_train = training_frames(scene, s.n_train)
    if s.report_cameras is not None:
        bad = [c for c in s.report_cameras if not (isinstance(c, int) and 0 <= c < scene.n_cameras)]
        if bad:
            raise SettingsError("report_cameras", s.report_cameras, f"indices must be in [0, {scene.n_cameras - 1}]")

    material = _check("material", s.material, lambda: get_material(s.material, **(s.material_options or {})))
    _check("initial_params", s.initial_params, lambda: material.validate(material.complete(s.initial_params)))
    fit_ranges = _check("model_options.fit_ranges", (s.model_options or {}).get("fit_ranges"),
                        lambda: material.fit_ranges((s.model_options or {}).get("fit_ranges")))
    wanted = s.optimize_params if s.optimize_params is not None else [p.name for p in material.params if p.optimize]
    for name, value in (s.initial_params or {}).items():
        lo, hi = fit_ranges.get(name, (-math.inf, math.inf))
        if name in wanted and not lo <= float(value) <= hi:
            raise SettingsError(f"initial_params.{name}", value,
                                f"expected a start inside its fit range [{lo:g}, {hi:g}]; widen the range with "
                                f"model: {{fit_ranges: {{{name}: [low, high]}}}} (valid: [{material.param(name).low:g}, "
                                f"{material.param(name).high:g}])")
    if s.optimize_params is not None:
        unknown = set(s.optimize_params) - set(material.param_names)
        if unknown:
            raise SettingsError("optimize_params", s.optimize_params,
                                f"{sorted(unknown)} are not parameters of {material.name!r} ({material.param_names})")
    from toolkit.physics.module import DEFAULT_LEARNING_RATES

    if s.learning_rates is not None:
        known = set(DEFAULT_LEARNING_RATES) | set(material.param_names)
        unknown = set(s.learning_rates) - known
        if unknown:
            raise SettingsError("learning_rates", s.learning_rates, f"unknown key(s) {sorted(unknown)}; known: {sorted(known)}")
        bad = {k: v for k, v in s.learning_rates.items() if not (isinstance(v, (int, float)) and v > 0)}
        if bad:
            raise SettingsError("learning_rates", s.learning_rates, f"rates must be numbers > 0, got {bad}")

    strategy = _check("curriculum", s.curriculum, lambda: resolve_curriculum(s.curriculum, s.curriculum_options))
    stages = _check("curriculum", s.curriculum, lambda: strategy.stages(material.registry_name or None))
    _check_stages(stages, s.curriculum, n_train, len(cameras), strict=isinstance(s.curriculum, str) and ":" in s.curriculum)

    sim = _check("sim", s.sim, lambda: SimConfig(**{"auto_dt_halving": True, **(s.sim or {})}))
    _check("continuum", s.continuum, lambda: ContinuumConfig.from_dict({"grid_size": 4 * sim.dx, **(s.continuum or {})}))
    _check_stage0(s.stage0)
    if s.renderer != "auto":
        from renderers import RENDERERS

        _check("renderer", s.renderer, lambda: RENDERERS.get(s.renderer))
    return {"device": device, "n_train": n_train, "cameras": cameras, "n_frames": scene.n_frames}


def _check_stages(stages, spec, n_train: int, n_cameras: int, strict: bool) -> None:
    """Frame windows and batch sizes against the data.

    A frame window (``@W``) longer than the training frames in a schedule string the user wrote
    (``strict``) is an error: it asks for frames that are not there. Batch sizes (``/CxF``) larger
    than what there is to sample, and a named strategy's window (its defaults are sized for 14
    training frames), are clamped by the fit, and said here (a warning for a user's schedule).
    """
    total = sum(st.iterations for st in stages)
    if total > _MAX_ITERATIONS:
        raise SettingsError("curriculum", spec, f"{total} iterations in all; at most {_MAX_ITERATIONS} are supported")
    for k, st in enumerate(stages):
        where = f"stage {k + 1} ({st.name})"
        notes = []
        if isinstance(st.frames, int) and st.frames > n_train:  # a free-flight window (@ff) is set per clip
            what = (f"{where} fits the first {st.frames} frames but the run has {n_train} training frames "
                    "(set n_train or a smaller @window)")
            if strict:
                raise SettingsError("curriculum", spec, what)
            notes.append(what)
        window = st.window(n_train)
        if st.frames_per_step is not None and st.frames_per_step > window:
            notes.append(f"{where} samples {st.frames_per_step} frames per iteration from a window of {window}")
        if st.cameras_per_step is not None and st.cameras_per_step > n_cameras:
            notes.append(f"{where} samples {st.cameras_per_step} cameras per iteration but {n_cameras} cameras are fitted")
        for note in notes:  # a named strategy's defaults are meant to be clamped: said at info level
            log.log(logging.WARNING if strict else logging.INFO, "curriculum %r: %s; the fit uses all there are", spec, note)


def _check_stage0(spec) -> None:
    from toolkit.scene.stage0 import Stage0Schedule

    if isinstance(spec, str):
        if spec not in ("full", "tiny"):
            raise SettingsError("stage0", spec, "expected 'full', 'tiny' or a mapping of Stage0Schedule fields "
                                                "(with optional 'preset': 'full' or 'tiny')")
        return
    if not isinstance(spec, dict):
        raise SettingsError("stage0", spec, "expected 'full', 'tiny' or a mapping of Stage0Schedule fields")
    spec = dict(spec)
    preset = spec.pop("preset", "full")
    if preset not in ("full", "tiny"):
        raise SettingsError("stage0.preset", preset, "expected 'full' or 'tiny'")
    base = (Stage0Schedule.tiny() if preset == "tiny" else Stage0Schedule.full()).to_dict()
    _check("stage0", spec, lambda: Stage0Schedule.from_dict({**base, **spec}))

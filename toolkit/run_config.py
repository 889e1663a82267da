"""The ``run:`` / ``model:`` / ``trainer:`` config layout of ``configs/``, read by ``projo4d run``.

One YAML file serves both commands: ``projo4d fit`` (LightningCLI) reads ``model:`` and
``trainer:``; ``projo4d run`` reads all three sections into a :class:`~toolkit.run_settings.RunSettings`.
Nothing is dropped: every key is either carried or refused.

* ``run:`` -- any :class:`~toolkit.run_settings.RunSettings` field (stage 0, cameras, n_train, ...).
* ``model:`` -- any :class:`~toolkit.physics.InversePhysicsModule` argument except
  ``input_path`` (the pipeline writes the physics input). The arguments RunSettings has fields for
  (:data:`RUN_MODEL_KEYS`) go to those fields; the others (:data:`MODULE_OPTIONS`: ``effects``,
  ``v0_init``, ``material_init``, ``lambda_image``, ``ssim_weight``, ``warmup_fraction``, ``embedding_neighbours``, ``embedding``,
  ``gaussian_shape``, ``fit_ranges``) go to ``RunSettings.model_options`` and on to the module unchanged.
* ``trainer:`` -- the Trainer keys that mean something for a whole run (:data:`TRAINER_KEYS`):
  ``accelerator`` (``auto``/``cpu``/``gpu``/``cuda``) becomes ``device`` unless ``run:`` sets it;
  ``default_root_dir`` is ``projo4d fit``'s folder and is accepted but not used: a run's folder is
  ``--out`` or ``run.out`` (default ``runs/<scene name>``, so one config serves many scenes). Other Trainer keys
  (``max_epochs``, ``logger``, ...) are refused: the run's curriculum and folders decide them.

An unknown key anywhere is a :class:`~toolkit.run_validation.SettingsError` naming the key and the
valid ones (exit status 2 from the CLI).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from toolkit.run_validation import SettingsError

__all__ = ["SECTIONS", "RUN_MODEL_KEYS", "MODULE_OPTIONS", "TRAINER_KEYS", "settings_from_sections", "check_model_options",
           "check_run_section"]

#: top-level sections of a config file in the sectioned layout
SECTIONS = ("run", "model", "trainer")
#: ``model:`` keys (InversePhysicsModule arguments) that are RunSettings fields of the same name
RUN_MODEL_KEYS = ("material", "material_options", "initial_params", "optimize_params", "curriculum", "sim",
                  "lambda_geometry", "learning_rates", "renderer", "seed", "optimize_gravity")
#: the other InversePhysicsModule arguments, carried in ``RunSettings.model_options``
#: ``model_options.material_init``: where the material's gradient descent starts
#: (:class:`toolkit.physics.module.InversePhysicsModule`).
MATERIAL_INITS = ("search", "search_joint", "given")

MODULE_OPTIONS = ("effects", "v0_init", "material_init", "lambda_image", "ssim_weight", "warmup_fraction",
                  "embedding_neighbours", "embedding", "gaussian_shape", "fit_ranges", "body_shift",
                  "uncertainty_options")
#: ``trainer:`` keys ``projo4d run`` accepts and the RunSettings field each sets (None: accepted, not used)
TRAINER_KEYS = {"accelerator": "device", "default_root_dir": None}
#: Lightning accelerator -> RunSettings.device
_ACCELERATOR_DEVICE = {"auto": "auto", "cpu": "cpu", "gpu": "cuda", "cuda": "cuda"}


def _unknown(where: str, given: Mapping, valid) -> None:
    """Raise naming the first unknown key of ``given`` (and any others) and the valid keys."""
    unknown = sorted(set(given) - set(valid), key=str)
    if unknown:
        more = f" (also unknown: {', '.join(map(str, unknown[1:]))})" if len(unknown) > 1 else ""
        raise SettingsError(f"{where}.{unknown[0]}", given[unknown[0]],
                            f"unknown key{more}; valid keys: {', '.join(sorted(valid))}")


def _section(cfg: Mapping, name: str, path) -> dict:
    value = cfg.get(name)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise SettingsError(f"{path}: {name}", value, "expected a mapping of keys to values")
    return dict(value)


def settings_from_sections(cfg: Mapping, path: Any) -> dict:
    """RunSettings fields (a dict) from a config in the ``run:`` / ``model:`` / ``trainer:`` layout.

    Args:
        cfg: the parsed YAML (a mapping with at least one of :data:`SECTIONS`).
        path: the file, for messages.

    Raises:
        SettingsError: an unknown section or key (the message names it and the valid ones), or a
            ``trainer.accelerator`` that has no run device.
    """
    from toolkit.pipeline import RunSettings

    fields = set(RunSettings.__dataclass_fields__)
    _unknown(f"{path}: section", cfg, SECTIONS)
    run, model, trainer = (_section(cfg, name, path) for name in SECTIONS)
    _unknown(f"{path}: run", run, fields)
    if "input_path" in model:
        raise SettingsError(f"{path}: model.input_path", model["input_path"],
                            "projo4d run writes the physics input itself (RUN/physics_input.pt); remove the key "
                            "(it is for `projo4d fit`)")
    _unknown(f"{path}: model", model, RUN_MODEL_KEYS + MODULE_OPTIONS)
    _unknown(f"{path}: trainer", trainer, TRAINER_KEYS)
    both = sorted(set(run) & set(model))
    if both:
        raise SettingsError(f"{path}: {both[0]}", both[0], "given in both run: and model:; keep one")

    out = {**run, **{k: model[k] for k in RUN_MODEL_KEYS if k in model}}
    options = {**(run.get("model_options") or {}), **{k: model[k] for k in MODULE_OPTIONS if k in model}}
    if options:
        out["model_options"] = options
    curriculum = out.get("curriculum")
    if isinstance(curriculum, dict):  # class_path / init_args, as LightningCLI writes a Strategy subclass
        if "class_path" not in curriculum:
            raise SettingsError(f"{path}: model.curriculum", curriculum, "a mapping needs class_path (and init_args)")
        out["curriculum"] = curriculum["class_path"]
        out["curriculum_options"] = dict(curriculum.get("init_args") or {})
    if "accelerator" in trainer and "device" not in out:
        accel = str(trainer["accelerator"])
        if accel not in _ACCELERATOR_DEVICE:
            raise SettingsError(f"{path}: trainer.accelerator", accel,
                                f"projo4d run supports {', '.join(_ACCELERATOR_DEVICE)} (or set run.device)")
        out["device"] = _ACCELERATOR_DEVICE[accel]
    return out


def check_run_section(run: Any, where: Any = "config") -> None:
    """Check the ``run:`` section of a config where ``projo4d fit`` reads it (it carries the
    pipeline's settings for ``projo4d run`` and ``projo4d stage0``): a mapping whose keys are
    :class:`~toolkit.run_settings.RunSettings` fields. The values are checked by ``projo4d run``
    against its scene; here only the keys, so one file means the same to every command.

    Raises:
        SettingsError: not a mapping, or an unknown key (named, with the valid keys).
    """
    from toolkit.pipeline import RunSettings

    if run is None:
        return
    if not isinstance(run, Mapping):
        raise SettingsError(f"{where}: run", run, "expected a mapping of RunSettings fields")
    _unknown(f"{where}: run", run, RunSettings.__dataclass_fields__)


def _number(name: str, value, low: float, high: float, *, closed_high: bool = True) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= low and (
        value <= high if closed_high else value < high)
    if not ok:
        raise SettingsError(f"model_options.{name}", value,
                            f"expected a number in [{low}, {high}{']' if closed_high else ')'}")


def check_model_options(options: Any) -> None:
    """Check ``RunSettings.model_options`` (InversePhysicsModule arguments) without building anything heavy.

    Valid keys are :data:`MODULE_OPTIONS`: ``effects`` ``{effect: {param: value}}`` (registered
    effects, values in each parameter's range), ``v0_init`` (3 numbers, m/s, canonical frame, or
    ``"auto"``/``"zero"``), ``material_init`` (``"search"``, ``"search_joint"`` or ``"given"``),
    ``lambda_image`` (>= 0 or None: ``1 / cameras``), ``ssim_weight`` in [0, 1],
    ``warmup_fraction`` in [0, 1), ``embedding_neighbours`` (integer >= 1), ``embedding``
    (``"idw"`` or ``"affine"``, :mod:`toolkit.physics.embedding`), ``gaussian_shape`` (``"rigid"``
    or ``"deformed"``), ``fit_ranges`` (``"valid"`` or ``{parameter: [low, high]}``; the
    parameters and ranges are checked against the material by
    :func:`toolkit.run_validation.validate_run_settings`).

    Raises:
        SettingsError: naming ``model_options.<key>``, the value and what is valid.
    """
    if options is None:
        return
    if not isinstance(options, dict):
        raise SettingsError("model_options", options, f"expected a mapping with keys {', '.join(MODULE_OPTIONS)}")
    _unknown("model_options", options, MODULE_OPTIONS)
    if options.get("effects") is not None:
        _check_effects(options["effects"])
    v0 = options.get("v0_init")
    if v0 is not None and v0 not in ("auto", "zero") and not (isinstance(v0, (list, tuple)) and len(v0) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in v0)):
        raise SettingsError("model_options.v0_init", v0, "expected 3 finite numbers (m/s, canonical frame), 'auto' or 'zero'")
    # the module's own checks, run here so that a config fails before any work
    from toolkit.physics.starting_state import rigid_shift
    from toolkit.physics.uncertainty import check_uncertainty_options

    for key, check in (("body_shift", rigid_shift), ("uncertainty_options", check_uncertainty_options)):
        if options.get(key) is not None:
            try:
                check(options[key])
            except ValueError as err:
                raise SettingsError(f"model_options.{key}", options[key], str(err)) from None
    if options.get("material_init", "search") not in MATERIAL_INITS:
        raise SettingsError("model_options.material_init", options["material_init"],
                            "expected 'search' (coarse search before gradient descent), 'search_joint' (the same with "
                            "the first and the yield parameter on one grid) or 'given' (start at the guesses)")
    if options.get("lambda_image") is not None:
        _number("lambda_image", options["lambda_image"], 0.0, math.inf)
    if "ssim_weight" in options:
        _number("ssim_weight", options["ssim_weight"], 0.0, 1.0)
    if "warmup_fraction" in options:
        _number("warmup_fraction", options["warmup_fraction"], 0.0, 1.0, closed_high=False)
    k = options.get("embedding_neighbours", 1)
    if not (isinstance(k, int) and not isinstance(k, bool) and k >= 1):
        raise SettingsError("model_options.embedding_neighbours", k, "expected an integer >= 1")
    if options.get("embedding", "idw") not in ("idw", "affine"):
        raise SettingsError("model_options.embedding", options["embedding"],
                            "expected 'idw' (inverse distance, the default) or 'affine' (Gaussians follow any locally affine motion exactly)")
    fr = options.get("fit_ranges")
    if fr is not None and fr != "valid" and not (isinstance(fr, dict) and all(
            isinstance(v, (list, tuple)) and len(v) == 2 for v in fr.values())):
        raise SettingsError("model_options.fit_ranges", fr,
                            "expected 'valid' (each parameter's valid range) or {parameter: [low, high]}")
    if options.get("gaussian_shape", "rigid") not in ("rigid", "deformed"):
        raise SettingsError("model_options.gaussian_shape", options["gaussian_shape"],
                            "expected 'rigid' (Gaussians keep their stage-0 shapes) or 'deformed' (their covariances follow the material)")


def _check_effects(effects) -> None:
    from toolkit.mpm.effects import EFFECTS, get_effect

    if not isinstance(effects, dict) or not all(isinstance(v, dict) for v in effects.values()):
        raise SettingsError("model_options.effects", effects, "expected {effect name: {parameter: initial value}}")
    for name, values in effects.items():
        if name not in EFFECTS:
            raise SettingsError("model_options.effects", name, f"unknown effect; registered: {', '.join(EFFECTS.names())}")
        effect = get_effect(name)
        _unknown(f"model_options.effects.{name}", values, [p.name for p in effect.params])
        try:
            effect.validate(values)
        except (ValueError, TypeError) as err:
            raise SettingsError(f"model_options.effects.{name}", values, str(err)) from None

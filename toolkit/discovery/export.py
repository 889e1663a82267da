"""Turn a discovery refit into an :class:`~toolkit.physics.InversePhysicsModule` with the effect added.

The new module has the base module's input, renderer, simulator settings, curriculum and loss
weights, the base module's Gaussians and particle offsets (plus the refit's rigid shift), the
refitted initial velocity and material parameters, and the discovered effect at its refitted
strength, optimized in ``M`` like any other effect. It can be evaluated with
:func:`toolkit.evaluation.evaluate_module` or fitted further with
:func:`toolkit.physics.fit.fit_physics`.

Expressible candidates: the simulator effects (``ground_friction``, ``air_drag``,
``extra_acceleration``; ``wall`` only with the default normal +x, since the module takes effect
*names*, not options), ``internal_damping`` (the registered ``kelvin_voigt`` material wrapping
the base one, :mod:`materials.kelvin_voigt`) and ``plastic_yield`` (``plasticine``). The
others (``timing``, ``stiffness_gradient`` and the controls) change the trainer, not the model,
and give ``None``.
"""

from __future__ import annotations

import logging
from typing import Optional

import torch

from toolkit.discovery.confirm import Refit

__all__ = ["module_with_effect", "EXPRESSIBLE", "config_of", "save_config"]

log = logging.getLogger(__name__)

EXPRESSIBLE = ("ground_friction", "air_drag", "extra_acceleration", "wall", "internal_damping", "plastic_yield")


def module_with_effect(refit: Refit):
    """A new module with ``refit``'s candidate added at its refitted parameters (see the module
    docstring), or ``None`` for a candidate the module cannot express."""
    from toolkit.physics import InversePhysicsModule

    lib, q, name = refit.lib, refit.q, refit.name
    if lib is None or name not in EXPRESSIBLE:
        return None
    m = lib.module
    if name == "wall" and tuple(lib.effects[len(lib._base_effects) + _wall_slot(lib)].options["normal"]) != (1.0, 0.0, 0.0):
        log.info("the discovered wall's normal is not +x; InversePhysicsModule takes effects by name only")
        return None
    phys = lib.physical(q)
    params = dict(phys["params"])
    effects = {e: dict(v) for e, v in phys["effects"].items()}
    material = m.material
    material_options = None  # the base material instance carries its own options
    optimize = list(m.optimized_material)
    if name in ("ground_friction", "air_drag", "extra_acceleration"):
        effects[name] = {k.split(".", 1)[1]: v for k, v in lib.describe(q, name).items()}
    elif name == "wall":
        effects["wall"] = {"strength": float(q[lib.index_of["wall.strength"]]), "offset": lib.wall_offset}
    elif name == "internal_damping":
        from materials.kelvin_voigt import NEGLIGIBLE_DAMPING

        material = "kelvin_voigt"
        material_options = {"base": m.material.registry_name, "base_options": dict(m.material.options)}
        params = {**params, "damping": max(float(q[lib.index_of["internal_damping.eta"]]), NEGLIGIBLE_DAMPING)}
        optimize = optimize + ["damping"]
    elif name == "plastic_yield":
        material, material_options = "plasticine", None
        optimize = sorted(set(optimize) | {"yield_stress"}, key=["E", "nu", "yield_stress"].index)
    hp = dict(m.hparams)
    new = InversePhysicsModule(
        m.input, material=material, material_options=material_options,
        initial_params=params, optimize_params=optimize, effects=effects, curriculum=hp.get("curriculum", "progressive"),
        renderer=m.renderer_name, sim=m.sim_config, v0_init=phys["v0"], material_init="given",  # continues the fit
        optimize_gravity=m.optimize_gravity,
        lambda_image=m.lambda_image, lambda_geometry=m.lambda_geometry, ssim_weight=m.ssim_weight,
        learning_rates=hp.get("learning_rates"), warmup_fraction=m.warmup_fraction, seed=m.seed,
        embedding_neighbours=hp.get("embedding_neighbours", 8), embedding=hp.get("embedding", "idw"),
        gaussian_shape=hp.get("gaussian_shape", "rigid"), body_shift=phys["shift"],
    )
    shift = torch.tensor(phys["shift"], dtype=torch.float32)
    with torch.no_grad():
        new.particle_offset.copy_(m.particle_offset.detach().cpu() + shift)
        new.gaussian_offset.copy_(m.gaussian_offset.detach().cpu() + shift)
        new.log_scales.copy_(m.log_scales.detach().cpu())
        new.quats.copy_(m.quats.detach().cpu())
        new.opacity_logits.copy_(m.opacity_logits.detach().cpu())
        if m.colors is not None:
            new.colors.copy_(m.colors.detach().cpu())
        else:
            new.sh.copy_(m.sh.detach().cpu())
        if m.optimize_gravity and "gravity" in phys:
            new.gravity.copy_(torch.tensor(phys["gravity"], dtype=torch.float32))
    new = new.to(m.device)
    if m.simulator.grid is not None:
        new.simulator.set_grid(m.simulator.grid)
    return new


def _wall_slot(lib) -> int:
    """Position of the active wall among the library's non-base effects."""
    names = [e.registry_name for e in lib.effects[len(lib._base_effects):]]
    return names.index("wall") + lib.wall_index


def config_of(refit: Refit, verdict: str = "") -> Optional[dict]:
    """The discovered model as a run config (the ``run:`` / ``model:`` / ``trainer:`` layout of
    :mod:`toolkit.run_config`), or ``None`` for a candidate a config cannot express
    (one not in :data:`EXPRESSIBLE`).

    ``model:`` carries the material, the refitted material parameters and initial velocity as
    starting values (``initial_params``, ``v0_init``), the discovered effect with its refitted
    strength (``effects``), the base module's curriculum (as a schedule string), simulator settings
and loss weights;
    ``run:`` the fitting cameras and training frames. ``projo4d run --config`` replays the whole
    pipeline with it (stage 0 makes the geometry again), ``projo4d fit --config`` the physics
    stages on a run's ``physics_input.pt``. The refit's rigid shift of the body (``shift``,
    metres) is carried as ``body_shift`` (where it is not zero), so the replayed model starts
    where the refit's did and meets the ground when it did. Not carried: position offsets the
    base fit gave single particles (the geometry comes from the run) and any ``comment``
    (``verdict`` is returned under the key ``_comment`` for the YAML header and removed before
    writing).
    """
    import dataclasses

    new = module_with_effect(refit)
    if new is None:
        return None
    m = refit.lib.module
    est = new.estimate()
    material = new.material.registry_name
    hp = dict(new.hparams)
    from toolkit.mpm import SimConfig

    # the settings that differ from the defaults; frame_dt and particle_volume come from the input,
    # gravity from the scene's world
    default = dataclasses.asdict(SimConfig())
    sim = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(m.sim_config).items()
           if k not in ("frame_dt", "particle_volume", "gravity") and v != default.get(k)}
    effects = {e: {k: float(v) for k, v in vals.items()} for e, vals in est.get("effects", {}).items()}
    model = {"material": material, "initial_params": {k: float(v) for k, v in est["params"].items()},
             "optimize_params": list(new.optimized_material),
             "curriculum": m.curriculum.schedule_string(m.material.registry_name or None),
             "sim": sim, "lambda_geometry": float(m.lambda_geometry), "optimize_gravity": bool(m.optimize_gravity),
             "effects": effects, "v0_init": [float(v) for v in new.v0.detach().cpu().tolist()],
             "ssim_weight": float(m.ssim_weight)}
    shift = [float(v) for v in hp.get("body_shift") or ()]
    if any(shift):
        model["body_shift"] = shift
    if hp.get("material_options"):
        model["material_options"] = dict(hp["material_options"])
    if hp.get("learning_rates"):
        model["learning_rates"] = dict(hp["learning_rates"])
    inp = m.input
    run = {"cameras": [int(c) for c in inp.train_cameras], "n_train": int(inp.n_train)}
    return {"run": run, "model": model, "trainer": {"accelerator": "auto"}, "_comment": verdict}


def save_config(refit: Refit, path, verdict: str = ""):
    """Write :func:`config_of` as YAML to ``path`` (returns the path, or ``None`` when the
    candidate has no config form)."""
    from pathlib import Path

    import yaml

    cfg = config_of(refit, verdict)
    if cfg is None:
        return None
    comment = cfg.pop("_comment", "")
    path = Path(path)
    head = "# discovered model (projo4d discover): replay with\n#   projo4d run --config THIS SCENE_DIR --out RUN_DIR\n" \
           "#   projo4d fit --config THIS --model.input_path RUN_DIR/physics_input.pt\n"
    if comment:
        head += "".join(f"# {line}\n" for line in _wrap(comment))
    from toolkit.atomic import write_text

    return write_text(path, head + yaml.safe_dump(cfg, sort_keys=False))


def _wrap(text: str, width: int = 110) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width)

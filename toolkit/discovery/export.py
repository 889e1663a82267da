"""Turn a discovery refit into an :class:`~toolkit.physics.InversePhysicsModule` with the effect added.

The new module has the base module's input, renderer, simulator settings, curriculum and loss
weights, the base module's Gaussians and particle offsets (plus the refit's rigid shift), the
refitted initial velocity and material parameters, and the discovered effect at its refitted
strength, optimized in ``M`` like any other effect. It can be evaluated with
:func:`toolkit.evaluation.evaluate_module` or fitted further with
:func:`toolkit.physics.fit.fit_physics`.

Expressible candidates: the simulator effects (``ground_friction``, ``air_drag``,
``extra_acceleration``; ``wall`` only with the default normal +x, since the module takes effect
*names*, not options), ``internal_damping`` (an
:class:`~toolkit.discovery.materials.AugmentedMaterial` instance, not registered: such a
module's checkpoint cannot be re-created by name) and ``plastic_yield`` (``plasticine``). The
others (``timing``, ``stiffness_gradient`` and the controls) change the trainer, not the model,
and give ``None``.
"""

from __future__ import annotations

import logging
import torch

from toolkit.discovery.confirm import Refit

__all__ = ["module_with_effect", "EXPRESSIBLE"]

log = logging.getLogger(__name__)

EXPRESSIBLE = ("ground_friction", "air_drag", "extra_acceleration", "wall", "internal_damping", "plastic_yield")


def module_with_effect(refit: Refit):
    """A new module with ``refit``'s candidate added at its refitted parameters (see the module
    docstring), or ``None`` for a candidate the module cannot express."""
    from toolkit.discovery.materials import AugmentedMaterial
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
    optimize = list(m.optimized_material)
    if name in ("ground_friction", "air_drag", "extra_acceleration"):
        effects[name] = {k.split(".", 1)[1]: v for k, v in lib.describe(q, name).items()}
    elif name == "wall":
        effects["wall"] = {"strength": float(q[lib.index_of["wall.strength"]]), "offset": lib.wall_offset}
    elif name == "internal_damping":
        material = AugmentedMaterial(m.material)
        params = {**params, "damping": float(q[lib.index_of["internal_damping.eta"]])}
        optimize = optimize + ["damping"]
    elif name == "plastic_yield":
        material = "plasticine"
        optimize = sorted(set(optimize) | {"yield_stress"}, key=["E", "nu", "yield_stress"].index)
    hp = dict(m.hparams)
    new = InversePhysicsModule(
        m.input, material=material, material_options=hp.get("material_options") if isinstance(material, str) and name != "plastic_yield" else None,
        initial_params=params, optimize_params=optimize, effects=effects, curriculum=hp.get("curriculum", "progressive"),
        renderer=m.renderer_name, sim=m.sim_config, v0_init=phys["v0"], material_init="given",  # continues the fit
        optimize_gravity=m.optimize_gravity,
        lambda_image=m.lambda_image, lambda_geometry=m.lambda_geometry, ssim_weight=m.ssim_weight,
        learning_rates=hp.get("learning_rates"), warmup_fraction=m.warmup_fraction, seed=m.seed,
        embedding_neighbours=hp.get("embedding_neighbours", 8),
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

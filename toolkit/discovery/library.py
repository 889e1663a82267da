"""The fitted base model extended by every candidate of the library, as one parameter vector.

:class:`LibraryModel` wraps a fitted :class:`~toolkit.physics.InversePhysicsModule` (read
only) and re-implements its forward model with extra parameters: the base parameters
``theta`` (initial velocity, the optimized material parameters in their raw space, a rigid
shift of the initial positions, the optimized parameters of effects already in the model) and
the strength of every candidate (zero = absent). One simulator carries every candidate at once
(an :class:`~toolkit.discovery.materials.AugmentedMaterial` and the library's effects, all at
zero strength), so at zero strengths the model moves exactly as the base module, and any subset
of candidates is a subset of free parameters of the same compiled kernels.

Parameters live in a flat ``float64`` vector ``q`` (numpy) with names (:attr:`LibraryModel.names`):

* ``v0.x|y|z`` (m/s; for a body resting on a non-separating ground its component along the
  ground normal is held at zero, group ``held``, as the module holds it), ``mat.<name>`` (raw
  material parameter), ``shift.x|y|z`` (m),
  ``effect<i>.<param>`` (an effect of the base model), ``gravity.x|y|z`` (with
  ``optimize_gravity``);
* ``<candidate>.<strength>`` for every candidate (``camera_pose.c<k>.x|y|z`` per fitted camera).

The forward model is the module's: simulate, move the Gaussians with the particles, render the
cameras, compare with the masked images and with the stage-0 surfaces. Its objectives (the
Gauss-Newton residuals of the ranking and the refits, and the fit's own per-camera image loss)
are in :mod:`toolkit.discovery.library_objectives`, mixed into :class:`LibraryModel`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from renderers.base import Gaussians
from toolkit.discovery.candidates import WALL_NORMALS, Candidate, library
from toolkit.discovery.library_objectives import LibraryObjectives
from toolkit.discovery.materials import AugmentedMaterial
from toolkit.mpm import MPMSimulator
from toolkit.mpm.effects import get_effect
from toolkit.physics.embedding import carry, carry_deformation

__all__ = ["LibraryModel", "ParamInfo", "STIFFNESS_PARAMS"]

#: material parameters scaled by the stiffness-gradient candidate (first group present wins).
STIFFNESS_PARAMS = (("E",), ("mu", "kappa"))

_RAW_STEP = {"log10": 0.02, "tanh": 0.01}


@dataclass(frozen=True)
class ParamInfo:
    """One entry of the library parameter vector.

    Attributes:
        name: ``v0.x``, ``mat.E``, ``ground_friction.mu``, ...
        group: ``base``, the candidate's name, or ``held`` (kept at its value, never refitted).
        step: finite-difference step (and scaling unit), parameter units.
        low, high: bounds.
        units: for reports.
    """

    name: str
    group: str
    step: float
    low: float = -math.inf
    high: float = math.inf
    units: str = ""


class LibraryModel(LibraryObjectives):
    """A fitted module plus every candidate of the library (see the module docstring).

    Args:
        module: a fitted :class:`~toolkit.physics.InversePhysicsModule` (not modified).
        candidates: candidate names (default: the whole library); those not applicable to the
            module's material or effects are dropped (see :attr:`candidates`).
        plastic: build the ``plastic_yield`` variant: the elastic material becomes
            ``plasticine`` and ``plastic_yield.log10_yield_stress`` is a parameter (its initial
            value ``plastic`` in log10 Pa).
        geometry_weight: scale of the geometric residuals in the Gauss-Newton objective;
            ``None`` matches the image/geometry balance of the module's own loss at the
            base point (see :meth:`calibrate_geometry_weight`).
    """

    def __init__(self, module, candidates: Optional[Sequence[str]] = None, plastic: Optional[float] = None,
                 geometry_weight: Optional[float] = None):
        self.module = module
        self.input = module.input
        self.device = module.device
        base_mat = module.material
        base_name = base_mat.registry_name or type(base_mat).__name__
        base_effects = [e.registry_name for e in module.simulator.effects]
        self.candidates: list[Candidate] = [c for c in library(candidates) if c.applicable(base_name, base_effects)]
        if plastic is not None:
            from materials import get_material

            self.base_material = get_material("plasticine")
            self.candidates = [c for c in self.candidates if c.name != "plastic_yield"]
            self.plastic = True
        else:
            self.base_material = base_mat
            self.plastic = False
            self.candidates = [c for c in self.candidates if c.name != "plastic_yield"]
        self.names_of = {c.name for c in self.candidates}
        self.material = AugmentedMaterial(self.base_material)
        # ------------------------------------------------------------ effects
        self._base_effects = list(module.simulator.effects)
        lib_effects = []
        for name in ("ground_friction", "air_drag", "extra_acceleration"):
            if name in self.names_of:
                lib_effects.append(get_effect(name))
        self._wall_count = len(WALL_NORMALS) if "wall" in self.names_of else 0
        for n in WALL_NORMALS[: self._wall_count]:
            lib_effects.append(get_effect("wall", normal=n, mode="separate"))
        self.effects = self._base_effects + lib_effects
        cfg = dataclasses.replace(module.sim_config, deterministic=True)
        self.sim = MPMSimulator(self.material, cfg, effects=self.effects, device=module.simulator.device)
        self.wall_index = 0
        self.wall_offset = 0.0
        self._wall_free = False
        # ------------------------------------------------------------ parameters
        infos: list[ParamInfo] = []
        values: list[float] = []

        def add(name, group, step, value, low=-math.inf, high=math.inf, units=""):
            infos.append(ParamInfo(name, group, float(step), float(low), float(high), units))
            values.append(float(value))

        v0 = module.v0.detach().cpu().double().numpy()
        #: the ground normal when the body starts resting on a non-separating ground: v0 has no
        #: component along it, as in the module (:mod:`toolkit.physics.contact`), and that
        #: component is held (group ``held``) instead of refitted
        self.contact_normal = module.contact_normal
        for i, a in enumerate("xyz"):
            held = self.contact_normal is not None and self.contact_normal[i] != 0.0
            add(f"v0.{a}", "held" if held else "base", 0.02, 0.0 if held else v0[i], units="m/s")
        raw = self._module_raw()
        self._mat_names = [n for n in module.optimized_material]
        for n in self._mat_names:
            p = base_mat.param(n)
            step = _RAW_STEP.get(p.transform, max(0.2 * p.lr, 1e-3))
            add(f"mat.{n}", "base", step, raw[n], units=f"{p.transform} {p.units}".strip())
        for a in "xyz":
            add(f"shift.{a}", "base", 0.002, 0.0, units="m")
        eff_vals = module.effect_params.detach().cpu().double().numpy().tolist()
        self._base_effect_free: list[tuple[int, str]] = []
        k = 0
        for i, e in enumerate(self._base_effects):
            for p in e.params:
                if p.optimize:
                    add(f"effect{i}.{e.name}.{p.name}", "base", max(0.2 * p.lr, 1e-3), eff_vals[k], p.low, p.high, p.units)
                    self._base_effect_free.append((k, f"effect{i}.{e.name}.{p.name}"))
                k += 1
        self._base_effect_values = eff_vals
        if module.optimize_gravity:
            g = module.gravity.detach().cpu().double().numpy()
            for i, a in enumerate("xyz"):
                add(f"gravity.{a}", "base", 0.02, g[i], units="m/s^2")
        self.mref = self._reference_modulus()
        self.n_train_cams = len(self.input.train_cameras)
        for c in self.candidates:
            if c.name == "camera_pose":
                for name in c.parameter_names(self.n_train_cams):
                    add(name, c.name, 0.002, 0.0, -0.2, 0.2, "m")
                continue
            for s, name in zip(c.strengths, c.parameter_names()):
                step, high = s.step, s.high
                if c.name == "internal_damping":
                    step = 0.01 * self.mref * cfg.frame_dt
                    high = self.damping_limit()
                add(name, c.name, step, 0.0, s.low, high, s.units)
        if self.plastic:
            add("plastic_yield.log10_yield_stress", "plastic_yield", 0.05, float(plastic), 0.0, 12.0, "log10 Pa")
        self.infos = infos
        self.names = [p.name for p in infos]
        self.index_of = {n: i for i, n in enumerate(self.names)}
        self.q0 = np.asarray(values, dtype=np.float64)
        self.steps = np.array([p.step for p in infos])
        self.low = np.array([p.low for p in infos])
        self.high = np.array([p.high for p in infos])
        self.base_names = [p.name for p in infos if p.group == "base"]
        # ------------------------------------------------------------ constants
        parts = module.particles0.detach()
        self._centre = parts.mean(0)
        self._half = float(((parts.max(0).values - parts.min(0).values) / 2).max().clamp_min(1e-6))
        self._stiff_cols = self._stiffness_columns()
        self._assign: Optional[list] = None
        self.geometry_weight = geometry_weight
        #: the frames the objectives fit (default: every training frame; the confirmation holds
        #: the last ones out)
        self.fit_frames: list[int] = list(range(self.input.n_train))
        grid = module.simulator.grid
        if grid is None:  # a module that never simulated: size its grid for the whole sequence
            module.predict_trajectory()
            grid = module.simulator.grid
        self.sim.set_grid(grid)

    # ------------------------------------------------------------------ parameter helpers
    def _module_raw(self) -> dict[str, float]:
        m = self.module
        out = {}
        for i, n in enumerate(m.material.param_names):
            t = m.material_raw[n] if n in m.material_raw else m.material_raw_fixed[i]
            out[n] = float(t.detach().cpu())
        return out

    def _reference_modulus(self) -> float:
        est = self.module.estimate()["params"]
        for n in ("E", "kappa", "mu"):
            if n in est:
                return float(est[n])
        return 1e4

    def damping_limit(self) -> float:
        """Largest stable Kelvin-Voigt viscosity for the explicit update, Pa s:
        ``0.5 rho dx^2 / (6 dt)`` (half the diffusion limit)."""
        cfg = self.module.sim_config
        return 0.5 * cfg.density * cfg.dx**2 / (6.0 * cfg.frame_dt / cfg.substeps)

    def _stiffness_columns(self) -> list[int]:
        names = self.material.param_names
        for group in STIFFNESS_PARAMS:
            cols = [names.index(n) for n in group if n in names]
            if cols:
                return cols
        return []

    def candidate(self, name: str) -> Candidate:
        for c in self.candidates:
            if c.name == name:
                return c
        raise KeyError(f"candidate {name!r} is not in this library model ({sorted(self.names_of)})")

    def params_of(self, group: str) -> list[str]:
        """Parameter names of a candidate (or ``"base"``)."""
        return [p.name for p in self.infos if p.group == group]

    def idx(self, names: Sequence[str]) -> list[int]:
        return [self.index_of[n] for n in names]

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.low, self.high)

    def set_wall(self, index: int, offset: float) -> None:
        """Choose the wall (normal ``WALL_NORMALS[index]``) and its offset (m) the ``wall.strength``
        parameter acts on."""
        if not 0 <= index < self._wall_count:
            raise ValueError(f"wall index must be in [0, {self._wall_count}), got {index}")
        self.wall_index, self.wall_offset = int(index), float(offset)

    def describe(self, q: np.ndarray, group: str) -> dict[str, float]:
        """``{parameter: value}`` of one candidate (or ``"base"``) at ``q`` (physical units)."""
        return {n: float(q[self.index_of[n]]) for n in self.params_of(group)}

    # ------------------------------------------------------------------ the forward model
    def _t(self, q) -> torch.Tensor:
        if isinstance(q, torch.Tensor):
            return q
        return torch.as_tensor(np.asarray(q, dtype=np.float64))

    def _get(self, qt: torch.Tensor, name: str, default: float = 0.0):
        i = self.index_of.get(name)
        if i is None:
            return torch.tensor(default, dtype=torch.float64)
        return qt[i]

    def _v0(self, qt: torch.Tensor) -> torch.Tensor:
        """(3,) initial velocity (m/s, float32 on the device), without its component along the
        ground normal for a body resting on a non-separating ground (the module's rule)."""
        v0 = torch.stack([qt[self.index_of[f"v0.{a}"]] for a in "xyz"]).float().to(self.device)
        if self.contact_normal is not None:
            n = torch.tensor(self.contact_normal, dtype=v0.dtype, device=v0.device)
            v0 = v0 - (v0 @ n) * n
        return v0

    def material_tensor(self, qt: torch.Tensor) -> torch.Tensor:
        """(P,) or (N, P) physical parameters of the augmented material, float32 on the device."""
        m = self.module
        raw_all = self._module_raw()
        base = self.base_material
        raws = []
        for p in base.params:
            if f"mat.{p.name}" in self.index_of:
                raws.append(qt[self.index_of[f"mat.{p.name}"]])
            elif p.name in raw_all:
                raws.append(torch.tensor(raw_all[p.name], dtype=torch.float64))
            else:  # plasticine's yield stress
                raws.append(torch.tensor(12.0, dtype=torch.float64))
        phys = base.to_physical(torch.stack(raws).float()).double()
        if self.plastic:
            k = base.param_names.index("yield_stress")
            phys = torch.cat([phys[:k], (10.0 ** self._get(qt, "plastic_yield.log10_yield_stress")).reshape(1), phys[k + 1:]])
        extras = torch.stack([self._get(qt, "internal_damping.eta"), self._get(qt, "density.log_ratio")])
        params = torch.cat([phys, extras]).float().to(self.device)
        names = ["stiffness_gradient.gx", "stiffness_gradient.gy", "stiffness_gradient.gz"]
        if "stiffness_gradient" in self.names_of and self._stiff_cols:
            g = torch.stack([self._get(qt, n) for n in names]).float().to(self.device)
            if qt.requires_grad or bool((g != 0).any()):
                rel = (m.particles0 - self._centre) / self._half  # (N, 3)
                factor = torch.pow(10.0, rel @ g)  # (N,)
                rows = params.unsqueeze(0).repeat(rel.shape[0], 1)
                scale = torch.ones_like(rows)
                scale[:, self._stiff_cols] = factor.unsqueeze(1)
                return rows * scale
        return params

    def effect_tensor(self, qt: torch.Tensor) -> torch.Tensor:
        """(E,) flat effect parameters, float32 on the device."""
        vals: list[torch.Tensor] = []
        k = 0
        free = dict(self._base_effect_free)
        for e in self._base_effects:
            for _ in e.params:
                vals.append(qt[self.index_of[free[k]]] if k in free else torch.tensor(self._base_effect_values[k], dtype=torch.float64))
                k += 1
        z = torch.tensor(0.0, dtype=torch.float64)
        if "ground_friction" in self.names_of:
            vals.append(self._get(qt, "ground_friction.mu"))
        if "air_drag" in self.names_of:
            vals += [self._get(qt, "air_drag.linear"), self._get(qt, "air_drag.quadratic")]
        if "extra_acceleration" in self.names_of:
            vals += [self._get(qt, f"extra_acceleration.{a}") for a in ("ax", "ay", "az")]
        for w in range(self._wall_count):
            s = self._get(qt, "wall.strength") if w == self.wall_index else z
            vals += [s, torch.tensor(self.wall_offset if w == self.wall_index else -1e3, dtype=torch.float64)]
        if not vals:
            return torch.zeros(0, device=self.device)
        return torch.stack(vals).float().to(self.device)

    def frame_times(self, qt: torch.Tensor, frames: Sequence[int]) -> Optional[torch.Tensor]:
        """Simulation times (in frames) of the observed ``frames``, or ``None`` when the timing
        candidate is absent (observed frame k = simulation frame k)."""
        if "timing" not in self.names_of:
            return None
        off, rate = self._get(qt, "timing.offset"), self._get(qt, "timing.rate")
        if not qt.requires_grad and float(off) == 0.0 and float(rate) == 0.0:
            return None
        k = torch.as_tensor(list(frames), dtype=torch.float64)
        return k * (1.0 + rate) + off

    def gravity(self, q) -> torch.Tensor:
        """Gravity (3,) in m/s^2 at ``q``: its parameters when the base fits it, else the module's."""
        if self.module.optimize_gravity:
            qt = self._t(q)
            return torch.stack([qt[self.index_of[f"gravity.{a}"]] for a in "xyz"]).float().to(self.device)
        return self.module.gravity.detach()

    def trajectory(self, q, frames: Sequence[int], grad: bool = False):
        """Particle positions at the observed ``frames``.

        Returns:
            ``(x0 (N, 3), positions (F, N, 3))``, float32 on the device.
        """
        qt = self._t(q)
        m = self.module
        shift = torch.stack([self._get(qt, f"shift.{a}") for a in "xyz"]).float().to(self.device)
        x0 = (m.particles0 + m.particle_offset.detach()) + shift
        v0 = self._v0(qt)
        gravity = self.gravity(qt)
        params = self.material_tensor(qt)
        effects = self.effect_tensor(qt)
        times = self.frame_times(qt, frames)
        n_sim = max(frames) if times is None else max(int(math.floor(float(times.detach().max()))) + 1, 1)
        n_sim = max(n_sim, 0)
        if grad:
            out = self.sim.simulate(x0, v0, params, gravity=gravity, effect_params=effects, n_frames=n_sim)
        else:
            with torch.no_grad():
                out = self.sim.rollout(x0, v0, params, gravity=gravity, effect_params=effects, n_frames=n_sim)
        if times is None:
            return x0, out.positions[list(frames)]
        return x0, _hermite(out.positions, out.velocities, times.to(self.device).float(), self.sim.config.frame_dt)

    def gaussian_means(self, q, x0: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """(F, G, 3) Gaussian means carried by ``positions`` (F, N, 3) simulated from ``x0``."""
        qt = self._t(q)
        m = self.module
        shift = torch.stack([self._get(qt, f"shift.{a}") for a in "xyz"]).float().to(self.device)
        means0 = m.gaussian_means0 + m.gaussian_offset.detach() + shift
        return carry(means0, positions, x0, m.embed_index, m.embed_weight)

    def _camera_shift(self, qt: torch.Tensor, cam: int) -> Optional[torch.Tensor]:
        if "camera_pose" not in self.names_of or cam not in self.input.train_cameras:
            return None
        k = list(self.input.train_cameras).index(cam)
        s = torch.stack([self._get(qt, f"camera_pose.c{k}.{a}") for a in "xyz"])
        if not qt.requires_grad and not bool((s != 0).any()):
            return None
        return s.float().to(self.device)

    def deformations(self, x0: torch.Tensor, positions: torch.Tensor) -> Optional[torch.Tensor]:
        """(F, G, 3, 3) the Gaussians' deformations at ``positions`` (F, N, 3) simulated from
        ``x0``, or None when the module's Gaussians keep their shapes (``gaussian_shape``)."""
        m = self.module
        if not m.deform_index.numel():
            return None
        return carry_deformation(positions, x0, m.deform_index, m.deform_gradient)

    def render(self, q, means: torch.Tensor, cams: Sequence[int], deformations: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(F, C, H, W, 3) renders of the Gaussians at ``means`` (F, G, 3), shaped by
        ``deformations`` (F, G, 3, 3) when given, for ``cams``."""
        qt = self._t(q)
        m = self.module
        shifts = [self._camera_shift(qt, c) for c in cams]
        out = []
        for k, mf in enumerate(means):
            g = Gaussians(means=mf, log_scales=m.log_scales.detach(), quats=m.quats.detach(),
                          opacity_logits=m.opacity_logits.detach(),
                          colors=None if m.colors is None else m.colors.detach(), sh=None if m.sh is None else m.sh.detach(),
                          deformation=None if deformations is None else deformations[k])
            if all(s is None for s in shifts):
                out.append(m.renderer(g, self.input.cameras[list(cams)].to(self.device)).rgb)
            else:
                per = []
                for c, s in zip(cams, shifts):
                    gc = g if s is None else g.replace(means=mf + s)
                    per.append(m.renderer(gc, self.input.cameras[[c]].to(self.device)).rgb[0])
                out.append(torch.stack(per))
        return torch.stack(out)

    def observed_images(self, frames: Sequence[int], cams: Sequence[int]) -> torch.Tensor:
        """(F, C, H, W, 3) masked observed images in [0, 1]."""
        imgs = self.module.images[list(cams)][:, list(frames)].float() / 255.0  # (C, F, H, W, 3)
        masks = self.module.masks[list(cams)][:, list(frames)].float().unsqueeze(-1) / 255.0
        return (imgs * masks).transpose(0, 1).to(self.device)

    def physical(self, q) -> dict:
        """The base parameters at ``q`` in physical units: ``params`` (material), ``v0`` (m/s),
        ``shift`` (m), ``effects`` (effects already in the model) and ``gravity``."""
        qt = self._t(q)
        with torch.no_grad():
            mat = self.material_tensor(qt)
            if mat.ndim == 2:
                mat = mat[0]
            vals = mat.detach().cpu().double().tolist()
        params = dict(zip(self.base_material.param_names, vals[: len(self.base_material.params)]))
        if self.plastic:
            params["yield_stress"] = float(10 ** q[self.index_of["plastic_yield.log10_yield_stress"]])
        out = {"params": params, "v0": self._v0(qt).detach().cpu().double().tolist(),
               "shift": [float(q[self.index_of[f"shift.{a}"]]) for a in "xyz"]}
        eff = self.effect_tensor(qt).detach().cpu().tolist()
        base_eff: dict = {}
        k = 0
        for e in self._base_effects:
            base_eff[e.name] = {p.name: eff[k + j] for j, p in enumerate(e.params)}
            k += len(e.params)
        out["effects"] = base_eff
        if self.module.optimize_gravity:
            out["gravity"] = [float(q[self.index_of[f"gravity.{a}"]]) for a in "xyz"]
        return out

    @torch.no_grad()
    def predict(self, q, n_frames: Optional[int] = None) -> dict[str, torch.Tensor]:
        """``positions`` (T, N, 3) and ``means`` (T, G, 3) at every observed frame (and
        ``deformations`` (T, G, 3, 3) when the module's Gaussians deform)."""
        T = n_frames or self.input.n_frames
        x0, pos = self.trajectory(q, list(range(T)))
        out = {"positions": pos, "means": self.gaussian_means(q, x0, pos)}
        deform = self.deformations(x0, pos)
        if deform is not None:
            out["deformations"] = deform
        return out


def _hermite(pos: torch.Tensor, vel: torch.Tensor, t: torch.Tensor, frame_dt: float) -> torch.Tensor:
    """Cubic Hermite interpolation of a trajectory at fractional frames ``t`` (K,).

    Args:
        pos, vel: (S + 1, N, 3) positions (m) and velocities (m/s) at integer frames.
        t: (K,) times in frames; outside ``[0, S]`` the end cubic is extrapolated.
        frame_dt: seconds per frame.
    """
    S = pos.shape[0] - 1
    if S < 1:
        return pos[:1].expand(len(t), -1, -1) + (t.reshape(-1, 1, 1) * frame_dt) * vel[:1]
    i = t.detach().floor().clamp(0, S - 1).long()
    u = (t - i.to(t.dtype)).reshape(-1, 1, 1)
    u2, u3 = u * u, u * u * u
    h00, h10 = 2 * u3 - 3 * u2 + 1, u3 - 2 * u2 + u
    h01, h11 = -2 * u3 + 3 * u2, u3 - u2
    return h00 * pos[i] + h10 * frame_dt * vel[i] + h01 * pos[i + 1] + h11 * frame_dt * vel[i + 1]

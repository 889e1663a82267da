"""The inverse-physics LightningModule: Gaussians + particles + v0 + material, driven by a strategy.

Parameter groups (DESIGN section 6) and what they hold here:

* ``X``: offsets of the simulation particles' initial positions (N, 3) and of the Gaussians'
  frame-0 means (G, 3), metres;
* ``A``: Gaussian appearance: colours (or SH), opacity logits, log-scales, quaternions;
* ``S``: the initial velocity v0 (3,) m/s (and gravity when ``optimize_gravity``);
* ``M``: the material's optimized parameters in their raw space (log10 E, tanh-bounded nu, ...)
  and the parameters of any added effects.

Each iteration the strategy names the active groups, the frame window and the batch; the module
samples cameras and frames (deterministically from the seed and the iteration, so a resumed run
sees the same batches), simulates up to the last sampled frame, moves the Gaussians with the
particles (:mod:`toolkit.physics.embedding`), renders the sampled cameras and minimizes

    lambda_img * sum_cameras L_img + lambda_geo * chamfer(simulated surface, stage-0 surface),

averaged over the sampled frames, with ``L_img = (1 - 0.2) L1 + 0.2 (1 - SSIM)`` on the masked
image (object on black) and ``lambda_img = 1 / |C|``. One Adam optimizer per group is created
once; only the active groups step. Learning rates follow a cosine decay with 10 % warm-up over
the iterations in which the group is active, a pure function of the iteration, so resuming needs
no scheduler state. The module keeps its own iteration counter (``curriculum_step``, saved in
checkpoints): under manual optimization Lightning's ``global_step`` counts optimizer steps.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Optional, Union

import pytorch_lightning as pl
import torch
from torch import nn

from materials import Material, get_material
from renderers import RENDERERS, get_renderer
from strategies import Strategy, get_strategy
from strategies.base import GROUPS
from toolkit.data.exclusion import EXCLUSION_META_KEY
from toolkit.mpm import MPMSimulator, SimConfig
from toolkit.physics.checkpoint_state import CheckpointStateMixin
from toolkit.physics.contact import ground_contact_normal, project_off_ground
from toolkit.physics.embedding import GAUSSIAN_SHAPES, embed, local_deformation
from toolkit.physics.inputs import PhysicsInput
from toolkit.physics.objective import FitObjectiveMixin
from toolkit.physics.prediction import PredictionMixin
from toolkit.physics.starting_state import (StepStream, cosine_with_warmup, free_flight_curriculum, initial_v0,
                                             rigid_shift, surface_particles, velocity_start_curriculum, warn_if_zero_start_is_held)
from toolkit.physics.time_scale import report_time_scale
from toolkit.run_config import MATERIAL_INITS

__all__ = ["InversePhysicsModule", "DEFAULT_LEARNING_RATES"]

log = logging.getLogger(__name__)

#: Adam learning rates of the non-material parameters (material ones come from MaterialParam.lr; the
#: velocity's default is replaced by :func:`toolkit.physics.rates.velocity_rate` of the observed motion).
DEFAULT_LEARNING_RATES = {
    "positions": 2e-4,  # m, X (3DGS position lr at a ~1 m scene)
    "colors": 2.5e-3,
    "opacity": 0.05,
    "scales": 5e-3,
    "rotations": 1e-3,
    "velocity": 2e-2,  # m/s (DESIGN: 1e-2 .. 5e-2)
    "gravity": 1e-2,
}


class InversePhysicsModule(FitObjectiveMixin, PredictionMixin, CheckpointStateMixin, pl.LightningModule):
    """Fit positions, appearance, initial velocity and material to multi-view video.

    Args:
        input_path: a ``physics_input.pt`` written after stage 0 (a :class:`PhysicsInput` object is
            accepted too, from Python).
        material: registered material name or a :class:`~materials.Material`.
        material_options: options of the material (e.g. ``{"yield_rule": "pacnerf"}``).
        initial_params: starting guesses (physical units); default the material's defaults.
        optimize_params: material parameters to optimize (default: those the material marks).
        effects: effects to add, ``{name: {param: initial value}}``; their parameters join ``M``.
        curriculum: a strategy name (``progressive``, ``sequential``, ``joint``, ``cyclic``), a
            schedule string (``"XAS:100@3,XASM:150"``) or a :class:`~strategies.Strategy`. (Not
            Lightning's ``Trainer(strategy=...)``, which is about distributed training.)
        renderer: registered renderer name, or ``"auto"`` (``warp`` if registered, else ``torch``).
        sim: simulator settings (``SimConfig``); ``frame_dt`` is taken from the input's times.
        v0_init: initial guess of v0 (m/s): a list of 3 numbers wins; ``None`` or ``"auto"``
            (default) estimates it from the stage-0 surfaces by a ballistic fit of the centroid over
            the frames before ground contact (:mod:`toolkit.physics.initial_velocity`; zero when too
            few such frames); ``"zero"`` starts from zero. The estimate is kept in ``v0_estimate``.
        material_init: ``"search"`` (default): at the first iteration that optimizes ``M``, a
            coarse global search of the optimized material parameters
            (:mod:`toolkit.physics.coarse_search`) picks where gradient descent starts (the given or
            default guess is one candidate; the record is kept in ``material_search`` and written to
            ``material_search.json`` in the trainer's folder); ``"search_joint"``: the same search
            with the first and the yield parameter swept on one grid
            (``coarse_search(joint_yield=True)``; the same as ``"search"`` for a material without a
            yield parameter); ``"given"``: start at ``initial_params`` / the material's defaults.
        optimize_gravity: put gravity in ``S`` too.
        lambda_image: weight of the image term per camera; default ``1 / |C|``.
        lambda_geometry: weight of the geometric term.
        ssim_weight: lambda of ``(1 - lambda) L1 + lambda (1 - SSIM)``.
        learning_rates: overrides of :data:`DEFAULT_LEARNING_RATES` and of material parameters'
            rates (keys: ``positions``, ``colors``, ..., or a material parameter name). By default
            v0's rate follows the observed motion and material rates follow their transforms
            (:mod:`toolkit.physics.rates`), so no scene needs hand-set rates.
        warmup_fraction: warm-up part of each group's cosine schedule.
        seed: seed of the batch sampling.
        embedding_neighbours: particles each Gaussian follows (``"affine"``: at least 24).
        embedding: how Gaussians follow them: ``"idw"`` (inverse-distance average of the
            displacements, default) or ``"affine"`` (exact for any locally affine motion); see
            :mod:`toolkit.physics.embedding`.
        gaussian_shape: ``"deformed"`` (default: each Gaussian's covariance follows the material
            around it, ``A Sigma A^T`` with ``A`` the local deformation gradient of its neighbouring
            particles since frame 0, :func:`~toolkit.physics.embedding.carry_deformation`, so a body
            that spreads or stretches keeps covering what it covers in the images instead of
            breaking into rigid blobs) or ``"rigid"`` (each keeps its stage-0 shape while it moves;
            the default before 2026-11-26, and what runs saved before then replay with).
        fit_ranges: where the fit keeps each optimized material parameter
            (:meth:`materials.base.Material.fit_ranges`): ``None`` (default) each parameter's own
            fit range (Poisson's ratio in [0, 0.49], inside its valid [-0.99, 0.49]), ``"valid"``
            the valid ranges (what runs saved before 2026-11-28 replay with), or
            ``{name: [low, high]}`` for the named parameters. Enforced by projection after each
            optimizer step; a start outside it is an error.
        body_shift: a rigid translation ``[dx, dy, dz]`` (m, the input's world frame) of the
            starting body: the particles' and Gaussians' position offsets (``X``) start at it
            instead of zero. A discovered model carries its refit's shift this way
            (:mod:`toolkit.discovery.export`); default none.
        uncertainty_options: keyword options of the uncertainty computed after the fit
            (:func:`~toolkit.physics.uncertainty.estimate_uncertainty`: ``level``, ``prior_step``,
            ``grid_term``, ``fine_guard``), e.g. ``{"fine_guard": True}``; options given to
            :meth:`uncertainty` win. Checked here, before any work.
    """

    def __init__(
        self,
        input_path: str,
        material: Union[str, Material] = "neo_hookean",
        material_options: Optional[dict] = None,
        initial_params: Optional[dict] = None,
        optimize_params: Optional[list[str]] = None,
        effects: Optional[dict[str, dict]] = None,
        curriculum: Union[str, Strategy] = "progressive",
        renderer: str = "auto",
        sim: Optional[SimConfig] = None,
        v0_init: Optional[Union[list[float], str]] = None,
        material_init: str = "search",
        optimize_gravity: bool = False,
        lambda_image: Optional[float] = None,
        lambda_geometry: float = 1.0,
        ssim_weight: float = 0.2,
        learning_rates: Optional[dict[str, float]] = None,
        warmup_fraction: float = 0.1,
        seed: int = 0,
        embedding_neighbours: int = 8,
        embedding: str = "idw",
        gaussian_shape: str = "deformed",
        fit_ranges: Optional[Union[dict, str]] = None,
        body_shift: Optional[list[float]] = None,
        uncertainty_options: Optional[dict] = None,
    ):
        super().__init__()
        self.automatic_optimization = False
        inp = input_path if isinstance(input_path, PhysicsInput) else PhysicsInput.load(input_path)
        # checkpoints hold plain data only (Lightning loads them with weights_only=True)
        self.save_hyperparameters(ignore=["input_path", "material", "curriculum", "sim"])
        self.input = inp
        self.material = get_material(material, **(material_options or {})) if isinstance(material, str) else material
        self.curriculum = get_strategy(curriculum)
        self.stages = self.curriculum.stages(self.material.registry_name or None)
        self.total_iterations = self.curriculum.total_iterations(self.material.registry_name or None)
        self.renderer_name = ("warp" if "warp" in RENDERERS else "torch") if renderer == "auto" else renderer
        self.renderer = get_renderer(self.renderer_name)
        cfg = sim if sim is not None else SimConfig(auto_dt_halving=True)
        if isinstance(cfg, dict):
            cfg = SimConfig(**cfg)
        cfg.frame_dt = inp.frame_dt
        cfg.particle_volume = float(inp.particle_volume)
        self.sim_config = cfg
        self.hparams.update(
            input_path=None if isinstance(input_path, PhysicsInput) else str(input_path),
            material=self.material.registry_name or type(self.material).__name__,
            material_options=dict(self.material.options),
            curriculum=self.curriculum.schedule_string(self.material.registry_name or None),
            sim=cfg.to_dict(),
        )
        from toolkit.physics.uncertainty import check_uncertainty_options

        #: default keyword options of :meth:`uncertainty`
        self.uncertainty_options = check_uncertainty_options(uncertainty_options)
        self.effect_init = dict(effects or {})
        if material_init not in MATERIAL_INITS:
            raise ValueError(f"material_init must be one of {', '.join(map(repr, MATERIAL_INITS))}, got {material_init!r}")
        self.material_init = material_init
        #: the coarse search's record (``toolkit.physics.coarse_search``), None until it ran
        self.material_search: Optional[dict] = None
        self.optimize_gravity = optimize_gravity
        self.lambda_image = lambda_image if lambda_image is not None else 1.0 / len(inp.train_cameras)
        self.lambda_geometry = lambda_geometry
        self.ssim_weight = ssim_weight
        from toolkit.physics.rates import velocity_rate

        # v0's rate scales with the observed motion (toolkit.physics.rates); a user's rates win
        self.lrs = {**DEFAULT_LEARNING_RATES, "velocity": velocity_rate(inp.surfaces, inp.frame_dt, inp.n_train),
                    **(learning_rates or {})}
        self.warmup_fraction = warmup_fraction
        self.seed = seed
        self.curriculum_step = 0
        self._sim: Optional[MPMSimulator] = None
        self._restored_grid: Optional[dict] = None
        self._restored_substeps_floor = 0
        #: substeps per frame of the latest rollout (logged as ``sim/substeps``; a change is logged)
        self.substeps: Optional[int] = None
        self._cached_positions: Optional[torch.Tensor] = None
        self.history: list[dict] = []

        # ---------------------------------------------------------- X: positions
        self.register_buffer("particles0", inp.particles.float().clone())
        self.register_buffer("gaussian_means0", inp.gaussians.means.float().clone())
        shift = rigid_shift(body_shift)
        self.particle_offset = nn.Parameter(torch.zeros_like(self.particles0) + shift)
        self.gaussian_offset = nn.Parameter(torch.zeros_like(self.gaussian_means0) + shift)
        index, weight = embed(self.gaussian_means0, self.particles0, k=embedding_neighbours, mode=embedding)
        self.register_buffer("embed_index", index)
        self.register_buffer("embed_weight", weight)
        self.register_buffer("deform_index", torch.zeros(0, 0, dtype=torch.int64))
        self.register_buffer("deform_gradient", torch.zeros(0, 0, 3))
        self.set_gaussian_shape(gaussian_shape)
        # simulated particles compared with the stage-0 surface: those near it at frame 0
        self.register_buffer("surface_index", surface_particles(inp))
        # ---------------------------------------------------------- A: appearance
        g = inp.gaussians
        self.log_scales = nn.Parameter(g.log_scales.float().clone())
        self.quats = nn.Parameter(g.quats.float().clone())
        self.opacity_logits = nn.Parameter(g.opacity_logits.float().clone())
        if g.sh is not None:
            self.sh = nn.Parameter(g.sh.float().clone())
            self.colors = None
        else:
            self.colors = nn.Parameter(g.colors.float().clone())
            self.sh = None
        # ---------------------------------------------------------- S: initial state
        #: the stage-0 estimate of v0 (``V0Estimate.to_dict()``), None when not estimated or not estimable
        start = initial_v0(v0_init, inp, cfg)
        if start.hparam is not None:
            self.hparams["v0_init"] = start.hparam[0]  # None or 3 numbers (a resume re-estimates the same)
        #: the stage-0 ballistic estimate v0 started from (``None`` when it did not)
        self.v0_estimate: Optional[dict] = start.estimate
        #: does the body fall at g in the folder's times and units (``TimeScaleCheck.to_dict()``; None: too few frames)
        self.time_scale: Optional[dict] = report_time_scale(inp, cfg)
        # a stage window "@ff" becomes this clip's frames before ground contact (a resume sets the same)
        self.curriculum = free_flight_curriculum(self.curriculum, self.material.registry_name or None, self.v0_estimate, inp, cfg)
        #: where v0 started, and how a ``[S]`` stage resolved (``"held"``/``"fitted"``; None without one)
        self.curriculum, self.v0_origin = velocity_start_curriculum(self.curriculum, self.material.registry_name or None, start)
        self.stages = self.curriculum.stages(self.material.registry_name or None)
        warn_if_zero_start_is_held(start, self.stages)
        self.v0 = nn.Parameter(torch.tensor(start.v0, dtype=torch.float32))
        # resting on a sticky/slip ground at frame 0: v0 has no normal component (issue #24, toolkit.physics.contact)
        self.contact_normal = ground_contact_normal(inp.particles.float() + shift, cfg, inp.surfaces)
        project_off_ground(self.v0.data, self.contact_normal)
        #: where v0 started (m/s): the uncertainty's prior is centred here
        self.v0_start: list[float] = self.v0.detach().tolist()
        #: the Laplace posterior of the last :meth:`uncertainty` call (a dict; kept in checkpoints)
        self.uncertainty_result: Optional[dict] = None
        gravity = torch.tensor(list(cfg.gravity), dtype=torch.float32)
        if optimize_gravity:
            self.gravity = nn.Parameter(gravity)
        else:
            self.register_buffer("gravity", gravity)
        # ---------------------------------------------------------- M: material and effects
        start = self.material.complete(initial_params)
        self.material.validate(start)
        names = self.material.param_names
        wanted = optimize_params if optimize_params is not None else [p.name for p in self.material.params if p.optimize]
        unknown = set(wanted) - set(names)
        if unknown:
            raise ValueError(f"optimize_params {sorted(unknown)} are not parameters of {self.material.name!r} ({names})")
        self.optimized_material = [n for n in names if n in wanted]
        self.fit_bounds = self.material.fit_ranges(fit_ranges)
        for n in self.optimized_material:
            lo, hi = self.fit_bounds[n]
            if not lo <= start[n] <= hi:
                raise ValueError(f"initial {n} = {start[n]:g} is outside its fit range [{lo:g}, {hi:g}] "
                                 f"({self.material.name}); start inside it or widen it with fit_ranges: "
                                 f"{{{n}: [low, high]}} (the valid range is [{self.material.param(n).low:g}, "
                                 f"{self.material.param(n).high:g}])")
        raw = self.material.to_raw(start)
        self.material_raw = nn.ParameterDict({n: nn.Parameter(raw[i].clone()) for i, n in enumerate(names) if n in wanted})
        self.register_buffer("material_raw_fixed", raw.clone())
        probe = MPMSimulator(self.material, cfg, effects=list(self.effect_init), device="cpu")
        self.effect_names = probe.effect_param_names
        self.effect_params = nn.Parameter(probe.pack_effects(self.effect_init).float())
        self._effect_specs = [(e, p) for e in probe.effects for p in e.params]

        # the images come from the input file, not from checkpoints
        self.register_buffer("images", inp.images, persistent=False)
        self.register_buffer("masks", inp.masks, persistent=False)
        keep = (inp.meta or {}).get(EXCLUSION_META_KEY)  # PAC-NeRF's loss-exclusion pixels (frame -2 masks)
        self.register_buffer("exclusion_keep", keep if keep is not None else torch.empty(0, dtype=torch.uint8), persistent=False)
        self._ground_truth = inp.ground_truth or {}

    # ------------------------------------------------------------------ helpers
    @property
    def simulator(self) -> MPMSimulator:
        if self._sim is None or self._sim.device != str(_warp_device(self.device)):
            self._sim = MPMSimulator(self.material, self.sim_config, effects=list(self.effect_init), device=_warp_device(self.device))
            if self._restored_grid is not None:
                # the grid origin enters (x - origin) / dx: a resumed run must use the same one
                from toolkit.mpm.simulator import GridSpec

                g = self._restored_grid
                self._sim.set_grid(GridSpec(tuple(g["origin"]), tuple(g["dims"]), float(g["dx"])))
            # a dt halving is kept for the rest of the fit, across resumes too
            self._sim.substeps_floor = max(self._sim.substeps_floor, self._restored_substeps_floor)
        return self._sim

    def material_params(self) -> torch.Tensor:
        """(P,) physical material parameters, differentiable for the optimized ones."""
        raws = [self.material_raw[n] if n in self.material_raw else self.material_raw_fixed[i]
                for i, n in enumerate(self.material.param_names)]
        return self.material.to_physical(torch.stack(raws))

    def project_material_bounds(self) -> None:
        """Clamp the optimized material parameters into their fit ranges (``fit_ranges``; the
        valid range ``[low, high]`` unless narrower): an optimizer step past a bound (a friction
        angle below 0 degrees) would otherwise stop the next rollout with a MaterialError, and a
        Poisson's ratio below 0 is kept at 0 by default. ``log10`` and ``tanh`` parameters
        cannot leave their valid range; only a narrower fit range clamps them."""
        with torch.no_grad():
            for n, raw in self.material_raw.items():
                p = self.material.param(n)
                rlo, rhi = p.raw_fit_bounds(self.fit_bounds.get(n, (p.low, p.high)))
                if math.isfinite(rlo) or math.isfinite(rhi):
                    raw.clamp_(min=rlo, max=rhi)

    def estimate(self) -> dict:
        """Current estimate: material parameters (physical), v0, gravity, effects."""
        with torch.no_grad():
            params = dict(zip(self.material.param_names, self.material_params().cpu().tolist()))
            eff = self.simulator.unpack_effects(self.effect_params) if self.effect_names else {}
        return {"material": self.material.registry_name, "params": params, "v0": self.v0.detach().cpu().tolist(),
                "gravity": self.gravity.detach().cpu().tolist(), "effects": eff}

    def uncertainty(self, **options) -> dict:
        """90 % intervals and identifiability labels of the estimate (:mod:`toolkit.physics.uncertainty`);
        ``options`` go to :func:`~toolkit.physics.uncertainty.estimate_uncertainty`, over the
        module's ``uncertainty_options``. Cached: the result is kept in :attr:`uncertainty_result`
        and in checkpoints."""
        from toolkit.physics.uncertainty import estimate_uncertainty

        self.uncertainty_result = estimate_uncertainty(self, **{**self.uncertainty_options, **options}).to_dict()
        return self.uncertainty_result

    def set_gaussian_shape(self, shape: str) -> None:
        """``"deformed"``: fit the deformation coefficients of every Gaussian in its 24 nearest
        particles at the current frame-0 state (:func:`~toolkit.physics.embedding.local_deformation`);
        ``"rigid"``: drop them. See the ``gaussian_shape`` argument."""
        if shape not in GAUSSIAN_SHAPES:
            raise ValueError(f"gaussian_shape must be one of {GAUSSIAN_SHAPES}, got {shape!r}")
        self.gaussian_shape = shape
        dev = self.particles0.device
        if shape == "deformed" and len(self.particles0) >= 4:
            index, gradient = local_deformation((self.gaussian_means0 + self.gaussian_offset).detach(),
                                                (self.particles0 + self.particle_offset).detach())
        else:
            index, gradient = torch.zeros(0, 0, dtype=torch.int64), torch.zeros(0, 0, 3)
        self.deform_index, self.deform_gradient = index.to(dev), gradient.to(dev)

    def _sample(self, stage, step: int) -> tuple[list[int], list[int]]:
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        cams = list(self.input.train_cameras)
        if stage.cameras_per_step and stage.cameras_per_step < len(cams):
            cams = [cams[i] for i in sorted(torch.randperm(len(cams), generator=gen)[: stage.cameras_per_step].tolist())]
        window = stage.window(self.input.n_train)
        frames = list(range(window))
        if stage.frames_per_step and stage.frames_per_step < window:
            frames = sorted(torch.randperm(window, generator=gen)[: stage.frames_per_step].tolist())
        return cams, frames

    def _lr_factor(self, group: str, step: int) -> float:
        key = self.material.registry_name or None
        done = self.curriculum.group_progress(group, step, key)
        total = self.curriculum.group_active_steps(group, key)
        return cosine_with_warmup(done, total, self.warmup_fraction)

    # ------------------------------------------------------------------ Lightning hooks
    def configure_optimizers(self):
        groups = {
            "X": [{"params": [self.particle_offset, self.gaussian_offset], "lr": self.lrs["positions"], "name": "positions"}],
            "A": [
                {"params": [self.colors if self.colors is not None else self.sh], "lr": self.lrs["colors"], "name": "colors"},
                {"params": [self.opacity_logits], "lr": self.lrs["opacity"], "name": "opacity"},
                {"params": [self.log_scales], "lr": self.lrs["scales"], "name": "scales"},
                {"params": [self.quats], "lr": self.lrs["rotations"], "name": "rotations"},
            ],
            "S": [{"params": [self.v0], "lr": self.lrs["velocity"], "name": "velocity"}]
            + ([{"params": [self.gravity], "lr": self.lrs["gravity"], "name": "gravity"}] if self.optimize_gravity else []),
            "M": [{"params": [self.material_raw[n]], "lr": self.lrs.get(n, self.material.param(n).lr), "name": n}
                  for n in self.optimized_material]
            + ([{"params": [self.effect_params], "lr": self.lrs.get("effects", 0.02), "name": "effects"}] if self.effect_names else []),
        }
        opts = []
        for g in GROUPS:
            if not groups[g]:  # a group with nothing to optimize (e.g. all material parameters fixed)
                groups[g] = [{"params": [nn.Parameter(torch.zeros(1, device=self.v0.device))], "lr": 0.0, "name": "empty"}]
            for pg in groups[g]:
                pg["base_lr"] = pg["lr"]
            opts.append(torch.optim.Adam(groups[g], eps=1e-15))
        return opts

    def train_dataloader(self):
        return torch.utils.data.DataLoader(StepStream(), batch_size=None)

    def training_step(self, batch, batch_idx):
        if self.curriculum_step >= self.total_iterations:
            self.trainer.should_stop = True
            return None
        step = self.curriculum_step
        at = self.curriculum.stage_at(step, self.material.registry_name or None)
        stage = at.stage
        cams, frames = self._sample(stage, step)
        key = self.material.registry_name or None
        if "M" in stage.groups and self.material_init != "given" and self.curriculum.group_progress("M", step, key) == 0:
            from toolkit.physics.coarse_search import search_and_apply

            folder = getattr(self._trainer, "default_root_dir", None) if self._trainer is not None else None
            self.material_search = search_and_apply(self, stage, folder, joint_yield=self.material_init == "search_joint")
        opts = self.optimizers()
        for o in opts:
            o.zero_grad(set_to_none=True)
        losses = self.losses(stage, cams, frames)
        total = losses["total"]
        if total.requires_grad:
            self.manual_backward(total)
            for gi, g in enumerate(GROUPS):
                if g not in stage.groups:
                    continue
                factor = self._lr_factor(g, step) * stage.lr_scale.get(g, 1.0)
                for pg in opts[gi].param_groups:
                    pg["lr"] = pg["base_lr"] * factor
                opts[gi].step()
            project_off_ground(self.v0.data, self.contact_normal)
            self.project_material_bounds()
        if stage.groups & {"X", "S", "M"}:
            self._cached_positions = None
        self.curriculum_step += 1
        self._log_step(at, losses)
        return total.detach()

    def _log_step(self, at, losses: dict) -> None:
        est = self.estimate()
        rec: dict[str, Any] = {"step": self.curriculum_step, "stage": at.index, "stage_name": at.stage.name}
        if self.substeps is not None:
            rec["sim/substeps"] = self.substeps
        for k, v in losses.items():
            rec[f"loss/{k}"] = float(v.detach())
        for k, v in est["params"].items():
            rec[f"param/{k}"] = v
        for i, c in enumerate("xyz"):
            rec[f"v0/{c}"] = est["v0"][i]
        for name, vals in est["effects"].items():
            for k, v in vals.items():
                rec[f"effect/{name}.{k}"] = v
        opts = self.optimizers()
        for gi, g in enumerate(GROUPS):
            rec[f"lr/{g}"] = opts[gi].param_groups[0]["lr"] if g in at.stage.groups else 0.0
        rec.update(self.parameter_errors(est))
        self.history.append(rec)
        for k, v in rec.items():
            if isinstance(v, (int, float)) and k != "step":
                self.log(k, float(v), on_step=True, on_epoch=False, prog_bar=k in ("loss/total",), batch_size=1)


def _warp_device(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda:{device.index or 0}"
    return "cpu"

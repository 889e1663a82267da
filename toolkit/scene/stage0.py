"""Stage 0: fitting 4D Gaussians (canonical Gaussians + deformation network) to multi-view video.

Objective (ProJo4D Sec. 4 "Stage 0", GIC ``train_gs.py``), per iteration on one frame ``t``
rendered from every fitting camera in one renderer call:

    L = (1 - λ) L1(Î, I) + λ (1 - SSIM(Î, I))          λ = 0.2 (``lambda_dssim``)
      + λ_α L1(α̂, α)                                   α: object masks (GIC ``--reg_alpha``, λ_α = 1)
      + λ_s mean(scales)   after the warm-up           GIC ``--reg_scale``: λ_s = 10
      + λ_a L_anchor       after the warm-up           silhouette anchor (not in GIC), λ_a = 1 in ``full``

Positions below the dataset's ground plane are rendered on it (``Stage0Schedule.ground``, not in
GIC; :meth:`Gaussians4DModule.on_ground`): the plane is kept in the checkpoint (``ground_plane``),
so a model answers :meth:`~Gaussians4DModule.gaussians_at` as it was trained.

Ground-truth images are the masked images on black (DESIGN section 7). Positions at time ``t``
are ``x_t = x_0 + Δ(x_0, t)``; during the static warm-up (the first ``warmup`` iterations, frame
0 only) ``Δ`` is not evaluated. SSIM is the 3DGS definition (:func:`toolkit.metrics.ssim_torch`,
evaluated with a cached window).

Schedule and learning rates (:class:`~toolkit.scene.stage0_schedule.Stage0Schedule`, in
:mod:`toolkit.scene.stage0_schedule`; views and data module in :mod:`toolkit.scene.stage0_data`):
the dataclass defaults are GIC's (``arguments/__init__.py::OptimizationParams``): 40k iterations with a 3k static warm-up,
position lr 1.6e-4 x 5 decaying exponentially to 1.6e-6 x 5 over 30k iterations (GIC's hard-coded
``spatial_lr_scale = 5``), deformation lr with the same values over 40k, colour 2.5e-3 (1/20 for
higher SH bands), opacity 0.1, scale 1e-3 x 5, rotation 1e-3, Adam with eps 1e-15; densification
every 100 iterations from 500 to 15k with gradient threshold 1.5e-4, opacity reset every 3k
iterations after the warm-up, one SH degree more every 1000 iterations.
:meth:`Stage0Schedule.full` adds a frame curriculum, the silhouette anchor and a cap of one
Gaussian per observed object pixel; :meth:`Stage0Schedule.tiny` is a short schedule for CPU tests
and the demo.

Differences from GIC: GIC renders one (camera, frame) view per iteration; here every fitting
camera of the frame is rendered in one batched call (DESIGN section 9), so an iteration sees C
views. Frames after the warm-up are visited in a random order that covers every training frame
once per pass (GIC's "viewpoint stack"), derived from ``(seed, step)`` so that resuming replays
exactly the same sequence, after a curriculum that introduces the frames in time order
(``frame_curriculum``: GIC has none; here the first third of the dynamic phase in both the full
and the tiny schedule, because drawing far frames at once lost the object on fast throws). The
screen-space gradient that drives densification is recovered from the 3D position gradient
(the renderers do not expose 2D means; see :func:`screen_space_stats`).

Resume: the checkpoint holds the model (Gaussians, deformation network, densification buffers),
both optimizers and the step counter; ``on_load_checkpoint`` resizes the Gaussians to the
checkpoint's count before the state dicts are loaded, so ``Trainer.fit(..., ckpt_path=...)``
continues where it stopped. The training loop issues no host synchronization of its own except at
densification steps and every ``log_every`` steps (the renderer may have its own).
"""

from __future__ import annotations

import logging
import math
import random
import dataclasses
from typing import Any, Literal, Optional, Sequence

import pytorch_lightning as pl
import torch

from renderers import RENDERERS, get_renderer
from renderers.base import Gaussians, RenderOutput
from toolkit.scene.continuum_ground import height_above
from toolkit.scene.silhouette_anchor import mask_centroids, silhouette_anchor_loss
from toolkit.scene.stage0_data import Stage0DataModule, TrainingViews
from toolkit.scene.stage0_losses import _SSIM, screen_space_stats
from toolkit.scene.stage0_schedule import (  # noqa: F401  (re-exported: the public names of stage 0)
    FULL_FRAME_CURRICULUM,
    FULL_GAUSSIANS_PER_OBSERVED_PIXEL,
    FULL_LAMBDA_ANCHOR,
    ITERATION_COUNT_FIELDS,
    Stage0Schedule,
    compressed_settings,
)
from toolkit.cameras import Cameras
from toolkit.data.exclusion import apply_keep
from toolkit.scene.deformation import DeformationConfig, DeformationNetwork
from toolkit.scene.gaussian_model import DensificationConfig, GaussianModel
from toolkit.scene.stage0_checkpoint import Stage0Checkpoint
from toolkit.scene.opacity_reset import OpacityResetGuard
from toolkit.scene.initialization import (
    camera_extent,
    gic_num_points,
    mask_bounding_box,
    colors_from_views,
    random_box_points,
    visual_hull_points,
)

__all__ = [
    "Stage0Schedule",
    "TrainingViews",
    "Stage0DataModule",
    "Gaussians4DModule",
    "Stage0Checkpoint",
    "fit_stage0",
    "screen_space_stats",
    "default_renderer_name",
    "exponential_lr",
]

log = logging.getLogger(__name__)


def default_renderer_name() -> str:
    """``"warp"`` when that backend is registered, else the ``"torch"`` reference."""
    return "warp" if "warp" in RENDERERS else "torch"


def exponential_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear decay from ``lr_init`` (step 0) to ``lr_final`` (``max_steps`` and after);
    3DGS/GIC ``get_expon_lr_func`` without delay."""
    if lr_init <= 0 or lr_final <= 0:
        return max(lr_init, 0.0) if max_steps <= 0 or step < max_steps else max(lr_final, 0.0)
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return math.exp((1.0 - t) * math.log(lr_init) + t * math.log(lr_final))


# ====================================================================== the module


class Gaussians4DModule(pl.LightningModule):
    """4D Gaussians trained on all training frames of the fitting cameras (stage 0).

    Use with :class:`Stage0DataModule` (``trainer.fit(module, datamodule=dm)``) or
    :func:`fit_stage0`. Manual optimization: one Adam for the Gaussians (one param group per
    attribute) and one for the deformation network, created once.

    Args:
        schedule: :class:`Stage0Schedule` or a dict of its fields (default: GIC's full schedule).
        deformation: :class:`DeformationConfig` or a dict (default: GIC's network).
        sh_degree: Maximum SH degree of the colours (GIC 3).
        isotropic: One scale per Gaussian (GIC) instead of three.
        renderer: Registered renderer name (default: ``"warp"`` if registered, else ``"torch"``).
        renderer_kwargs: Extra constructor arguments of the renderer (``"warp"`` defaults to
            ``validate=False``: its input checks synchronize with the device every call).
        init: ``"hull"`` (points in the visual hull of the frame-0 masks, colours from the images)
            or ``"box"`` (GIC: uniform points in the bounding box, grey).
        init_points: Number of initial Gaussians (default: 2000 for ``"hull"``,
            :func:`gic_num_points` for ``"box"``).
        init_bbox: ``(min, max)`` corners of the scene box, metres (default: bounding box of the
            visual hull of the frame-0 masks).
        init_opacity: Initial opacity (GIC 0.1).
        hull_resolution: Voxels along the longest side when carving the masks.
        background: Render background colour (black, as the ground truth).
        seed: Seed of initialization, frame order and split sampling.
    """

    def __init__(
        self,
        schedule: Stage0Schedule | dict | None = None,
        deformation: DeformationConfig | dict | None = None,
        *,
        sh_degree: int = 3,
        isotropic: bool = True,
        renderer: Optional[str] = None,
        renderer_kwargs: Optional[dict] = None,
        init: Literal["hull", "box"] = "hull",
        init_points: Optional[int] = None,
        init_bbox: Optional[Sequence[Sequence[float]]] = None,
        init_opacity: float = 0.1,
        hull_resolution: int = 64,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.schedule = Stage0Schedule.from_dict(schedule)
        dcfg = DeformationConfig.from_dict(deformation)
        if init not in ("hull", "box"):
            raise ValueError(f"init must be 'hull' or 'box', got {init!r}")
        self.renderer_name = renderer or default_renderer_name()
        self.save_hyperparameters(
            {
                "schedule": self.schedule.to_dict(),
                "deformation": dcfg.to_dict(),
                "sh_degree": int(sh_degree),
                "isotropic": bool(isotropic),
                "renderer": self.renderer_name,
                "renderer_kwargs": dict(renderer_kwargs or {}),
                "init": init,
                "init_points": init_points,
                "init_bbox": None if init_bbox is None else [list(map(float, c)) for c in init_bbox],
                "init_opacity": float(init_opacity),
                "hull_resolution": int(hull_resolution),
                "background": [float(c) for c in background],
                "seed": int(seed),
            }
        )
        self.automatic_optimization = False
        self.gaussians = GaussianModel(sh_degree=sh_degree, isotropic=isotropic)
        with torch.random.fork_rng(devices=[]):  # the network's initial weights follow `seed`
            torch.manual_seed(int(seed))
            self.deformation = DeformationNetwork(dcfg, scale_dim=1 if isotropic else 3)
        rkw = dict(renderer_kwargs or {})
        if self.renderer_name == "warp":
            # its per-call input validation synchronizes with the device; training data is checked
            # by the finite-loss guard at logging/densification steps instead
            rkw.setdefault("validate", False)
        self.renderer = get_renderer(self.renderer_name, background=tuple(background), **rkw)
        self.register_buffer("extent", torch.ones(()))
        self.register_buffer("ground_plane", torch.full((6,), float("nan")))  # point, unit normal; NaN: none
        self._has_ground: Optional[bool] = None  # cached on the host: training steps do not synchronize
        self._ssim = _SSIM()
        self.step = 0
        self.stop_at: Optional[int] = None
        self.seed = int(seed)
        self._initialized = False
        self.reset_guard = OpacityResetGuard()  # undoes an opacity reset that would wipe out the model
        self._views: Optional[TrainingViews] = None

    @classmethod
    def from_preset(cls, preset: Literal["full", "tiny"] = "full", **overrides: Any) -> "Gaussians4DModule":
        """A module with consistent settings for a size preset.

        ``"full"``: GIC's schedule and network, SH degree 3, 2000 hull-initialized Gaussians.
        ``"tiny"``: :meth:`Stage0Schedule.tiny`, :meth:`DeformationConfig.tiny`, SH degree 0 and
        1000 initial Gaussians (the settings the tests measure). ``overrides`` are constructor
        arguments.
        """
        if preset == "full":
            kwargs: dict[str, Any] = {"schedule": Stage0Schedule.full(), "deformation": DeformationConfig()}
        elif preset == "tiny":
            kwargs = {"schedule": Stage0Schedule.tiny(), "deformation": DeformationConfig.tiny(), "sh_degree": 0, "init_points": 1000}
        else:
            raise ValueError(f"preset must be 'full' or 'tiny', got {preset!r}")
        kwargs.update(overrides)
        return cls(**kwargs)

    # ------------------------------------------------------------------ initialization

    def setup(self, stage: str) -> None:
        if stage == "fit" and not self._initialized:
            dm = self.trainer.datamodule if self.trainer is not None else None
            if dm is None or not hasattr(dm, "training_views"):
                raise RuntimeError("Gaussians4DModule needs a Stage0DataModule: trainer.fit(module, datamodule=dm)")
            self.initialize(dm.training_views())

    @torch.no_grad()
    def initialize(self, views: TrainingViews) -> None:
        """Create the canonical Gaussians and the normalizations from the training views."""
        hp = self.hparams
        cams = views.cameras.to("cpu")
        masks0 = None if views.masks is None else views.masks[0].cpu()
        if hp.init_bbox is not None:
            lo = torch.tensor(hp.init_bbox[0], dtype=torch.float32)
            hi = torch.tensor(hp.init_bbox[1], dtype=torch.float32)
        elif masks0 is not None:
            lo, hi = mask_bounding_box(cams, masks0, resolution=hp.hull_resolution)
        else:
            raise ValueError("the scene has no masks: pass init_bbox=(min, max) to Gaussians4DModule")
        cap = self.gaussian_cap(views)
        if hp.init == "hull":
            if masks0 is None:
                raise ValueError("init='hull' needs masks; use init='box' with init_bbox for scenes without masks")
            n = int(hp.init_points or 2000)
            n = n if cap is None else max(1, min(n, cap))
            pts = visual_hull_points(cams, masks0, n, bbox=(lo, hi), resolution=hp.hull_resolution, seed=self.seed)
            colors = colors_from_views(pts, cams, views.images[0].cpu(), masks0)
        else:
            n = int(hp.init_points or gic_num_points(lo.numpy(), hi.numpy()))
            n = n if cap is None else max(1, min(n, cap))
            pts = random_box_points(lo, hi, n, seed=self.seed)
            colors = None
        self.gaussians.init_from_points(pts, colors, opacity=hp.init_opacity)
        self.extent.fill_(0.5 * camera_extent(cams))
        t = views.times.cpu()
        self.deformation.set_normalization(lo, hi, float(t.min()), float(t.max()))
        if self.schedule.ground and views.ground is not None:
            point, normal = (torch.as_tensor(v, dtype=torch.float32) for v in views.ground)
            self.ground_plane.copy_(torch.cat([point, normal / normal.norm()]))
        self._has_ground = None
        self._initialized = True
        log.info("stage 0: %d initial Gaussians (%s init), at most %s, box %s..%s m", n, hp.init, cap,
                 lo.tolist(), hi.tolist())

    # ------------------------------------------------------------------ queries

    def gaussians_at(self, time: float | torch.Tensor | None = None, sh_degree: Optional[int] = None) -> Gaussians:
        """The Gaussians at ``time`` (seconds; None: canonical, no deformation), differentiable."""
        g = self.gaussians
        if time is None:
            return g.gaussians(sh_degree=sh_degree)
        d = self.deformation(g.means, torch.as_tensor(time, dtype=g.means.dtype, device=g.means.device))
        return g.gaussians(means=self.on_ground(g.means + d.xyz), d_log_scales=d.log_scales, d_quats=d.quats,
                           sh_degree=sh_degree)

    def on_ground(self, means: torch.Tensor) -> torch.Tensor:
        """(N, 3) ``means`` with those below the ground plane (``ground_plane``) moved onto it
        along its normal; the gradient passes straight through. Unchanged without a plane."""
        plane = self.ground_plane
        if self._has_ground is None:
            self._has_ground = bool(torch.isfinite(plane).all())
        if not self._has_ground:
            return means
        normal = plane[3:].to(means.dtype)
        return means + torch.relu(-height_above(means.detach(), (plane[:3], normal)))[:, None] * normal

    def centers_at(self, times: Sequence[float] | torch.Tensor) -> torch.Tensor:
        """(T, N, 3) Gaussian centres ``x_0 + Δ(x_0, t)`` at each time (no grad)."""
        with torch.no_grad():
            g = self.gaussians
            tt = torch.as_tensor(times, dtype=g.means.dtype, device=g.means.device).reshape(-1)
            out = []
            for t in tt:  # one time at a time keeps memory at O(N)
                out.append(self.on_ground(g.means + self.deformation(g.means, t).xyz))
            return torch.stack(out) if out else torch.zeros(0, g.n, 3, device=g.means.device)

    def render(self, cameras: Cameras, time: float | torch.Tensor | None = None) -> RenderOutput:
        """Render every camera of ``cameras`` at ``time`` in one call (differentiable)."""
        return self.renderer(self.gaussians_at(time), cameras.to(self.gaussians.means.device))

    def active_sh_degree(self, step: Optional[int] = None) -> int:
        it = (self.step if step is None else step) + 1
        return min(self.gaussians.sh_degree, it // self.schedule.sh_increase_interval)

    def frame_for_step(self, step: int, n_frames: int) -> int:
        """Index (into the training frames) of the frame used at ``step``: 0 during the warm-up,
        then a fresh random permutation of all frames per pass, a pure function of (seed, step)."""
        s = self.schedule
        if step < s.warmup or n_frames <= 1:
            return 0
        k = step - s.warmup
        if k < s.frame_curriculum:
            window = 1 + int((n_frames - 1) * (k + 1) / s.frame_curriculum)
            return random.Random(self.seed * 1_000_003 + 7 * step + 1).randrange(min(window, n_frames))
        k -= s.frame_curriculum
        perm = list(range(n_frames))
        random.Random(self.seed * 1_000_003 + k // n_frames).shuffle(perm)
        return perm[k % n_frames]

    def learning_rates(self, step: int) -> dict[str, float]:
        s = self.schedule
        return {
            "means": exponential_lr(step, s.position_lr_init, s.position_lr_final, s.position_lr_max_steps),
            "deformation": exponential_lr(step, s.deform_lr_init, s.deform_lr_final, s.deform_lr_max_steps),
        }

    # ------------------------------------------------------------------ optimization

    def configure_optimizers(self):
        s, g = self.schedule, self.gaussians
        groups = [
            {"params": [g.means], "lr": s.position_lr_init, "name": "means"},
            {"params": [g.sh_dc], "lr": s.feature_lr, "name": "sh_dc"},
            {"params": [g.opacity_logits], "lr": s.opacity_lr, "name": "opacity_logits"},
            {"params": [g.log_scales], "lr": s.scaling_lr, "name": "log_scales"},
        ]
        if g.sh_degree > 0:
            groups.append({"params": [g.sh_rest], "lr": s.feature_lr / 20.0, "name": "sh_rest"})
        if not g.isotropic:
            groups.append({"params": [g.quats], "lr": s.rotation_lr, "name": "quats"})
        opt_g = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        opt_d = torch.optim.Adam(self.deformation.parameters(), lr=s.deform_lr_init, eps=1e-15)
        return [opt_g, opt_d]

    def gaussian_cap(self, views: TrainingViews) -> Optional[int]:
        """The most Gaussians densification may grow to: the smaller of
        ``densification.max_gaussians`` and ``gaussians_per_observed_pixel`` times the object
        pixels (mask > 0.5) of every training frame and fitting camera; None when neither applies."""
        s = self.schedule
        caps = [] if s.densification.max_gaussians is None else [int(s.densification.max_gaussians)]
        if s.gaussians_per_observed_pixel > 0 and views.masks is not None:
            observed = int((views.masks > 0.5).sum())
            caps.append(max(1, int(math.ceil(s.gaussians_per_observed_pixel * observed))))
        return min(caps) if caps else None

    def _densification(self, views: TrainingViews) -> DensificationConfig:
        if getattr(self, "_densification_of", None) is not views:
            cap = self.gaussian_cap(views)
            self._densification_cfg = dataclasses.replace(self.schedule.densification, max_gaussians=cap)
            self._densification_of = views
        return self._densification_cfg

    def _mask_centroids(self, views: TrainingViews) -> torch.Tensor:
        if getattr(self, "_centroids_of", None) is not views:
            self._centroids, self._centroids_of = mask_centroids(views.masks), views
        return self._centroids

    def _device_views(self) -> TrainingViews:
        if self._views is None or self._views.device != self.gaussians.means.device:
            self._views = self.trainer.datamodule.training_views().to(self.gaussians.means.device)
        return self._views

    def training_step(self, batch: Any, batch_idx: int) -> None:
        s = self.schedule
        step = self.step
        it = step + 1
        views = self._device_views()
        opt_g, opt_d = self.optimizers()
        lrs = self.learning_rates(step)
        for group in opt_g.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = lrs["means"]
        for group in opt_d.optimizer.param_groups:
            group["lr"] = lrs["deformation"]

        fi = self.frame_for_step(step, views.n_frames)
        gt = views.images[fi]
        cams = views.cameras
        dynamic = step >= s.warmup
        g = self.gaussians
        d_ls = d_q = None
        if dynamic:
            d = self.deformation(g.means, views.times[fi])
            means = self.on_ground(g.means + d.xyz)
            means.retain_grad()
            d_ls, d_q = d.log_scales, d.quats
        else:
            means = g.means
        gs = g.gaussians(means=means, d_log_scales=d_ls, d_quats=d_q, sh_degree=self.active_sh_degree(step))
        out = self.renderer(gs, cams)

        rgb, gt = apply_keep(out.rgb, gt, views.keep)  # PAC-NeRF loss-exclusion masks (frame -2)
        l1 = (rgb - gt).abs().mean()
        ssim = self._ssim(rgb, gt)
        loss = (1.0 - s.lambda_dssim) * l1 + s.lambda_dssim * (1.0 - ssim)
        alpha_loss = None
        if views.masks is not None and s.lambda_alpha > 0:
            alpha_err = (out.alpha - views.masks[fi]).abs()
            alpha_loss = (alpha_err if views.keep is None else alpha_err * views.keep).mean()
            loss = loss + s.lambda_alpha * alpha_loss
        if dynamic and s.lambda_scale > 0:
            loss = loss + s.lambda_scale * g.scales(d_ls).mean()
        if dynamic and s.lambda_anchor > 0 and views.masks is not None:
            weights = torch.sigmoid(g.opacity_logits.detach()).reshape(-1)
            loss = loss + s.lambda_anchor * silhouette_anchor_loss(means, weights, cams, self._mask_centroids(views)[fi],
                                                                   s.anchor_tolerance)

        opt_g.zero_grad(set_to_none=True)
        opt_d.zero_grad(set_to_none=True)
        self.manual_backward(loss)

        track = it < s.densify_until
        if it == s.densify_until:
            self.reset_guard.release()
        densify_now = track and it > s.densify_from and it % s.densify_interval == 0
        logging_now = bool(s.log_every) and it % s.log_every == 0
        if (densify_now or logging_now) and not bool(torch.isfinite(loss)):  # these steps sync anyway
            raise FloatingPointError(f"stage 0: the loss is {float(loss)} at iteration {it}")
        if track:
            grad = means.grad if means.grad is not None else torch.zeros_like(means)
            with torch.no_grad():
                factor, visible, radii = screen_space_stats(means.detach(), gs.log_scales.detach().exp().amax(1), cams)
                g.add_densification_stats(grad.norm(dim=-1) * factor, visible, radii)
        opt_g.step()
        if dynamic:
            opt_d.step()

        if track:
            if densify_now:
                self.reset_guard.check(g, [opt_g], s.densification.min_opacity, it)
                max_px = (
                    s.densification.max_screen_fraction * max(cams.width, cams.height)
                    if it > s.opacity_reset_interval
                    else None
                )
                gen = torch.Generator().manual_seed(self.seed * 7_919 + step)
                stats = g.densify_and_prune(self._densification(views), float(self.extent), [opt_g], max_screen_px=max_px, generator=gen)
                log.debug("iteration %d: densification %s", it, stats)
            if it > s.warmup and it % s.opacity_reset_interval == 0:
                self.reset_guard.reset(g, [opt_g], s.densification.opacity_reset_value, it)

        self.step = step + 1
        if logging_now:
            psnr = -10.0 * torch.log10(((rgb - gt) ** 2).mean().detach().clamp_min(1e-10))
            metrics = {"train/loss": loss.detach(), "train/l1": l1.detach(), "train/ssim": ssim.detach(), "train/psnr": psnr,
                       "train/n_gaussians": float(g.n), "train/iteration": float(it)}
            if alpha_loss is not None:
                metrics["train/alpha_l1"] = alpha_loss.detach()
            self.log_dict(metrics, prog_bar=True, logger=False, on_step=True, on_epoch=False, batch_size=len(cams))
            # written here, once per logging iteration: Lightning would repeat step-logged values on later steps
            for lg in self.loggers:
                lg.log_metrics({k: float(v) for k, v in metrics.items()}, step=it)

    # ------------------------------------------------------------------ checkpoints

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["stage0"] = {"step": int(self.step), "n_gaussians": int(self.gaussians.n), "initialized": bool(self._initialized), "version": 1,
                                "opacity_resets_disabled": bool(self.reset_guard.disabled), "opacity_resets_reverted": list(self.reset_guard.reverted)}

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        state = checkpoint.get("stage0", {})
        n = int(checkpoint["state_dict"]["gaussians.means"].shape[0])
        checkpoint["state_dict"].setdefault("ground_plane", torch.full((6,), float("nan")))  # trained without one
        self._has_ground = bool(torch.isfinite(checkpoint["state_dict"]["ground_plane"]).all())
        self.gaussians.resize_(n)
        self.step = int(state.get("step", 0))
        self._initialized = bool(state.get("initialized", True))
        self.reset_guard = OpacityResetGuard(disabled=bool(state.get("opacity_resets_disabled", False)),
                                             reverted=list(state.get("opacity_resets_reverted", [])))
        self._views = None


from toolkit.scene.stage0_fit import fit_stage0  # noqa: E402  (re-exported; it needs the module above)

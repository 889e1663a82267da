"""Stage 0: fitting 4D Gaussians (canonical Gaussians + deformation network) to multi-view video.

Objective (ProJo4D Sec. 4 "Stage 0", GIC ``train_gs.py``), per iteration on one frame ``t``
rendered from every fitting camera in one renderer call:

    L = (1 - λ) L1(Î, I) + λ (1 - SSIM(Î, I))          λ = 0.2 (``lambda_dssim``)
      + λ_α L1(α̂, α)                                   α: object masks (GIC ``--reg_alpha``, λ_α = 1)
      + λ_s mean(scales)   after the warm-up           GIC ``--reg_scale``: λ_s = 10
      + λ_a L_anchor       after the warm-up           silhouette anchor (not in GIC), λ_a = 1 in ``full``

Ground-truth images are the masked images on black (DESIGN section 7). Positions at time ``t``
are ``x_t = x_0 + Δ(x_0, t)``; during the static warm-up (the first ``warmup`` iterations, frame
0 only) ``Δ`` is not evaluated. SSIM is the 3DGS definition (:func:`toolkit.metrics.ssim_torch`,
evaluated with a cached window).

Schedule and learning rates (:class:`Stage0Schedule`): :meth:`Stage0Schedule.full` is GIC's
(``arguments/__init__.py::OptimizationParams``): 40k iterations with a 3k static warm-up,
position lr 1.6e-4 x 5 decaying exponentially to 1.6e-6 x 5 over 30k iterations (GIC's hard-coded
``spatial_lr_scale = 5``), deformation lr with the same values over 40k, colour 2.5e-3 (1/20 for
higher SH bands), opacity 0.1, scale 1e-3 x 5, rotation 1e-3, Adam with eps 1e-15; densification
every 100 iterations from 500 to 15k with gradient threshold 1.5e-4, opacity reset every 3k
iterations after the warm-up, one SH degree more every 1000 iterations.
:meth:`Stage0Schedule.tiny` is a short schedule for CPU tests and the demo.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Literal, Optional, Sequence

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, IterableDataset

from renderers import RENDERERS, get_renderer
from renderers.base import Gaussians, RenderOutput
from toolkit.scene.silhouette_anchor import mask_centroids, silhouette_anchor_loss
from toolkit.cameras import Cameras
from toolkit.data.exclusion import apply_keep
from toolkit.settings import DictSettings
from toolkit.scene.deformation import DeformationConfig, DeformationNetwork
from toolkit.scene.gaussian_model import DensificationConfig, GaussianModel
from toolkit.scene.stage0_checkpoint import Stage0Checkpoint
from toolkit.scene.opacity_reset import OpacityResetGuard
from toolkit.scene.initialization import (
    camera_extent,
    gic_num_points,
    mask_bounding_box,
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


# ====================================================================== schedule


#: the fields of :class:`Stage0Schedule` that count iterations (scaled by :meth:`Stage0Schedule.compressed`)
ITERATION_COUNT_FIELDS = ("warmup", "position_lr_max_steps", "deform_lr_max_steps", "densify_from", "densify_until",
                          "densify_interval", "opacity_reset_interval", "sh_increase_interval", "frame_curriculum")

#: :meth:`Stage0Schedule.full`'s frame curriculum: the first third of GIC's dynamic phase (37k iterations)
FULL_FRAME_CURRICULUM = 12_300
#: :meth:`Stage0Schedule.full`'s silhouette-anchor weight (:mod:`toolkit.scene.silhouette_anchor`)
FULL_LAMBDA_ANCHOR = 1.0
#: :meth:`Stage0Schedule.full`'s cap: one Gaussian per observed object pixel
FULL_GAUSSIANS_PER_OBSERVED_PIXEL = 1.0


@dataclass
class Stage0Schedule(DictSettings):
    settings_name = "Stage0Schedule settings"

    """Iterations, learning rates, loss weights and densification settings of stage 0.

    Iteration numbers follow GIC's 1-based convention: iteration ``it = step + 1``.

    Attributes:
        iterations: Total iterations (GIC 40k).
        warmup: Static iterations on frame 0 before the deformation is used (GIC 3k).
        position_lr_init, position_lr_final, position_lr_max_steps: Exponential decay of the
            canonical positions' lr (GIC 1.6e-4 x 5 -> 1.6e-6 x 5 over 30k).
        deform_lr_init, deform_lr_final, deform_lr_max_steps: Same for the deformation network
            (GIC: same values over 40k).
        feature_lr: lr of the SH DC coefficients (GIC 2.5e-3); higher bands use 1/20 of it.
        opacity_lr: lr of the opacity logits (GIC 0.1; 3DGS 0.05).
        scaling_lr: lr of the log-scales (GIC 1e-3 x 5).
        rotation_lr: lr of the quaternions (GIC 1e-3; anisotropic Gaussians only).
        lambda_dssim: SSIM weight λ (0.2).
        lambda_alpha: Weight of the alpha-mask L1 (GIC ``reg_alpha``: 1).
        lambda_scale: Weight of the mean scale (metres) after the warm-up (GIC ``reg_scale``: 10).
        lambda_anchor: Weight of the silhouette anchor after the warm-up
            (:mod:`toolkit.scene.silhouette_anchor`; GIC: none): the projected mean of the
            Gaussians is drawn toward each mask's centroid, so a frame the deformation carried off
            the object still has a gradient back. 0 (GIC, the tiny schedule) turns it off;
            :meth:`full` uses 1.
        anchor_tolerance: The anchor's dead zone, as a fraction of the image size.
        densify_from, densify_until, densify_interval: Densify at iterations ``it`` with
            ``densify_from < it < densify_until`` and ``it % densify_interval == 0``.
        opacity_reset_interval: Reset opacities at multiples of this after the warm-up (and
            before ``densify_until``); screen-size pruning starts after the first interval.
        sh_increase_interval: One more active SH degree every this many iterations.
        frame_curriculum: Iterations after the warm-up during which the frames drawn grow from
            the first one to all training frames (frames ``[0, w)`` with ``w`` rising linearly);
            0 (GIC) draws from all frames at once. Helps when the motion is larger than the
            object: far frames then do not overlap the undeformed Gaussians, and their offsets
            can overshoot out of every view and be lost.
        gaussians_per_observed_pixel: Cap on the number of Gaussians, per object pixel the
            training views observe (mask > 0.5, summed over every training frame and fitting
            camera); 0 (GIC) leaves the count to the gradient threshold. :meth:`full` uses 1:
            more Gaussians than observed object pixels cannot be told apart by the images, and
            every physics iteration renders them all. The cap also bounds the initial count and
            combines with ``densification.max_gaussians`` (the smaller wins).
        densification: Thresholds (:class:`DensificationConfig`).
        log_every: Log losses every this many iterations (each log is a host synchronization).
    """

    iterations: int = 40_000
    warmup: int = 3_000
    position_lr_init: float = 1.6e-4 * 5
    position_lr_final: float = 1.6e-6 * 5
    position_lr_max_steps: int = 30_000
    deform_lr_init: float = 1.6e-4 * 5
    deform_lr_final: float = 1.6e-6 * 5
    deform_lr_max_steps: int = 40_000
    feature_lr: float = 2.5e-3
    opacity_lr: float = 0.1
    scaling_lr: float = 1e-3 * 5
    rotation_lr: float = 1e-3
    lambda_dssim: float = 0.2
    lambda_alpha: float = 1.0
    lambda_scale: float = 10.0
    lambda_anchor: float = 0.0
    anchor_tolerance: float = 0.02
    densify_from: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    opacity_reset_interval: int = 3_000
    sh_increase_interval: int = 1_000
    frame_curriculum: int = 0
    gaussians_per_observed_pixel: float = 0.0
    densification: DensificationConfig = field(default_factory=DensificationConfig)
    log_every: int = 100

    def __post_init__(self) -> None:
        self.densification = DensificationConfig.from_dict(self.densification)
        if self.iterations < 1 or self.warmup < 0:
            raise ValueError(f"iterations must be >= 1 and warmup >= 0, got {self.iterations}, {self.warmup}")
        if self.densify_interval < 1 or self.opacity_reset_interval < 1 or self.sh_increase_interval < 1:
            raise ValueError("densify_interval, opacity_reset_interval and sh_increase_interval must be >= 1")
        for name in ("frame_curriculum", "lambda_anchor", "anchor_tolerance", "gaussians_per_observed_pixel"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")

    @classmethod
    def full(cls) -> "Stage0Schedule":
        """GIC's schedule for full-size scenes (the defaults), with three changes: the frames of the
        dynamic phase are introduced in time order over its first third
        (``frame_curriculum`` = :data:`FULL_FRAME_CURRICULUM`; GIC draws from all frames at once),
        the silhouette anchor is on (``lambda_anchor`` = :data:`FULL_LAMBDA_ANCHOR`), and the
        number of Gaussians is capped at one per observed object pixel
        (``gaussians_per_observed_pixel`` = :data:`FULL_GAUSSIANS_PER_OBSERVED_PIXEL`).

        Without it the deformation lost the object on fast throws: at 96 px and 2500 iterations
        (:meth:`compressed`), 12 of the 30 sliding-box scenes of the discovery benchmark fell to
        25-28 dB right after the warm-up and stayed there, with their Gaussians carried metres out
        of every view (the black background alone scores about 27 dB); 3 of them left the
        continuum empty. On two of them the curriculum alone still lost the last three frames;
        with the anchor no frame was lost (``docs/limits.md``, "Stage 0 losing the object").

        Without the cap the same 96 px scenes, whose object covers about 90 pixels a view,
        grew 27k-104k Gaussians, 100-400 per observed pixel, and every physics iteration
        rendered them all (no base fit finished in 17 minutes on a CPU core)."""
        return cls(frame_curriculum=FULL_FRAME_CURRICULUM, lambda_anchor=FULL_LAMBDA_ANCHOR,
                   gaussians_per_observed_pixel=FULL_GAUSSIANS_PER_OBSERVED_PIXEL)

    @classmethod
    def tiny(cls) -> "Stage0Schedule":
        """A CPU-sized schedule (tests, demo): 600 iterations, 80 of them static warm-up, on
        48-64 px images with 1000-2500 Gaussians (about 35 s on one CPU core at 64 px).
        Learning rates are raised (x4 for positions and the deformation network, x4 for colours)
        and decay 10x over the run, so the short run converges; densification runs every 40
        iterations until about halfway through the dynamic phase (GIC: until 15k of 40k) and is
        capped at 2500 Gaussians; no opacity reset (recovering from one takes thousands of
        iterations). The frames of the dynamic phase are introduced progressively over its first
        third (``frame_curriculum``): drawing far frames from the start made Adam overshoot their
        offsets in some runs until those frames left every view (1 run in 4 on the test scene),
        after which no gradient could bring them back."""
        return cls(
            iterations=600,
            warmup=80,
            position_lr_init=3.2e-3,
            position_lr_final=3.2e-4,
            position_lr_max_steps=600,
            deform_lr_init=3.2e-3,
            deform_lr_final=3.2e-4,
            deform_lr_max_steps=600,
            feature_lr=1e-2,
            opacity_lr=0.05,
            scaling_lr=5e-3,
            densify_from=40,
            densify_until=320,
            densify_interval=40,
            opacity_reset_interval=100_000,
            sh_increase_interval=100_000,
            frame_curriculum=170,
            densification=DensificationConfig(grad_threshold=1.5e-4, max_gaussians=2500),
            log_every=50,
        )

    @classmethod
    def compressed(cls, iterations: int) -> "Stage0Schedule":
        """:meth:`full`'s schedule with every iteration count (:data:`ITERATION_COUNT_FIELDS`: warm-up,
        learning-rate decay lengths, densification window and interval, opacity resets, SH steps,
        frame curriculum)
        scaled by ``iterations / 40_000``; rates, thresholds and loss weights unchanged.
        ``compressed(40_000) == full()``. Counts round to the nearest iteration, at least 1.
        ``projo4d run --stage0-iterations N`` and ``projo4d benchmark --stage0-iterations N`` use it
        (through :func:`compressed_settings`; a cheaper, less converged stage 0:
        ``benchmarks/whole_scene.py`` measures the trade, issue #16).

        Raises:
            ValueError: ``iterations`` is not an integer >= 100.
        """
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 100:
            raise ValueError(f"iterations must be an integer >= 100, got {iterations!r}")
        base = cls.full()
        f = iterations / base.iterations
        scaled = {key: max(1, int(round(getattr(base, key) * f))) if getattr(base, key) else 0 for key in ITERATION_COUNT_FIELDS}
        return cls(**{**base.to_dict(), "iterations": iterations, **scaled})

    @classmethod
    def defaults(cls) -> "Stage0Schedule":
        return cls.full()


def compressed_settings(iterations: int) -> dict:
    """:meth:`Stage0Schedule.compressed` as a ``RunSettings.stage0`` mapping: ``preset`` "full",
    ``iterations``, the scaled :data:`ITERATION_COUNT_FIELDS`, the anchor weight and the Gaussian cap (so that the
    mapping alone, without the preset, gives the same schedule).

    Raises:
        ValueError: ``iterations`` is not an integer >= 100.
    """
    schedule = Stage0Schedule.compressed(iterations)
    return {"preset": "full", "iterations": schedule.iterations,
            **{key: getattr(schedule, key) for key in ITERATION_COUNT_FIELDS}, "lambda_anchor": schedule.lambda_anchor,
            "gaussians_per_observed_pixel": schedule.gaussians_per_observed_pixel}


# ====================================================================== data


@dataclass
class TrainingViews:
    """All fitting views of a scene, as tensors (cached on the training device).

    Attributes:
        cameras: The C fitting cameras, scaled to the image size.
        images: (T, C, H, W, 3) float32 in [0, 1]; masked on black when masks exist.
        masks: (T, C, H, W) float32 object masks in [0, 1], or None.
        times: (T,) float32 frame times, seconds.
        frames: Scene frame index of each of the T frames.
        camera_indices: Scene camera index of each of the C cameras.
        keep: (C, H, W) float32 loss weights (0 = pixel excluded: PAC-NeRF frame -2 masks,
            :mod:`toolkit.data.exclusion`), or None.
    """

    cameras: Cameras
    images: torch.Tensor
    masks: Optional[torch.Tensor]
    times: torch.Tensor
    frames: list[int]
    camera_indices: list[int]
    keep: Optional[torch.Tensor] = None

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def n_cameras(self) -> int:
        return int(self.images.shape[1])

    @property
    def device(self) -> torch.device:
        return self.images.device

    def to(self, device: torch.device | str) -> "TrainingViews":
        return TrainingViews(
            cameras=self.cameras.to(device),
            images=self.images.to(device),
            masks=None if self.masks is None else self.masks.to(device),
            times=self.times.to(device),
            frames=list(self.frames),
            camera_indices=list(self.camera_indices),
            keep=None if self.keep is None else self.keep.to(device),
        )

    @classmethod
    def from_datamodule(cls, dm: Any, composite_on_black: bool = True) -> "TrainingViews":
        """Load the training split (fitting cameras x training frames) of a
        :class:`toolkit.data.datamodule.MultiViewDataModule`."""
        cams_idx, frames = list(dm.train_cameras), list(dm.train_frames)
        ds = dm.dataset(cams_idx, frames)
        C, T = len(cams_idx), len(frames)
        imgs, masks = [], []
        has_masks = True
        for i in range(len(ds)):
            item = ds[i]
            imgs.append(item["image"])
            if "mask" in item:
                masks.append(item["mask"])
            else:
                has_masks = False
        H, W = imgs[0].shape[:2]
        images = torch.stack(imgs).reshape(T, C, H, W, 3).float()
        mask_t = torch.stack(masks).reshape(T, C, H, W).float() if has_masks and masks else None
        if mask_t is not None and composite_on_black:
            images = images * mask_t[..., None]
        times = torch.as_tensor(np.asarray(dm.scene.times)[frames], dtype=torch.float32)
        from toolkit.data.exclusion import keep_weights

        keep = keep_weights(dm.scene, cams_idx, size=(H, W))
        return cls(dm.cameras[cams_idx], images, mask_t, times, frames, cams_idx, keep)


class _StepStream(IterableDataset):
    """Yields the module's iteration numbers from its current step to the end of the schedule."""

    def __init__(self, dm: "Stage0DataModule"):
        super().__init__()
        self.dm = dm

    def _range(self) -> range:
        module = self.dm.trainer.lightning_module if self.dm.trainer is not None else None
        if module is None:
            return range(0)
        stop = module.schedule.iterations if module.stop_at is None else min(module.stop_at, module.schedule.iterations)
        return range(module.step, max(module.step, stop))

    def __iter__(self) -> Iterator[int]:
        return iter(self._range())


class _StepLoader(DataLoader):
    """The step stream's loader. It is resumable by construction (the stream restarts at the
    module's restored step), which ``state_dict``/``load_state_dict`` tell Lightning."""

    def state_dict(self) -> dict:
        return {"resumes_at_module_step": True}

    def load_state_dict(self, state_dict: dict) -> None:
        pass


class Stage0DataModule(pl.LightningDataModule):
    """Training views for :class:`Gaussians4DModule`.

    The views (fitting cameras x training frames, see
    :class:`toolkit.data.datamodule.MultiViewDataModule`) are loaded once and cached on the
    training device by the module; the train dataloader only yields iteration numbers (the
    module picks the frame of each iteration), so no image is copied to the device per step.

    Args:
        scene: A :class:`MultiViewScene`, a scene folder, or None when ``views`` is given.
        cameras: Fitting cameras (``"sparse"``, ``"all"`` or 0-based indices).
        n_train: Number of training frames (None: min(14, T)).
        downscale: Image downscale factor.
        composite_on_black: Multiply images by their masks (ground truth on black).
        layout: Layout of a scene folder.
        views: Ready-made :class:`TrainingViews` (benchmarks, tests) instead of a scene.
    """

    def __init__(
        self,
        scene: Any = None,
        *,
        cameras: Sequence[int] | str = "sparse",
        n_train: Optional[int] = None,
        downscale: float = 1.0,
        composite_on_black: bool = True,
        layout: str = "auto",
        views: Optional[TrainingViews] = None,
    ) -> None:
        super().__init__()
        if (scene is None) == (views is None):
            raise ValueError("give exactly one of scene or views")
        self.multiview = None
        if scene is not None:
            from toolkit.data.datamodule import MultiViewDataModule

            self.multiview = MultiViewDataModule(
                scene, cameras=cameras, n_train=n_train, downscale=downscale, shuffle=False, layout=layout
            )
        self.composite_on_black = composite_on_black
        self._views = views

    def training_views(self) -> TrainingViews:
        """The training views on the CPU (loaded on first use)."""
        if self._views is None:
            self._views = TrainingViews.from_datamodule(self.multiview, self.composite_on_black)
        return self._views

    def train_dataloader(self) -> DataLoader:
        return _StepLoader(_StepStream(self), batch_size=None, num_workers=0)


# ====================================================================== training helpers


@torch.no_grad()
def screen_space_stats(
    means: torch.Tensor, max_scale: torch.Tensor, cameras: Cameras
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-Gaussian visibility, 2D radius and the metres-to-NDC factor for a batch of cameras.

    3DGS densifies on ``|dL/d mean2d|`` in NDC units, ``mean2d`` being the projected centre. The
    renderers here are differentiated with respect to 3D means only; since a lateral move of
    ``dx`` metres at depth ``z`` moves the projection by ``f dx / z`` pixels, i.e.
    ``2 f dx / (z W)`` NDC units, ``|dL/d ndc| ≈ |dL/dx| z W / (2 f)``. With C cameras in one loss
    the 3D gradient is the sum of the per-view ones; the factor is averaged over the cameras
    that see the Gaussian.

    Args:
        means: (N, 3) rendered positions, metres.
        max_scale: (N,) largest standard deviation, metres.
        cameras: C cameras.

    Returns:
        ``(factor (N,), visible (N,) bool, radii (N,))``: metres-to-NDC gradient factor (mean
        over the cameras that see each Gaussian), in view of at least one camera (projected 3-sigma
        disc overlaps the image, centre in front of the near plane), largest 3-sigma radius in
        pixels.
    """
    pc = cameras.world_to_camera(means)  # (C, N, 3)
    z = pc[..., 2]
    valid = z > cameras.near
    zs = torch.where(valid, z, torch.ones_like(z))
    K = cameras.K.to(means)
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    u = fx * pc[..., 0] / zs + K[:, 0, 2, None]
    v = fy * pc[..., 1] / zs + K[:, 1, 2, None]
    r = 3.0 * max_scale[None] * torch.maximum(fx, fy) / zs
    vis = valid & (u + r > 0) & (u - r < cameras.width) & (v + r > 0) & (v - r < cameras.height)
    visf = vis.to(means.dtype)
    factor_c = zs * cameras.width / (2.0 * fx)
    factor = (factor_c * visf).sum(0) / visf.sum(0).clamp_min(1.0)
    radii = (r * visf).amax(0)
    return factor, vis.any(0), radii


class _SSIM:
    """:func:`toolkit.metrics.ssim_torch` (3DGS SSIM: 11 x 11 Gaussian window, sigma 1.5, zero
    padding) with the window cached per device and dtype: building it on the CPU and copying it
    to the GPU every call would synchronize the host with the device each iteration."""

    def __init__(self, window_size: int = 11, sigma: float = 1.5):
        self.window_size, self.sigma = window_size, sigma
        self._cache: dict = {}

    def __call__(self, img: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """img, gt: (B, H, W, C) in [0, 1] -> scalar mean SSIM (differentiable)."""
        x, y = img.permute(0, 3, 1, 2), gt.to(img.dtype).permute(0, 3, 1, 2)
        c = x.shape[1]
        key = (x.device, x.dtype, c)
        w = self._cache.get(key)
        if w is None:
            from toolkit.metrics.image import gaussian_window

            w = gaussian_window(self.window_size, self.sigma, dtype=x.dtype, device=x.device)
            w = self._cache[key] = w.expand(5 * c, 1, self.window_size, self.window_size).contiguous()
        stats = torch.cat([x, y, x * x, y * y, x * y], dim=1)
        blurred = torch.nn.functional.conv2d(stats, w, padding=self.window_size // 2, groups=5 * c)
        mu_x, mu_y, e_xx, e_yy, e_xy = blurred.split(c, dim=1)
        mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
        c1, c2 = 0.01**2, 0.03**2
        ssim_map = ((2 * mu_xy + c1) * (2 * (e_xy - mu_xy) + c2)) / ((mu_xx + mu_yy + c1) * (e_xx - mu_xx + e_yy - mu_yy + c2))
        return ssim_map.mean()


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
        if hp.init == "hull":
            if masks0 is None:
                raise ValueError("init='hull' needs masks; use init='box' with init_bbox for scenes without masks")
            n = int(hp.init_points or 2000)
            cap = self.gaussian_cap(views)
            n = n if cap is None else max(1, min(n, cap))
            pts = visual_hull_points(cams, masks0, n, bbox=(lo, hi), resolution=hp.hull_resolution, seed=self.seed)
            colors = _colors_from_views(pts, cams, views.images[0].cpu(), masks0)
        else:
            n = int(hp.init_points or gic_num_points(lo.numpy(), hi.numpy()))
            pts = random_box_points(lo, hi, n, seed=self.seed)
            colors = None
        self.gaussians.init_from_points(pts, colors, opacity=hp.init_opacity)
        self.extent.fill_(0.5 * camera_extent(cams))
        t = views.times.cpu()
        self.deformation.set_normalization(lo, hi, float(t.min()), float(t.max()))
        self._initialized = True
        log.info("stage 0: %d initial Gaussians (%s init), at most %s, box %s..%s m", n, hp.init, self.gaussian_cap(views),
                 lo.tolist(), hi.tolist())

    # ------------------------------------------------------------------ queries

    def gaussians_at(self, time: float | torch.Tensor | None = None, sh_degree: Optional[int] = None) -> Gaussians:
        """The Gaussians at ``time`` (seconds; None: canonical, no deformation), differentiable."""
        g = self.gaussians
        if time is None:
            return g.gaussians(sh_degree=sh_degree)
        d = self.deformation(g.means, torch.as_tensor(time, dtype=g.means.dtype, device=g.means.device))
        return g.gaussians(means=g.means + d.xyz, d_log_scales=d.log_scales, d_quats=d.quats, sh_degree=sh_degree)

    def centers_at(self, times: Sequence[float] | torch.Tensor) -> torch.Tensor:
        """(T, N, 3) Gaussian centres ``x_0 + Δ(x_0, t)`` at each time (no grad)."""
        with torch.no_grad():
            g = self.gaussians
            tt = torch.as_tensor(times, dtype=g.means.dtype, device=g.means.device).reshape(-1)
            out = []
            for t in tt:  # one time at a time keeps memory at O(N)
                out.append(g.means + self.deformation(g.means, t).xyz)
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
            means = g.means + d.xyz
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
        self.gaussians.resize_(n)
        self.step = int(state.get("step", 0))
        self._initialized = bool(state.get("initialized", True))
        self.reset_guard = OpacityResetGuard(disabled=bool(state.get("opacity_resets_disabled", False)),
                                             reverted=list(state.get("opacity_resets_reverted", [])))
        self._views = None


def _colors_from_views(points: torch.Tensor, cameras: Cameras, images: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """(N, 3) mean image colour at each point's projection over the views whose mask covers it."""
    uv, z = cameras.project(points)
    W, H = cameras.width, cameras.height
    u = torch.floor(uv[..., 0]).long()
    v = torch.floor(uv[..., 1]).long()
    ok = (z > cameras.near) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    ui, vi = u.clamp(0, W - 1), v.clamp(0, H - 1)
    ci = torch.arange(len(cameras))[:, None].expand_as(ui)
    ok = ok & (masks[ci, vi, ui] > 0.5)
    col = images[ci, vi, ui] * ok[..., None]
    cnt = ok.sum(0)[:, None]
    return torch.where(cnt > 0, col.sum(0) / cnt.clamp_min(1), torch.full_like(col[0], 0.5)).clamp(0.02, 0.98)


# ====================================================================== checkpoints and a one-call fit


def fit_stage0(
    data: Stage0DataModule,
    module: Optional[Gaussians4DModule] = None,
    *,
    out_dir: Optional[str | Path] = None,
    checkpoint_every: Optional[int] = None,
    ckpt_path: Optional[str | Path] = None,
    stop_at: Optional[int] = None,
    accelerator: str = "auto",
    progress_bar: bool = False,
    logger: Any = None,
    **module_kwargs: Any,
) -> Gaussians4DModule:
    """Train stage 0 with a ready-configured Lightning ``Trainer``.

    Args:
        data: The training views.
        module: A module to train (default: ``Gaussians4DModule(**module_kwargs)``).
        out_dir: Where checkpoints go (``step_XXXXXX.ckpt``, ``last.ckpt``); None: no checkpoints.
        checkpoint_every: Iterations between checkpoints.
        ckpt_path: Resume from this checkpoint.
        stop_at: Stop after this iteration (the schedule is unchanged, so a later resume
            continues it).
        accelerator: Lightning accelerator (``"cpu"``, ``"gpu"``, ``"auto"``).
        progress_bar: Show the stage-0 progress bar (``stage 0``, iteration/total, ETA, loss;
            drawn only on a terminal, see :func:`toolkit.progress.stage0_progress_bar`).
        logger: Lightning logger(s) for the ``train/*`` metrics (loss, L1, SSIM, PSNR in dB,
            Gaussian count, iteration; every ``schedule.log_every`` iterations). Default: with
            ``out_dir``, CSV under ``out_dir/logs/version_K`` (and TensorBoard when installed, as
            the physics stages do); without, none. ``False`` turns logging off.

    Returns:
        The trained module.
    """
    module = module if module is not None else Gaussians4DModule(**module_kwargs)
    module.stop_at = stop_at
    callbacks: list[pl.Callback] = []
    if out_dir is not None:
        callbacks.append(Stage0Checkpoint(out_dir, checkpoint_every))
    if progress_bar:
        from toolkit.progress import stage0_progress_bar

        callbacks.append(stage0_progress_bar())
    if logger is None:
        from toolkit.physics.fit import default_loggers

        logger = default_loggers(out_dir) if out_dir is not None else False
    trainer = pl.Trainer(
        accelerator=accelerator,
        devices=1,
        max_epochs=1,
        max_steps=-1,
        logger=logger,
        log_every_n_steps=1,  # the module logs every schedule.log_every iterations itself
        enable_checkpointing=False,
        enable_model_summary=False,
        enable_progress_bar=progress_bar,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        callbacks=callbacks,
    )
    trainer.fit(module, datamodule=data, ckpt_path=None if ckpt_path is None else str(ckpt_path))
    return module

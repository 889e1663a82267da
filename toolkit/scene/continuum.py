"""Gaussian-informed continuum: simulation particles and per-frame surface points from 4D Gaussians.

Procedure (GIC ``train_dynamic.py::prepare_gt``; facts, re-implemented), for every frame ``t``:

1. Take the Gaussians at ``t``; drop degenerate ones (non-finite values, zero quaternions,
   standard deviation above ``max_scale``) so that nothing downstream can blow up, and render
   every camera in one call (alpha and depth).
2. Keep the Gaussian centres with opacity above ``opacity_threshold`` that project, in every
   view, inside the image and onto a rendered pixel (alpha > ``alpha_threshold``). Their bounding
   box padded by ``grid_size`` is the working box.
3. **Carve** a fine candidate lattice (spacing ``grid_size / 2**candidate_level``; default /16,
   the final lattice; GIC: /32, see :class:`ContinuumConfig`):
   a candidate survives when, in every view, it projects inside the image, onto the object mask
   (the ground-truth mask ``> mask_threshold`` and rendered alpha ``> alpha_threshold``; rendered
   alpha ``> 0.5`` when there are no masks) and *behind* the rendered depth there (camera ``z``
   larger than the depth + ``depth_margin``; GIC's alpha-normalized depth,
   ``carve_depth="expected"``, or that of the Gaussians rendered opaque, ``"opaque"``).
4. **Rasterize** the surviving candidates and the kept Gaussians into an occupancy volume at
   ``grid_size / 2`` (a candidate sets the voxel holding it, or every voxel of its cell when its
   lattice is coarser than the volume's; a Gaussian sets the voxel holding its centre, GIC's
   ``centre_stamp="voxel"``, which grows every face by about 0.75 voxel, or with
   ``centre_stamp="ellipsoid"`` the voxels whose centres lie inside its 1-sigma ellipsoid and
   every view's silhouette: :mod:`toolkit.scene.continuum_stamp`).
5. **Smooth coarse-to-fine**: for each finer level ``i = 2 .. final_level`` (spacing
   ``grid_size / 2**i``; GIC: down to /16), upsample trilinearly, blur with a 3x3x3 box filter,
   zero values below 0.5, and set the voxels holding points back to 1; then repeat
   blur / threshold / re-stamp ``n_smooth`` times (GIC: 20) at the finest level.
6. **Threshold**: ``density = blur(volume)``; interior voxels have ``density >= density_min``;
   surface voxels are interior voxels whose twice-blurred density is in ``(0, density_max)``
   (GIC PAC-NeRF: 0.5 and 0.7). Interior voxel centres of the first frame are the simulation
   particles (each of volume ``spacing^3``); surface voxel centres of every frame are the
   pseudo-ground-truth point sets of the geometric loss.
7. **Ground** (not in GIC; ``ground_clip``, on when a ground plane is given): nothing below the
   dataset's ground is object, in any frame, and the first frame's particles carried by the
   Gaussians' motion to a frame where the object lies on the ground must stay above it
   (:mod:`toolkit.scene.continuum_ground`): the downward-looking views never carve the underside.

The surfaces come from the fitted model only; the dataset's ground-truth clouds are for
evaluation and never enter here.

Guards: besides (1), centres far outside the bulk of the others are ignored (counted in the
stats), and the candidate lattice and the volume are capped (``max_candidates``,
``max_voxels``): a too-fine setting for the box is coarsened by powers of two (reported in the
stats) instead of exhausting memory or time; a box too large even for the coarsest level is a
clear error. Everything is in metres, on the model's device.
"""

from __future__ import annotations

import logging
import math
import time as _time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from renderers import get_renderer
from renderers.base import Gaussians, Renderer
from toolkit.cameras import Cameras
from toolkit.scene.continuum_stamp import box_blur as _box_blur
from toolkit.scene.continuum_ground import Ground, above_ground, carve_first_frame
from toolkit.scene.continuum_stamp import density_volume
from toolkit.settings import DictSettings

__all__ = ["ContinuumConfig", "Continuum", "build_continuum", "sanitize_gaussians", "density_volume", "why_empty"]

log = logging.getLogger(__name__)


@dataclass
class ContinuumConfig(DictSettings):
    settings_name = "continuum settings"

    """Settings of :func:`build_continuum` (defaults: GIC's PAC-NeRF configs, ``physics`` block).

    Attributes:
        grid_size: Coarse grid spacing, metres (GIC ``density_grid_size`` 0.1; Spring-Gaus 0.07).
        candidate_level: Candidates at ``grid_size / 2**candidate_level`` on a lattice aligned with
            the volume's (GIC: 5, i.e. twice finer than the volume; rasterizing the finer lattice
            by rounding dilates the shape by about half a voxel: +47 % volume on a test torus
            against +2 % with 4, so the default carves the final lattice itself).
        final_level: Final volume spacing ``grid_size / 2**final_level`` (GIC 4).
        n_smooth: Blur / threshold / re-stamp passes at the final level (GIC 20).
        centre_stamp: How a kept Gaussian marks the volume: ``"voxel"`` (default, GIC) sets
            the vertex nearest its centre, which grows every face by about 0.75 voxel;
            ``"ellipsoid"`` sets the lattice vertices inside its 1-sigma ellipsoid and every
            view's silhouette (:mod:`toolkit.scene.continuum_stamp`). The two defaults' errors
            partly cancel on real stage-0 models (``docs/results/continuum_volume.md``).
        density_min: Interior threshold (GIC ``density_min_th`` 0.5; Spring-Gaus 0.67).
        density_max: Surface upper threshold (GIC ``density_max_th`` 0.7; Spring-Gaus 0.8).
        opacity_threshold: Centres with lower opacity are ignored (GIC 0.01).
        mask_threshold: Ground-truth mask value above which a pixel is object.
        alpha_threshold: Rendered alpha above which a pixel is covered (GIC: rgb != 0 / > 1/255).
        depth_margin: Candidates must be this far behind the rendered depth, metres.
        carve_depth: The depth of the carving test: ``"expected"`` (default, GIC) is the
            alpha-normalized rendered depth, which lies behind the front surface where the
            Gaussians are semi-transparent, so the carving removes body near that surface (GIC's
            nearest-vertex stamping adds about as much back elsewhere); ``"opaque"`` renders every
            Gaussian above ``opacity_threshold`` opaque, so the depth is that of the first
            Gaussians along the ray (faint floaters then hide what lies behind them).
        max_scale: Gaussians with a larger standard deviation are dropped, metres (None:
            ``grid_size``).
        min_log_scale: Log-scales are clamped from below at this value (near-singular guard).
        max_candidates: Cap on the candidate lattice size (coarsened by 2 until below).
        max_voxels: Cap on the final volume size (final level lowered until below).
        chunk: Points per projection batch.
        ground_clip: With a ground plane given to :func:`build_continuum`, nothing below it is
            object: per frame, lattice points and centres below the plane are dropped, and the
            first frame's particles are carried through the clip by their nearest Gaussians and
            dropped where a frame puts them more than one spacing below it
            (:mod:`toolkit.scene.continuum_ground`; not in GIC, whose downward-looking views
            leave the underside of the visual hull uncarved). False: GIC's procedure.
    """

    grid_size: float = 0.1
    candidate_level: int = 4
    final_level: int = 4
    n_smooth: int = 20
    centre_stamp: str = "voxel"
    carve_depth: str = "expected"
    density_min: float = 0.5
    density_max: float = 0.7
    opacity_threshold: float = 0.01
    mask_threshold: float = 0.5
    alpha_threshold: float = 1.0 / 255.0
    depth_margin: float = 0.0
    max_scale: Optional[float] = None
    min_log_scale: float = -20.0
    max_candidates: int = 1 << 23
    max_voxels: int = 1 << 24
    chunk: int = 1 << 20
    ground_clip: bool = True

    def __post_init__(self) -> None:
        if self.centre_stamp not in ("ellipsoid", "voxel"):
            raise ValueError(f"continuum centre_stamp must be 'ellipsoid' or 'voxel', got {self.centre_stamp!r}")
        if self.carve_depth not in ("expected", "opaque"):
            raise ValueError(f"continuum carve_depth must be 'expected' or 'opaque', got {self.carve_depth!r}")
        if not isinstance(self.ground_clip, bool):
            raise ValueError(f"continuum ground_clip must be true or false, got {self.ground_clip!r}")



@dataclass
class Continuum:
    """Particles and per-frame surface points.

    Attributes:
        particles: (N, 3) float32 interior voxel centres at the first frame, metres (CPU).
        particle_volume: Volume of one particle, ``spacing^3``, m^3.
        surfaces: Per frame, (M_t, 3) float32 surface points, metres (CPU).
        spacing: Final lattice spacing, metres.
        stats: Counts and settings per frame (``frames``: list of dicts) and totals.
    """

    particles: torch.Tensor
    particle_volume: float
    surfaces: list[torch.Tensor]
    spacing: float
    stats: dict = field(default_factory=dict)

    @property
    def volume(self) -> float:
        """Total particle volume, m^3."""
        return float(self.particles.shape[0]) * self.particle_volume

    def summary(self) -> str:
        m = [int(s.shape[0]) for s in self.surfaces]
        return (
            f"continuum: {self.particles.shape[0]} particles (spacing {self.spacing * 1e3:.2f} mm, volume "
            f"{self.volume * 1e6:.1f} cm^3), surface points per frame {min(m) if m else 0}..{max(m) if m else 0} "
            f"over {len(m)} frames, {self.stats.get('dropped_gaussians', 0)} degenerate Gaussians dropped"
        )

    def save(self, out_dir: str | Path) -> Path:
        """Write ``particles.ply``, ``surface_XXX.ply`` (binary PLY points) and ``stats.json``
        (:attr:`stats`: what each step kept, per frame) into ``out_dir``."""
        from toolkit.atomic import write_json
        from toolkit.data.ply import write_ply_points

        out = Path(out_dir)
        write_ply_points(out / "particles.ply", self.particles.numpy())
        for i, s in enumerate(self.surfaces):
            write_ply_points(out / f"surface_{i:03d}.ply", s.numpy())
        write_json(out / "stats.json", self.stats)
        return out

    def empty_reason(self) -> str:
        """Which step of the procedure left the first frame without particles, from its stats
        (empty string when there are particles)."""
        if self.particles.shape[0] > 0:
            return ""
        frames = self.stats.get("frames") or [{}]
        return why_empty(frames[0], self.stats.get("config") or {})


def why_empty(st: dict, config: dict) -> str:
    """One sentence naming the step that emptied a frame, from its entry of ``Continuum.stats["frames"]``."""
    if st.get("gaussians", 1) == 0:
        return (f"all {st.get('dropped_gaussians', 0)} Gaussians were degenerate (non-finite, or a standard deviation "
                f"above max_scale)")
    if st.get("centres", 1) == 0 and st.get("centres_below_ground", 0) > 0:
        return (f"all {st['centres_below_ground']} Gaussian centres covered in every view lie below the dataset's ground "
                f"plane: check the scene's world (ground_point, ground_normal), or set continuum ground_clip false")
    if st.get("centres", 1) == 0:
        return (f"no Gaussian centre with opacity above {config.get('opacity_threshold', 0.01)} projects onto a rendered "
                f"pixel in every training view: the views disagree on where the object is")
    if st.get("carved", 1) == 0:
        return (f"none of the {st.get('candidates', 0)} lattice points is inside every view's mask and behind its rendered "
                f"depth")
    return (f"{st.get('carved', 0)} of {st.get('candidates', 0)} lattice points survived the carving and "
            f"{st.get('centres', 0)} Gaussian centres were kept, but too few lie together for the smoothed density to "
            f"reach density_min {config.get('density_min', 0.5)}")


@torch.no_grad()
def sanitize_gaussians(g: Gaussians, max_scale: float, min_log_scale: float = -20.0) -> tuple[Gaussians, int]:
    """Drop Gaussians that are non-finite, have a zero quaternion or a standard deviation above
    ``max_scale`` (metres); clamp log-scales from below. Returns ``(kept, n_dropped)``."""
    kept, idx = _sanitize(g, max_scale, min_log_scale)
    return kept, int(len(g) - idx.numel())


def _sanitize(g: Gaussians, max_scale: float, min_log_scale: float) -> tuple[Gaussians, torch.Tensor]:
    """:func:`sanitize_gaussians`, returning the kept Gaussians' indices in ``g``."""
    rows = lambda t: t.reshape(t.shape[0], -1)  # noqa: E731
    ok = torch.ones(len(g), dtype=torch.bool, device=g.means.device)
    for t in (g.means, g.log_scales, g.quats, g.opacity_logits, g.colors, g.sh):
        if t is not None:
            ok &= torch.isfinite(rows(t)).all(dim=1)
    ls = torch.nan_to_num(g.log_scales, nan=0.0, posinf=1e30, neginf=min_log_scale).clamp_min(min_log_scale)
    ok &= ls.amax(dim=1) <= math.log(max_scale)
    ok &= torch.nan_to_num(g.quats).norm(dim=-1) > 1e-12
    idx = ok.nonzero()[:, 0]
    kept = Gaussians(
        means=g.means[idx],
        log_scales=ls[idx],
        quats=g.quats[idx],
        opacity_logits=g.opacity_logits[idx],
        colors=None if g.colors is None else g.colors[idx],
        sh=None if g.sh is None else g.sh[idx],
    )
    return kept, idx


def _project_lookup(cams: Cameras, p: torch.Tensor):
    uv, z = cams.project(p)  # (C, P, 2), (C, P)
    u = torch.floor(uv[..., 0])
    v = torch.floor(uv[..., 1])
    inside = (z > cams.near) & (u >= 0) & (u < cams.width) & (v >= 0) & (v < cams.height)
    ui = u.clamp(0, cams.width - 1).long()
    vi = v.clamp(0, cams.height - 1).long()
    ci = torch.arange(len(cams), device=p.device)[:, None].expand_as(ui)
    return inside, ci, vi, ui, z


def _frame_gaussians(model: Any, index: int, t: Optional[float]) -> Gaussians:
    if isinstance(model, Gaussians):
        return model
    if hasattr(model, "gaussians_at"):
        return model.gaussians_at(t)
    if isinstance(model, (list, tuple)):
        return model[index]
    if callable(model):
        return model(t)
    raise TypeError(
        f"model must be a Gaussians4DModule (gaussians_at), Gaussians, a list of Gaussians per frame "
        f"or a callable time -> Gaussians; got {type(model).__name__}"
    )


@torch.no_grad()
def build_continuum(
    model: Any,
    cameras: Any,
    masks: Optional[torch.Tensor | np.ndarray] = None,
    times: Optional[Sequence[float] | torch.Tensor] = None,
    *,
    frames: Optional[Sequence[int]] = None,
    config: ContinuumConfig | dict | None = None,
    renderer: Optional[str | Renderer] = None,
    device: Optional[torch.device | str] = None,
    ground: Optional[Ground] = None,
    lost_frames: Sequence[int] = (),
) -> Continuum:
    """Build simulation particles (first frame) and surface points (every frame) from Gaussians.

    Args:
        model: A :class:`toolkit.scene.stage0.Gaussians4DModule` (or anything with
            ``gaussians_at(time)``), static :class:`renderers.base.Gaussians`, a list of
            Gaussians per frame, or a callable ``time -> Gaussians``.
        cameras: The fitting cameras (C), or a :class:`toolkit.scene.stage0_data.TrainingViews`
            (then ``masks`` and ``times`` default to its own).
        masks: (T, C, H, W) (or (C, H, W) for one frame) object masks in [0, 1]; None: use the
            rendered alpha alone.
        times: (T,) frame times in seconds (None: one frame per mask frame, time None).
        frames: Indices into the T frames to process (default all); the first one gives the
            particles, and ``surfaces`` follows this order.
        config: :class:`ContinuumConfig` or a dict of its fields.
        renderer: Renderer name or instance (default: the model's, else ``"warp"``/``"torch"``).
        device: Where to compute (default: the Gaussians' device).
        ground: ``(point, normal)`` of the ground plane in the cameras' frame (metres; the normal
            points into free space), e.g. the dataset's :class:`toolkit.data.world.World`. With
            ``config.ground_clip`` (default) nothing below it becomes object, and the first
            frame's particles are carved by every frame of the clip
            (:mod:`toolkit.scene.continuum_ground`). None: no ground (GIC's procedure).
        lost_frames: Frames (indices into the T frames) in which stage 0 lost the object; their
            Gaussians do not carve the first frame's particles.

    Returns:
        :class:`Continuum`; ``stats`` reports per frame the Gaussians used and dropped, the
        candidate and final spacings, candidates kept, centres kept, particles and surface points.
    """
    cfg = ContinuumConfig.from_dict(config)
    t_start = _time.perf_counter()
    if hasattr(cameras, "cameras") and hasattr(cameras, "images"):  # TrainingViews
        views = cameras
        cameras = views.cameras
        masks = views.masks if masks is None else masks
        times = views.times if times is None else times
    if not isinstance(cameras, Cameras):
        raise TypeError(f"cameras must be Cameras or TrainingViews, got {type(cameras).__name__}")
    if masks is not None:
        masks = masks if isinstance(masks, torch.Tensor) else torch.as_tensor(np.asarray(masks))
        masks = masks.float()
        if masks.ndim == 3:
            masks = masks[None]
        if masks.ndim != 4 or masks.shape[1:] != (len(cameras), cameras.height, cameras.width):
            raise ValueError(
                f"masks must have shape (T, C, H, W) with C, H, W = {len(cameras)}, {cameras.height}, "
                f"{cameras.width}; got {tuple(masks.shape)}"
            )
    if times is None:
        n_frames = masks.shape[0] if masks is not None else (len(model) if isinstance(model, (list, tuple)) else 1)
        time_list: list[Optional[float]] = [None] * n_frames
    else:
        time_list = [float(t) for t in torch.as_tensor(times).reshape(-1).tolist()]
        if masks is not None and masks.shape[0] != len(time_list):
            raise ValueError(f"{len(time_list)} times but masks for {masks.shape[0]} frames")
    frame_ids = list(range(len(time_list))) if frames is None else [int(f) for f in frames]
    if not frame_ids or any(not 0 <= f < len(time_list) for f in frame_ids):
        raise ValueError(f"frames must be a non-empty list of indices in 0..{len(time_list) - 1}, got {frames}")
    if renderer is None:
        renderer = getattr(model, "renderer", None)
        if renderer is None:
            from toolkit.scene.stage0 import default_renderer_name

            renderer = default_renderer_name()
    if isinstance(renderer, str):
        renderer = get_renderer(renderer)
    max_scale = cfg.max_scale if cfg.max_scale is not None else cfg.grid_size

    floor = ground if cfg.ground_clip else None
    particles = torch.zeros(0, 3)
    spacing = cfg.grid_size / 2**cfg.final_level
    surfaces: list[torch.Tensor] = []
    frame_stats: list[dict] = []
    dropped_total = 0
    for order, fi in enumerate(frame_ids):
        t = time_list[fi]
        g_raw = _frame_gaussians(model, fi, t)
        dev = torch.device(device) if device is not None else g_raw.means.device
        g, usable = _sanitize(g_raw.detach().to(dev), max_scale, cfg.min_log_scale)
        n_dropped = len(g_raw) - usable.numel()
        dropped_total += n_dropped
        cams = cameras.to(dev)
        st: dict = {"frame": fi, "time": t, "gaussians": len(g), "dropped_gaussians": n_dropped}
        empty = torch.zeros(0, 3)
        if len(g) == 0:
            log.warning("continuum frame %d: no usable Gaussians", fi)
            surfaces.append(empty)
            st.update(particles=0, surface_points=0)
            frame_stats.append(st)
            continue
        out = renderer(g, cams)
        alpha = out.alpha
        depth = out.expected_depth()
        if cfg.carve_depth == "opaque":
            solid = torch.where(torch.sigmoid(g.opacity_logits) > cfg.opacity_threshold, 20.0, -20.0)
            depth = renderer(g.replace(opacity_logits=solid), cams).expected_depth()
        covered = alpha > cfg.alpha_threshold
        if masks is not None:
            obj = covered & (masks[fi].to(dev) > cfg.mask_threshold)
        else:
            obj = alpha > 0.5

        # step 2: centres
        opac = torch.sigmoid(g.opacity_logits)
        keep = (opac > cfg.opacity_threshold).nonzero().squeeze(1)
        inside, ci, vi, ui, _ = _project_lookup(cams, g.means[keep])
        keep = keep[(inside & covered[ci, vi, ui]).all(0)]
        up = above_ground(g.means[keep], floor)
        st["centres_below_ground"] = int((~up).sum())
        keep = keep[up]
        cent = g.means[keep]
        st["centres"] = int(cent.shape[0])
        if cent.shape[0] == 0:
            log.warning("continuum frame %d: no Gaussian centre is covered in every view", fi)
            surfaces.append(empty)
            st.update(particles=0, surface_points=0)
            frame_stats.append(st)
            continue
        # outlier guard: centres far outside the bulk (beyond the 1-99 % quantile box widened by
        # half its size) would blow up the working box; they are dropped and counted
        q = torch.quantile(cent, torch.tensor([0.01, 0.99], device=dev, dtype=cent.dtype), dim=0)
        pad = 0.5 * (q[1] - q[0]) + cfg.grid_size
        bulk = ((cent >= q[0] - pad) & (cent <= q[1] + pad)).all(1)
        st["outlier_centres"] = int((~bulk).sum())
        cent, keep = cent[bulk], keep[bulk]
        lo = cent.min(0).values - cfg.grid_size
        hi = cent.max(0).values + cfg.grid_size
        coarse = math.prod(int(round(float(b) / (cfg.grid_size / 2))) + 1 for b in (hi - lo))
        if coarse > cfg.max_voxels:
            raise ValueError(
                f"continuum frame {fi}: the Gaussians span {(hi - lo).tolist()} m, {coarse} voxels at "
                f"grid_size / 2 = {cfg.grid_size / 2} m (max_voxels {cfg.max_voxels}); raise grid_size"
            )

        # step 3: carve candidates, slab by slab along x
        # (vertex lattice lo + k h_c, aligned with the density volume's lattice)
        h_c = cfg.grid_size / 2**cfg.candidate_level
        while math.prod(int(round(float(e) / h_c)) + 1 for e in (hi - lo)) > cfg.max_candidates:
            h_c *= 2.0
        dims_c = [int(round(float(e) / h_c)) + 1 for e in (hi - lo)]
        ys = lo[1] + torch.arange(dims_c[1], device=dev, dtype=torch.float32) * h_c
        zs = lo[2] + torch.arange(dims_c[2], device=dev, dtype=torch.float32) * h_c
        yz = torch.stack(torch.meshgrid(ys, zs, indexing="ij"), -1).reshape(-1, 2)
        slab = max(1, cfg.chunk // max(1, yz.shape[0]))
        kept = []
        for x0 in range(0, dims_c[0], slab):
            xs = lo[0] + torch.arange(x0, min(x0 + slab, dims_c[0]), device=dev, dtype=torch.float32) * h_c
            p = torch.cat([xs[:, None, None].expand(-1, yz.shape[0], 1), yz[None].expand(xs.shape[0], -1, -1)], -1).reshape(-1, 3)
            inside, ci, vi, ui, z = _project_lookup(cams, p)
            ok = inside & obj[ci, vi, ui] & (z > depth[ci, vi, ui] + cfg.depth_margin)
            ok = ok.all(0) & above_ground(p, floor)
            kept.append(p[ok])
        carved = torch.cat(kept) if kept else torch.zeros(0, 3, device=dev)
        st.update(candidate_spacing=h_c, candidates=int(math.prod(dims_c)), carved=int(carved.shape[0]))

        # steps 4-5: density volume, coarse to fine (with a voxel cap)
        level = cfg.final_level
        while level > 1 and math.prod(int(round(float(b) / (cfg.grid_size / 2**level))) + 1 for b in (hi - lo)) > cfg.max_voxels:
            level -= 1
        ell = (g.log_scales[keep], g.quats[keep]) if cfg.centre_stamp == "ellipsoid" else None

        def in_silhouettes(p: torch.Tensor) -> torch.Tensor:
            inside, ci, vi, ui, _ = _project_lookup(cams, p)
            return (inside & obj[ci, vi, ui]).all(0)

        vol, h = density_volume(cent, lo, hi, cfg.grid_size, max(level, 1), cfg.n_smooth, cells=carved, cell_size=h_c,
                                ellipsoids=ell, keep_vertex=in_silhouettes)

        # step 6: thresholds
        density = _box_blur(vol)
        interior = density >= cfg.density_min
        smooth2 = _box_blur(density)
        surface = (smooth2 > 0) & (smooth2 < cfg.density_max) & interior
        surf_pts = surface.nonzero().float() * h + lo
        surf_pts = surf_pts[above_ground(surf_pts, floor, slack=h / 2)].float().cpu()
        surfaces.append(surf_pts)
        st.update(spacing=h, final_level=level, surface_points=int(surf_pts.shape[0]), interior_voxels=int(interior.sum()))
        if order == 0:
            inner = interior.nonzero().float() * h + lo
            inner = inner[above_ground(inner, floor, slack=h / 2)]
            spacing = h
            if floor is not None and inner.shape[0]:
                skip = {fi, *(int(x) for x in lost_frames)}
                others = [f for f in range(len(time_list)) if f not in skip]
                inner, st["ground_carve"] = carve_first_frame(inner, g_raw, usable[keep], others, floor, h,
                                                              lambda f: _frame_gaussians(model, f, time_list[f]))
            particles = inner.float().cpu()
            st["particles"] = int(particles.shape[0])
        frame_stats.append(st)
        log.info(
            "continuum frame %d: %d Gaussians (%d dropped), %d/%d candidates kept, %d interior voxels, %d surface points",
            fi, len(g), n_dropped, st["carved"], st["candidates"], st["interior_voxels"], st["surface_points"],
        )

    stats = {
        "frames": frame_stats,
        "n_particles": int(particles.shape[0]),
        "n_surface_points": [int(s.shape[0]) for s in surfaces],
        "dropped_gaussians": dropped_total,
        "spacing": spacing,
        "particle_volume": spacing**3,
        "volume": float(particles.shape[0]) * spacing**3,
        "seconds": _time.perf_counter() - t_start,
        "config": asdict(cfg),
    }
    result = Continuum(particles=particles, particle_volume=spacing**3, surfaces=surfaces, spacing=spacing, stats=stats)
    log.info(result.summary())
    return result


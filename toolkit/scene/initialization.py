"""Where the canonical Gaussians start: random points in a box, or a visual hull of the masks.

* :func:`random_box_points` is GIC's initialization (``scene/dataset_readers.py``): uniform
  points in the scene's bounding box, ``clip(prod(50 * extent), 1e4, 2e5)`` of them
  (:func:`gic_num_points`). GIC reads the box from a per-dataset config; here it can also come
  from the masks (:func:`mask_bounding_box`).
* :func:`visual_hull_points` samples points inside the visual hull: voxels whose centre projects
  inside the object mask of every view (shape from silhouette).

Cameras follow :mod:`toolkit.cameras` (OpenCV, world-to-camera, pixel ``(i, j)`` covers
``[i, i+1) x [j, j+1)``). Masks are (C, H, W) arrays/tensors in [0, 1], one per camera, at the
cameras' image size. Everything is in metres and runs on the masks' device.
"""

from __future__ import annotations

import math
from typing import Literal, Optional, Sequence

import numpy as np
import torch

from toolkit.cameras import Cameras

__all__ = [
    "colors_from_views",
    "camera_focus_point",
    "camera_extent",
    "grid_points",
    "carve",
    "mask_bounding_box",
    "visual_hull_points",
    "random_box_points",
    "gic_num_points",
]


def _as_masks(masks, cameras: Cameras) -> torch.Tensor:
    m = masks if isinstance(masks, torch.Tensor) else torch.as_tensor(np.asarray(masks))
    m = m.float()
    if m.ndim != 3 or m.shape[0] != len(cameras) or tuple(m.shape[1:]) != (cameras.height, cameras.width):
        raise ValueError(
            f"masks must have shape (C, H, W) = ({len(cameras)}, {cameras.height}, {cameras.width}), got {tuple(m.shape)}"
        )
    return m


def camera_focus_point(cameras: Cameras) -> torch.Tensor:
    """(3,) the point closest (least squares) to all optical axes, metres.

    Falls back towards the mean camera centre when the axes are (nearly) parallel.
    """
    c = cameras.centers.double().cpu()
    d = cameras.R.double().cpu()[:, 2, :]  # forward axis (camera +z) in world coordinates
    eye = torch.eye(3, dtype=torch.float64)
    P = eye[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(0) + 1e-6 * eye
    b = (P @ c[:, :, None]).sum(0)[:, 0] + 1e-6 * c.mean(0)
    return torch.linalg.solve(A, b).float()


def camera_extent(cameras: Cameras) -> float:
    """3DGS/GIC scene radius ("nerf++ normalization"): 1.1 x the largest distance of a camera
    centre from the cameras' mean centre, metres. GIC densifies with half of it."""
    c = cameras.centers.double()
    r = float((c - c.mean(0)).norm(dim=-1).max()) * 1.1
    if r <= 0:  # a single camera: use its distance to the focus point
        r = float((c[0] - camera_focus_point(cameras).double()).norm()) * 1.1
    return r


def grid_points(bbox_min, bbox_max, spacing: float, device=None) -> tuple[torch.Tensor, tuple[int, int, int]]:
    """Voxel-centre lattice covering a box.

    Args:
        bbox_min, bbox_max: (3,) box corners, metres.
        spacing: Voxel edge, metres.

    Returns:
        ``(points (X*Y*Z, 3) float32 in ij-order, (X, Y, Z))``; centre ``k`` along an axis is
        ``bbox_min + (k + 0.5) * spacing``.
    """
    lo = torch.as_tensor(bbox_min, dtype=torch.float32, device=device).reshape(3)
    hi = torch.as_tensor(bbox_max, dtype=torch.float32, device=device).reshape(3)
    dims = [max(1, int(math.ceil(float(hi[i] - lo[i]) / spacing))) for i in range(3)]
    axes = [lo[i] + (torch.arange(dims[i], dtype=torch.float32, device=lo.device) + 0.5) * spacing for i in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return pts, (dims[0], dims[1], dims[2])


def carve(
    cameras: Cameras,
    masks,
    points: torch.Tensor,
    *,
    threshold: float = 0.5,
    outside: Literal["carve", "keep"] = "carve",
    chunk: int = 1 << 20,
) -> torch.Tensor:
    """(P,) bool: points whose projection lies inside the mask (``> threshold``) in every view.

    Args:
        cameras: C cameras.
        masks: (C, H, W) object masks in [0, 1].
        points: (P, 3) world points, metres.
        threshold: Mask value above which a pixel is object.
        outside: What a view does with a point that projects outside its image or lies behind
            it: ``"carve"`` removes it (GIC), ``"keep"`` lets that view abstain.
        chunk: Points per projection batch (bounds memory).
    """
    m = _as_masks(masks, cameras).to(points.device) > threshold
    cams = cameras.to(points.device)
    W, H = cams.width, cams.height
    out = torch.empty(points.shape[0], dtype=torch.bool, device=points.device)
    for s in range(0, points.shape[0], chunk):
        p = points[s : s + chunk]
        uv, z = cams.project(p)  # (C, P, 2), (C, P)
        u = torch.floor(uv[..., 0])
        v = torch.floor(uv[..., 1])
        inside = (z > cams.near) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        ui = u.clamp(0, W - 1).long()
        vi = v.clamp(0, H - 1).long()
        cam_idx = torch.arange(len(cams), device=p.device)[:, None].expand_as(ui)
        hit = m[cam_idx, vi, ui]
        ok = (inside & hit) if outside == "carve" else (~inside | hit)
        out[s : s + chunk] = ok.all(dim=0)
    return out


def _occupied_bounds(points: torch.Tensor, keep: torch.Tensor, pad: float) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
    if not bool(keep.any()):
        return None
    sel = points[keep]
    return sel.min(0).values - pad, sel.max(0).values + pad


def mask_bounding_box(
    cameras: Cameras,
    masks,
    *,
    resolution: int = 64,
    margin: float = 0.05,
    search_half_size: Optional[float] = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Axis-aligned bounding box of the visual hull of the masks.

    A cube around :func:`camera_focus_point` (half-size: what the cameras see at that distance,
    unless ``search_half_size`` is given) is carved at ``resolution`` voxels per side; the
    occupied bounds are carved again at the same resolution for precision.

    Args:
        cameras: C cameras.
        masks: (C, H, W) object masks.
        resolution: Voxels along the longest side per pass.
        margin: Fractional padding of the result (of its largest side).
        search_half_size: Half-size of the first search cube, metres.

    Returns:
        ``(bbox_min, bbox_max)``, (3,) float32 tensors on the masks' device, metres.

    Raises:
        ValueError: The masks have no common 3D support (empty visual hull).
    """
    m = _as_masks(masks, cameras)
    dev = m.device
    focus = camera_focus_point(cameras).to(dev)
    if search_half_size is None:
        dist = (cameras.centers.to(dev) - focus).norm(dim=-1)
        tan_half = torch.maximum(0.5 * cameras.width / cameras.fx, 0.5 * cameras.height / cameras.fy).to(dev)
        search_half_size = float((dist * tan_half).max()) * 1.2
    if not search_half_size > 0:  # one camera (or parallel axes): no point where the views meet
        raise ValueError(
            f"the {len(cameras)} camera(s) give no point where their optical axes meet, so the masks cannot "
            "bound the object: stage 0 needs at least 2 cameras looking at it from different directions"
        )
    lo, hi = focus - search_half_size, focus + search_half_size
    for _ in range(2):
        spacing = float((hi - lo).max()) / resolution
        pts, _ = grid_points(lo, hi, spacing, device=dev)
        bounds = _occupied_bounds(pts, carve(cameras, m, pts), spacing)
        if bounds is None:
            raise ValueError(
                "the masks have an empty visual hull: no point of the search box projects inside the "
                "object mask of every camera (check the masks, the camera poses, or pass a bounding box)"
            )
        lo, hi = bounds
    pad = margin * float((hi - lo).max())
    return lo - pad, hi + pad


def visual_hull_points(
    cameras: Cameras,
    masks,
    n: int,
    *,
    bbox: Optional[tuple[Sequence[float], Sequence[float]]] = None,
    resolution: int = 64,
    seed: int = 0,
) -> torch.Tensor:
    """``n`` points sampled uniformly inside the visual hull of the masks.

    Args:
        cameras: C cameras.
        masks: (C, H, W) object masks.
        n: Number of points.
        bbox: Box to carve (default :func:`mask_bounding_box`).
        resolution: Voxels along the longest side of the box.
        seed: Seed of the sampling.

    Returns:
        (n, 3) float32 points on the masks' device: random occupied voxels, uniformly jittered
        inside the voxel.
    """
    m = _as_masks(masks, cameras)
    lo, hi = mask_bounding_box(cameras, m, resolution=resolution) if bbox is None else bbox
    lo = torch.as_tensor(lo, dtype=torch.float32, device=m.device)
    hi = torch.as_tensor(hi, dtype=torch.float32, device=m.device)
    spacing = float((hi - lo).max()) / resolution
    pts, _ = grid_points(lo, hi, spacing, device=m.device)
    occ = pts[carve(cameras, m, pts)]
    if occ.shape[0] == 0:
        raise ValueError("the visual hull of the masks is empty inside the given box")
    g = torch.Generator().manual_seed(int(seed))
    idx = torch.randint(0, occ.shape[0], (int(n),), generator=g)
    jitter = (torch.rand(int(n), 3, generator=g) - 0.5) * spacing
    return occ[idx.to(m.device)] + jitter.to(m.device)


def random_box_points(bbox_min, bbox_max, n: int, *, seed: int = 0, device=None) -> torch.Tensor:
    """(n, 3) float32 points uniform in the box ``[bbox_min, bbox_max]`` (GIC's initialization)."""
    lo = torch.as_tensor(bbox_min, dtype=torch.float32).reshape(3)
    hi = torch.as_tensor(bbox_max, dtype=torch.float32).reshape(3)
    g = torch.Generator().manual_seed(int(seed))
    return (torch.rand(int(n), 3, generator=g) * (hi - lo) + lo).to(device)


def gic_num_points(bbox_min, bbox_max) -> int:
    """GIC's number of initial points for a box: ``clip(prod(50 * (max - min)), 1e4, 2e5)``."""
    ext = np.asarray(bbox_max, dtype=np.float64) - np.asarray(bbox_min, dtype=np.float64)
    return int(min(max(float(np.prod(ext * 50.0)), 1e4), 2e5))


def colors_from_views(points: torch.Tensor, cameras: Cameras, images: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
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

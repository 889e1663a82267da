"""Loss-exclusion masks: pixels a dataset marks as "do not fit" (PAC-NeRF frame -2 images).

PAC-NeRF (xuan-li/PAC-NeRF ``train.py::load_data``) reads ``data/r_{cam}_-2.png`` and sets
``ray_mask_all[cam][alpha > 50] = 0``: those pixels of that camera drop out of the rendering loss
in every frame (the static, velocity and dynamic stages alike). Here the same rule gives per-camera
*keep weights* (1 = the pixel counts, 0 = excluded); image losses multiply both the rendering and
the target by them (:func:`apply_keep`), so an excluded pixel contributes nothing.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["EXCLUSION_META_KEY", "apply_keep", "exclusion_meta", "keep_weights", "physics_keep"]

#: ``PhysicsInput.meta`` key of the (C, H, W) uint8 keep weights (255 = pixel counts).
EXCLUSION_META_KEY = "exclusion_keep"


def keep_weights(scene, cameras: Optional[Sequence[int]] = None, size: Optional[tuple[int, int]] = None,
                 downscale: int = 1) -> Optional[torch.Tensor]:
    """(C, H, W) float32 keep weights in [0, 1] of ``cameras`` (default all), or None when the
    scene has no exclusion masks.

    Args:
        scene: a :class:`~toolkit.data.scene.MultiViewScene`.
        cameras: scene camera indices (0-based).
        size: (height, width) to area-resample to; else the images' size divided by ``downscale``
            (the same box filter and cropping as :func:`toolkit.physics.inputs.load_all_images`).
        downscale: integer factor, used when ``size`` is None.
    """
    if getattr(scene, "exclusion_mask_paths", None) is None:
        return None
    cams = list(range(scene.n_cameras)) if cameras is None else list(cameras)
    out = []
    for c in cams:
        excluded = scene.load_exclusion_mask(c).astype(np.float32)
        if size is None and downscale > 1:
            h, w = excluded.shape[0] // downscale * downscale, excluded.shape[1] // downscale * downscale
            excluded = excluded[:h, :w].reshape(h // downscale, downscale, w // downscale, downscale).mean((1, 3))
        t = torch.from_numpy(np.ascontiguousarray(excluded))
        if size is not None and tuple(t.shape) != tuple(size):
            t = F.interpolate(t[None, None], size=size, mode="area")[0, 0]
        out.append(1.0 - t)
    return torch.stack(out).float()


def apply_keep(render: torch.Tensor, target: torch.Tensor, keep: Optional[torch.Tensor]):
    """``(render * keep, target * keep)`` for (..., H, W, 3) images and (..., H, W) weights; the
    inputs unchanged when ``keep`` is None."""
    if keep is None:
        return render, target
    w = keep.to(render.device, render.dtype).unsqueeze(-1)
    return render * w, target * w


def exclusion_meta(scene, downscale: int = 1) -> dict:
    """``{EXCLUSION_META_KEY: (C, H, W) uint8 keep weights}`` for a physics input's ``meta``, or
    ``{}`` when the scene has no exclusion masks (the images' size after ``downscale``)."""
    keep = keep_weights(scene, downscale=downscale)
    if keep is None:
        return {}
    return {EXCLUSION_META_KEY: torch.round(keep.clamp(0, 1) * 255).to(torch.uint8)}


def physics_keep(meta: dict, cams) -> Optional[torch.Tensor]:
    """(len(cams), H, W) float32 keep weights of a physics input's cameras ``cams``, or None."""
    keep = (meta or {}).get(EXCLUSION_META_KEY)
    if keep is None:
        return None
    return keep[cams].float() / 255.0

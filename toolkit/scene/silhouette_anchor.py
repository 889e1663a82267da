"""A pull that keeps stage 0's Gaussians on the object's silhouettes when the images give no gradient.

When the deformation puts a frame's Gaussians where they overlap none of that frame's masks, the
photometric and alpha losses are flat in their position: nothing moves them back, and the frame
stays lost (:mod:`toolkit.scene.coverage`). This term gives every frame a gradient: the
opacity-weighted mean of the Gaussian centres, projected into each fitting camera, is drawn toward
the centroid of that camera's mask, beyond a dead zone of ``tolerance`` (a fraction of the image
size) so that a model on the object is not biased by the difference between a projected 3D mean
and a silhouette's 2D centroid (perspective, self-occlusion)::

    L_anchor = mean over cameras c of max(0, norm(P_c(x_mean) - m_c) / S - tolerance) ** 2

with ``P_c`` the projection into camera ``c``, ``x_mean`` the opacity-weighted mean centre,
``m_c`` the mask's centroid and ``S = max(W, H)`` pixels.
"""

from __future__ import annotations

import torch

__all__ = ["mask_centroids", "silhouette_anchor_loss"]


@torch.no_grad()
def mask_centroids(masks: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """(T, C, 2) centroid ``(u, v)`` in pixels (pixel ``(i, j)`` centred at ``(i + 0.5, j + 0.5)``,
    as :meth:`toolkit.cameras.Cameras.project`) of each mask's pixels above ``threshold``; NaN
    for an empty mask. ``masks``: (T, C, H, W)."""
    T, C, H, W = masks.shape
    m = (masks > threshold).to(torch.float32)
    area = m.sum((2, 3))
    u = (torch.arange(W, device=masks.device, dtype=torch.float32) + 0.5)
    v = (torch.arange(H, device=masks.device, dtype=torch.float32) + 0.5)
    cu = (m.sum(2) * u).sum(-1) / area
    cv = (m.sum(3) * v).sum(-1) / area
    out = torch.stack([cu, cv], -1)
    return torch.where(area[..., None] > 0, out, torch.full_like(out, float("nan")))


def silhouette_anchor_loss(means: torch.Tensor, opacity: torch.Tensor, cameras, centroids: torch.Tensor,
                           tolerance: float) -> torch.Tensor:
    """The term above for one frame (differentiable in ``means`` and ``opacity``).

    Args:
        means: (N, 3) Gaussian centres at the frame, metres.
        opacity: (N,) opacities in [0, 1] (weights of the mean).
        cameras: the C fitting :class:`~toolkit.cameras.Cameras`.
        centroids: (C, 2) the frame's mask centroids in pixels (NaN: no mask; that camera is skipped).
        tolerance: dead zone, as a fraction of ``max(width, height)``.

    Returns:
        A scalar; 0 when every camera sees the mean within the dead zone of its mask's centroid,
        or when no camera has a mask.
    """
    w = opacity.reshape(-1, 1).clamp_min(0.0)
    centre = (means * w).sum(0) / w.sum().clamp_min(1e-12)
    uv, z = cameras.project(centre[None])  # (C, 1, 2), (C, 1)
    valid = torch.isfinite(centroids).all(-1) & (z[:, 0] > 0)
    if not bool(valid.any()):
        return means.sum() * 0.0
    size = float(max(cameras.width, cameras.height))
    err = (uv[:, 0] - torch.nan_to_num(centroids)).norm(dim=-1) / size
    return (torch.relu(err - tolerance)[valid] ** 2).mean()

"""The silhouette anchor gives stage 0 a way back to the object when a frame's Gaussians overlap
no mask (where the image losses are flat): it is zero on the object, positive off it, and its
gradient moves the Gaussians toward the silhouettes (checked against finite differences)."""

from __future__ import annotations

import torch

from tests.test_stage0 import _ring_cameras, _sphere_gaussians, _sphere_masks
from toolkit.scene.silhouette_anchor import mask_centroids, silhouette_anchor_loss


def test_mask_centroids_are_pixel_centred_and_nan_for_empty_masks():
    masks = torch.zeros(2, 1, 8, 10)
    masks[0, 0, 2:4, 3:7] = 1.0  # rows 2-3, columns 3-6
    c = mask_centroids(masks)
    assert torch.allclose(c[0, 0], torch.tensor([5.0, 3.0]))  # u = (3.5 + 6.5) / 2, v = (2.5 + 3.5) / 2
    assert torch.isnan(c[1, 0]).all()


def test_the_anchor_is_zero_on_the_object_and_pulls_a_lost_frame_back():
    centre, radius = (0.0, 0.3, 0.0), 0.1
    cams = _ring_cameras(centre, size=48)[[0, 5, 10]]
    cent = mask_centroids(_sphere_masks(cams, centre, radius)[None])[0]
    g = _sphere_gaussians(500, radius, centre)
    w = torch.ones(len(g.means))
    assert float(silhouette_anchor_loss(g.means, w, cams, cent, tolerance=0.02)) == 0.0

    # 0.3 m off: no overlap with any mask, yet a loss and a gradient
    shift = torch.tensor([0.3, -0.1, 0.2], requires_grad=True)
    loss = silhouette_anchor_loss(g.means + shift, w, cams, cent, tolerance=0.02)
    loss.backward()
    assert float(loss.detach()) > 1e-3
    # the gradient agrees with central finite differences along each axis
    for k in range(3):
        e = torch.zeros(3)
        e[k] = 1e-4
        with torch.no_grad():
            fd = (silhouette_anchor_loss(g.means + shift + e, w, cams, cent, 0.02)
                  - silhouette_anchor_loss(g.means + shift - e, w, cams, cent, 0.02)) / 2e-4
        assert abs(float(fd) - float(shift.grad[k])) < 1e-3 * max(1.0, abs(float(fd))), (k, float(fd), float(shift.grad[k]))
    # plain gradient descent on the shift brings the body back near the object
    x = shift.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=0.01)
    for _ in range(300):
        opt.zero_grad()
        silhouette_anchor_loss(g.means + x, w, cams, cent, tolerance=0.02).backward()
        opt.step()
    assert float(x.norm()) < 0.05, x  # from 0.37 m off to within the dead zone's reach
    # a camera without a mask is skipped; none at all gives zero
    none = torch.full_like(cent, float("nan"))
    assert float(silhouette_anchor_loss(g.means + shift.detach(), w, cams, none, 0.02)) == 0.0

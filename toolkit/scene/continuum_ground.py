"""The ground bounds the continuum: nothing of the object lies below it, in any frame.

Training cameras that look down at a throw never see the object's underside, so the visual hull
that :func:`toolkit.scene.continuum.build_continuum` carves extends below the body: on small-size
stage-0 models the first frame's body sat 3-17 mm low (lowest point up to 37 mm below the true
underside; 38 mm on the paper-size torus), and once the object rests on the ground the surface
points of those frames reach several centimetres *into* the ground (17 % of the torus's points in
its last training frame), where no simulated body can follow them.

Two uses of the dataset's ground plane (``point``, unit ``normal`` into the free half-space,
dataset frame, metres) remove that without any threshold to tune:

- :func:`above_ground`: per frame, a lattice point or Gaussian centre below the plane is not
  object (voxel centres get half a voxel of slack: the voxel straddling the plane is kept).
- :func:`carve_through_time`: the first frame's particles are carried to every other frame by the
  motion of their nearest Gaussians (the stage-0 deformation, inverse-distance weighted); a
  particle carried more than one lattice spacing below the ground in some frame is removed. So the
  frames in which the object lies on the ground carve the underside the cameras never saw.
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Sequence

import torch

__all__ = ["Ground", "above_ground", "carve_first_frame", "carve_through_time", "height_above"]

Ground = tuple[Sequence[float], Sequence[float]]
"""(point, normal) of the ground plane, metres, dataset frame; the normal points into free space."""


def height_above(points: torch.Tensor, ground: Ground) -> torch.Tensor:
    """Signed height (m) of (..., 3) ``points`` above the plane ``ground`` (positive: free side)."""
    p = torch.as_tensor(ground[0], dtype=points.dtype).to(points.device)
    n = torch.as_tensor(ground[1], dtype=points.dtype).to(points.device)
    return (points - p) @ (n / n.norm())


def above_ground(points: torch.Tensor, ground: Optional[Ground], slack: float = 0.0) -> torch.Tensor:
    """(N,) bool: which of (N, 3) ``points`` lie at most ``slack`` metres below ``ground``
    (all True when ``ground`` is None)."""
    if ground is None:
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    return height_above(points, ground) >= -slack


@torch.no_grad()
def carve_through_time(
    particles: torch.Tensor,
    centres: torch.Tensor,
    centres_later: Sequence[torch.Tensor],
    ground: Ground,
    tolerance: float,
    k: int = 8,
    chunk: int = 4096,
) -> tuple[torch.Tensor, list[int], list[float]]:
    """Which first-frame particles stay above the ground when carried through the clip.

    Args:
        particles: (N, 3) first-frame particles, metres.
        centres: (G, 3) first-frame centres of the Gaussians that carry the motion.
        centres_later: per later frame, (G, 3) the same Gaussians' centres (same order).
        ground: (point, normal) of the ground plane.
        tolerance: how far below the plane (m) a carried particle may sit (one lattice spacing:
            the carrying is an interpolation, the underside is a voxel layer).
        k: nearest Gaussians per particle (inverse-distance weights).
        chunk: most particles per distance batch (fewer when ``chunk * G`` exceeds 2**26 floats).

    The floor of a frame is the plane, or the lowest carrying centre where the model puts
    Gaussians below it (the model's own placement error there is not the object's extent).

    Returns:
        ``(keep, removed_per_frame, floor_per_frame)``: (N,) bool, how many particles each later
        frame put below its floor (a particle may be counted in several frames), and each frame's
        floor (m, signed height; 0 is the plane).
    """
    n = particles.shape[0]
    keep = torch.ones(n, dtype=torch.bool, device=particles.device)
    if n == 0 or centres.shape[0] == 0 or not centres_later:
        return keep, [0] * len(centres_later), [0.0] * len(centres_later)
    k = min(k, centres.shape[0])
    chunk = max(1, min(chunk, (1 << 26) // centres.shape[0]))  # at most 64M distances (256 MB) at once
    idx_all, w_all = [], []
    for s in range(0, n, chunk):
        d = torch.cdist(particles[s:s + chunk], centres)
        dist, idx = d.topk(k, dim=1, largest=False)
        w = 1.0 / dist.clamp_min(1e-6)
        idx_all.append(idx)
        w_all.append(w / w.sum(1, keepdim=True))
    idx, w = torch.cat(idx_all), torch.cat(w_all)
    removed, floors = [], []
    for later in centres_later:
        moved = particles + ((later - centres)[idx] * w[..., None]).sum(1)
        # where the model itself puts Gaussians below the plane, its own error sets the floor
        floor = min(0.0, float(height_above(later, ground).min()))
        below = height_above(moved, ground) < floor - tolerance
        removed.append(int(below.sum()))
        floors.append(round(floor, 4))
        keep &= ~below
    return keep, removed, floors


@torch.no_grad()
def carve_first_frame(particles: torch.Tensor, first: Any, carriers: torch.Tensor, frames: Sequence[int],
                      ground: Ground, spacing: float, gaussians_at_frame: Callable[[int], Any]) -> tuple[torch.Tensor, Any]:
    """:func:`carve_through_time` for a deformed Gaussian model.

    Args:
        particles: (N, 3) first-frame particles, metres.
        first: the first frame's Gaussians (``.means`` (G, 3)), before any filtering.
        carriers: indices into ``first`` of the Gaussians that carry the motion (the kept centres).
        frames: the other frames to carve with (indices passed to ``gaussians_at_frame``).
        ground: (point, normal) of the ground plane.
        spacing: the lattice spacing (m): the tolerance below the plane.
        gaussians_at_frame: frame index -> that frame's Gaussians, the same index naming the same
            Gaussian in every frame.

    Returns:
        ``(kept particles, record)``: the record lists the frames used, the particles removed and how
        many each frame put below the ground, or says why nothing was carved (a model whose frames
        hold different Gaussians).
    """
    means0 = first.means.detach()
    later, used = [], []
    for f in frames:
        g = gaussians_at_frame(f)
        if len(g) != len(first):
            return particles, f"skipped: frame {f} has {len(g)} Gaussians, the first frame {len(first)}"
        later.append(g.means.detach()[carriers.to(g.means.device)].to(particles.device).float())
        used.append(int(f))
    centres = means0[carriers.to(means0.device)].to(particles.device).float()
    keep, below, floors = carve_through_time(particles, centres, later, ground, tolerance=spacing)
    return particles[keep], {"frames": used, "removed": int((~keep).sum()), "below_per_frame": below,
                             "floor_per_frame": floors}

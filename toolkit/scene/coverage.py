"""Does stage 0 still hold the object? Coverage of the object masks by the rendered Gaussians.

A 4D Gaussian model can lose the object: on a fast throw the deformation network may carry the
Gaussians out of every view within a hundred iterations of the warm-up's end, after which no
gradient brings them back. Such a model still scores about 27 dB on small objects over a black
background (the background alone), so PSNR does not reveal it. The coverage does: for every
training frame and fitting camera, the fraction of the mask's pixels where the rendered alpha
exceeds one half. A frame whose coverage falls below ``threshold`` in any camera is *lost*; its
surface points and the physics fitted to them are then not measurements of the object.
"""

from __future__ import annotations

import math
from typing import Any

import torch

__all__ = ["mask_coverage", "lost_frames", "coverage_record", "format_frames", "lost_object_message"]

#: coverage below which a frame counts as lost (in any fitting camera)
LOST_BELOW = 0.5


@torch.no_grad()
def mask_coverage(module: Any, views: Any, alpha_min: float = 0.5) -> torch.Tensor:
    """(T, C) float32 on the CPU: per training frame and camera, the fraction of mask pixels
    (mask > 0.5) where the rendered alpha of ``module.gaussians_at(time)`` exceeds ``alpha_min``;
    NaN where the mask is empty. ``views`` is a :class:`~toolkit.scene.stage0_data.TrainingViews` with
    masks; ``module`` a :class:`~toolkit.scene.stage0.Gaussians4DModule` (on the views' device)."""
    if views.masks is None:
        raise ValueError("mask coverage needs the training views' masks")
    rows = []
    for fi in range(views.n_frames):
        alpha = module.render(views.cameras, float(views.times[fi])).alpha  # (C, H, W)
        mask = views.masks[fi] > 0.5
        area = mask.sum((1, 2)).float()
        hit = ((alpha > alpha_min) & mask).sum((1, 2)).float()
        rows.append(torch.where(area > 0, hit / area.clamp_min(1.0), torch.full_like(area, math.nan)).cpu())
    return torch.stack(rows)


def lost_frames(coverage: torch.Tensor, threshold: float = LOST_BELOW) -> list[int]:
    """Indices of the frames whose coverage is below ``threshold`` in at least one camera
    (cameras with an empty mask are ignored)."""
    low = torch.nan_to_num(coverage, nan=1.0) < threshold
    return [int(i) for i in low.any(1).nonzero().reshape(-1)]


def format_frames(frames: list[int]) -> str:
    """``[1, 2, 3, 7]`` -> ``"1-3, 7"``."""
    runs: list[list[int]] = []
    for f in sorted(frames):
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def coverage_record(coverage: torch.Tensor, threshold: float = LOST_BELOW) -> dict:
    """What ``stage0/coverage.json`` holds: each frame's lowest coverage over the cameras, the lost
    frames and the threshold."""
    per_frame = torch.nan_to_num(coverage, nan=1.0).amin(1)
    return {"per_frame_min": [round(float(v), 4) for v in per_frame], "lost_frames": lost_frames(coverage, threshold),
            "threshold": threshold, "cameras": int(coverage.shape[1])}


def lost_object_message(record: dict, where: Any = "stage0/coverage.json") -> str:
    """One warning line for a :func:`coverage_record` with lost frames."""
    lost = record["lost_frames"]
    lowest = min(record["per_frame_min"][f] for f in lost)
    n = len(record["per_frame_min"])
    return (f"stage 0 lost the object in training frame{'s' if len(lost) > 1 else ''} {format_frames(lost)} of 0-{n - 1}: "
            f"there the Gaussians cover under {record['threshold']:.0%} of a fitting camera's mask (lowest {lowest:.0%}; "
            f"{where}), so those frames' surfaces, and a physics fit to them, do not measure the object. Train stage 0 "
            "again (another --seed, or more iterations) before trusting this run")

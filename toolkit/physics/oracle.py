"""Physics inputs from a synthetic scene's ground truth ("oracle geometry").

For testing and ablating the physics stages alone: the particles, Gaussians and geometric
targets come from the generator's ground-truth point clouds instead of stage 0. Fits made this
way say nothing about reconstruction quality; the pipeline (``projo4d run``) uses stage 0.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from renderers.base import Gaussians
from toolkit.data import load_scene
from toolkit.data.datamodule import resolve_cameras
from toolkit.physics.inputs import PhysicsInput, load_all_images

__all__ = ["oracle_input", "voxel_downsample"]


def voxel_downsample(points: np.ndarray, spacing: float) -> np.ndarray:
    """One point per occupied voxel of size ``spacing`` (the mean of its points), in voxel order."""
    keys = np.floor(points / spacing).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.reshape(-1), points)
    return (sums / counts[:, None]).astype(np.float32)


def oracle_input(scene_root: str | Path, cameras: Sequence[int] | str = "sparse", n_train: int | None = None,
                 particle_spacing: float = 0.01, downscale: int = 1, dx: float | None = None,
                 gaussian_scale: float = 0.6, **reader_options) -> PhysicsInput:
    """A :class:`PhysicsInput` whose geometry is the scene's ground truth.

    Args:
        scene_root: a generated scene (``projo4d generate``), with ``ground_truth.json``.
        cameras: training cameras (``"sparse"`` = 1, 5, 9; ``"all"``; or indices).
        n_train: training frames (default: the scene's own split, else 2/3 of the frames).
        particle_spacing: particles are the ground-truth cloud voxel-downsampled to this pitch (m).
        downscale: integer image downscale factor (cameras scaled to match).
        dx: grid spacing of the fit (m) for the world checks; default ``2 * particle_spacing``.
        gaussian_scale: each particle's isotropic Gaussian has the standard deviation
            ``gaussian_scale * particle_spacing``. The default 0.6 covers the body without gaps
            but renders a silhouette wider than the images' (about 1.4x the mask's area on the
            64 px suite), and along E the image loss is then flat with its minimum on the soft
            side (``benchmarks/image_loss_bias.py``; ``docs/limits.md``, "Where the image loss
            puts E"). Inputs whose thresholds were calibrated with the default keep it.
        **reader_options: passed to the scene's reader (e.g. ``ground_height`` for Spring-Gaus).

    Everything is in the canonical world (the reader moved the scene there); ``meta["world"]`` says
    how (:func:`toolkit.physics.world_checks.world_meta`). The world checks run before returning:
    a body below the ground raises :class:`~toolkit.physics.world_checks.WorldError`.
    """
    from toolkit.data.exclusion import exclusion_meta
    from toolkit.physics.world_checks import check_world, world_meta

    if not gaussian_scale > 0:
        raise ValueError(f"gaussian_scale must be > 0 (a fraction of the particle spacing), got {gaussian_scale}")
    scene = load_scene(scene_root, **reader_options)
    gt = scene.ground_truth
    if gt is None or not gt.point_clouds:
        raise ValueError(f"{scene_root} has no ground-truth point clouds; oracle inputs need a generated scene")
    train = resolve_cameras(scene, cameras)
    clouds = [gt.load_point_cloud(f) for f in range(scene.n_frames)]
    particles = voxel_downsample(clouds[0], particle_spacing)
    sim_meta = gt.extra.get("simulation", {})
    truth_volume = float(sim_meta.get("particles_volume", 0.0)) or len(clouds[0]) * float(sim_meta.get("particle_volume", 0.0))
    particle_volume = truth_volume / len(particles) if truth_volume > 0 else particle_spacing**3
    images, masks = load_all_images(scene, downscale)
    cams = scene.cameras.scaled(1.0 / downscale) if downscale > 1 else scene.cameras
    colors = _colors_from_images(particles, cams, images[:, 0], masks[:, 0], train)
    n = len(particles)
    gaussians = Gaussians(
        means=torch.from_numpy(particles),
        log_scales=torch.full((n, 3), math.log(gaussian_scale * particle_spacing)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        opacity_logits=torch.full((n,), 3.0),
        colors=colors,
    )
    surfaces = [torch.from_numpy(voxel_downsample(c, particle_spacing)) for c in clouds]
    if n_train is None:
        n_train = int(gt.extra.get("frames", {}).get("n_train_frames") or max(1, 2 * scene.n_frames // 3))
    gt_dict = {"material": gt.material, "params": dict(gt.params), "v0": gt.v0, "gravity": gt.gravity, "effects": gt.effects,
               "point_clouds": [str(p) for p in gt.point_clouds], "to_canonical": scene.to_canonical.to_dict()}
    world = world_meta(scene)
    check_world(particles, surfaces, scene.times, dx if dx is not None else 2 * particle_spacing, world)
    return PhysicsInput(gaussians=gaussians, particles=torch.from_numpy(particles), particle_volume=particle_volume,
                        surfaces=surfaces, cameras=cams, train_cameras=train, images=images, masks=masks,
                        times=torch.as_tensor(np.asarray(scene.times, dtype=np.float32)), n_train=n_train,
                        ground_truth=gt_dict, meta={"scene_root": str(scene_root), "source": "oracle", "world": world,
                                                                  **exclusion_meta(scene, downscale)})


def _colors_from_images(points: np.ndarray, cameras, images: torch.Tensor, masks: torch.Tensor, train: list[int]) -> torch.Tensor:
    """Mean colour of each point's projection over the training views where it lands on the object."""
    pts = torch.from_numpy(points)
    total = torch.zeros(len(points), 3)
    weight = torch.zeros(len(points), 1)
    for c in train:
        pix, depth = cameras[c].project(pts)
        pix = pix[0]
        H, W = images.shape[1], images.shape[2]
        u = pix[:, 0].floor().long().clamp(0, W - 1)
        v = pix[:, 1].floor().long().clamp(0, H - 1)
        inside = (pix[:, 0] >= 0) & (pix[:, 0] < W) & (pix[:, 1] >= 0) & (pix[:, 1] < H) & (depth[0] > 0)
        on_object = masks[c, v, u].float() / 255.0 > 0.5
        w = (inside & on_object).float().unsqueeze(1)
        total += images[c, v, u].float() / 255.0 * w
        weight += w
    return torch.where(weight > 0, total / weight.clamp_min(1), torch.full_like(total, 0.5))

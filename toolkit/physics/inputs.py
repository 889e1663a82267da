"""What the physics stages start from: Gaussians, particles, pseudo-ground-truth surfaces, images.

A :class:`PhysicsInput` is written by the pipeline after stage 0 and the particle continuum
(``RUN_DIR/physics_input.pt``) and read by :class:`~toolkit.physics.InversePhysicsModule`.
Everything is in the world frame (metres, y up, ground y = 0), frame 0 is the initial state.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from renderers.base import Gaussians
from toolkit.atomic import CorruptArtifactError, load_error_reason
from toolkit.cameras import Cameras

__all__ = ["PhysicsInput", "load_all_images"]

_FORMAT = "projo4d-physics-input"


@dataclass
class PhysicsInput:
    """Inputs of the physics stages.

    Attributes:
        gaussians: Gaussians at frame 0 (means (G, 3), log_scales, quats, opacity_logits, colors
            or sh), world frame.
        particles: (N, 3) float32 simulation particles at frame 0 (the continuum's interior).
        particle_volume: m^3 per particle (the continuum's sampling volume).
        surfaces: per frame t, (M_t, 3) float32 surface points: the pseudo-ground-truth of the
            geometric loss (from stage 0, never from the dataset's ground truth).
        cameras: all cameras of the scene (C of them).
        train_cameras: indices of the cameras used for fitting (sparse views).
        images: (C, T, H, W, 3) uint8 images of every camera and frame.
        masks: (C, T, H, W) uint8 object masks (255 = object).
        times: (T,) seconds.
        n_train: frames ``[0, n_train)`` are fitted, the rest are the future to predict.
        ground_truth: optional dict (material, params, v0, effects, point-cloud paths) for
            logging parameter errors and evaluation; never used by the fit itself.
        meta: anything else (scene root, stage-0 settings, counts).
    """

    gaussians: Gaussians
    particles: torch.Tensor
    particle_volume: float
    surfaces: list[torch.Tensor]
    cameras: Cameras
    train_cameras: list[int]
    images: torch.Tensor
    masks: torch.Tensor
    times: torch.Tensor
    n_train: int
    ground_truth: Optional[dict] = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise ``ValueError`` naming the field and what is expected."""
        self.gaussians.validate()
        if self.particles.ndim != 2 or self.particles.shape[1] != 3 or self.particles.shape[0] == 0:
            raise ValueError(f"PhysicsInput.particles must have shape (N, 3) with N >= 1, got {tuple(self.particles.shape)}")
        if not torch.isfinite(self.particles).all():
            raise ValueError("PhysicsInput.particles contains NaN or inf")
        if not self.particle_volume > 0:
            raise ValueError(f"PhysicsInput.particle_volume must be > 0 m^3, got {self.particle_volume!r}")
        C = len(self.cameras)
        if self.images.ndim != 5 or self.images.shape[0] != C or self.images.shape[-1] != 3:
            raise ValueError(f"PhysicsInput.images must have shape (C={C}, T, H, W, 3), got {tuple(self.images.shape)}")
        T = self.images.shape[1]
        if tuple(self.masks.shape) != tuple(self.images.shape[:4]):
            raise ValueError(f"PhysicsInput.masks must have shape {tuple(self.images.shape[:4])}, got {tuple(self.masks.shape)}")
        if (self.images.shape[2], self.images.shape[3]) != (self.cameras.height, self.cameras.width):
            raise ValueError(
                f"PhysicsInput.images are {self.images.shape[3]}x{self.images.shape[2]} but the cameras are "
                f"{self.cameras.width}x{self.cameras.height}"
            )
        if self.times.shape != (T,):
            raise ValueError(f"PhysicsInput.times must have shape ({T},), got {tuple(self.times.shape)}")
        if len(self.surfaces) != T:
            raise ValueError(f"PhysicsInput.surfaces must have one point set per frame ({T}), got {len(self.surfaces)}")
        if not 1 <= self.n_train <= T:
            raise ValueError(f"PhysicsInput.n_train must be in [1, {T}], got {self.n_train}")
        bad = [c for c in self.train_cameras if not 0 <= c < C]
        if bad or not self.train_cameras:
            raise ValueError(f"PhysicsInput.train_cameras must be non-empty indices in [0, {C}), got {self.train_cameras}")

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[1])

    @property
    def frame_dt(self) -> float:
        """Seconds between frames (from ``times``)."""
        return float(self.times[1] - self.times[0]) if self.n_frames > 1 else 1.0 / 24.0

    @property
    def held_out_cameras(self) -> list[int]:
        return [c for c in range(len(self.cameras)) if c not in self.train_cameras]

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write to ``path`` atomically (a ``torch.save`` file of plain tensors and dicts)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        g = {f.name: getattr(self.gaussians, f.name) for f in fields(self.gaussians)}
        from toolkit.atomic import torch_save

        torch_save({
            "format": _FORMAT,
            "version": 1,
            "gaussians": {k: (None if v is None else v.detach().cpu()) for k, v in g.items()},
            "particles": self.particles.detach().cpu(),
            "particle_volume": float(self.particle_volume),
            "surfaces": [s.detach().cpu() for s in self.surfaces],
            "cameras": self.cameras.to_dict(),
            "train_cameras": list(self.train_cameras),
            "images": self.images.cpu(),
            "masks": self.masks.cpu(),
            "times": self.times.cpu(),
            "n_train": int(self.n_train),
            "ground_truth": self.ground_truth,
            "meta": self.meta,
        }, path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "PhysicsInput":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"physics input file {path} does not exist (written by `projo4d run` after stage 0)")
        try:
            d = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:  # noqa: BLE001 - truncated, not a torch file, foreign objects
            raise CorruptArtifactError(f"{path} is unreadable ({load_error_reason(err)}); delete it or rerun `projo4d run` "
                                       "(which sets it aside and rebuilds it)") from None
        if not isinstance(d, dict) or d.get("format") != _FORMAT:
            raise ValueError(f"{path} is not a projo4d physics input file (expected format {_FORMAT!r})")
        return cls(
            gaussians=Gaussians(**d["gaussians"]),
            particles=d["particles"],
            particle_volume=d["particle_volume"],
            surfaces=d["surfaces"],
            cameras=Cameras.from_dict(d["cameras"]),
            train_cameras=d["train_cameras"],
            images=d["images"],
            masks=d["masks"],
            times=d["times"],
            n_train=d["n_train"],
            ground_truth=d.get("ground_truth"),
            meta=d.get("meta", {}),
        )


def load_all_images(scene, downscale: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Every camera and frame of a :class:`~toolkit.data.MultiViewScene` as uint8 tensors.

    Args:
        scene: the scene.
        downscale: integer factor; images are box-filtered (cameras must be scaled to match).

    Returns:
        ``images`` (C, T, H, W, 3) and ``masks`` (C, T, H, W), uint8 (masks: 255 = object).
    """
    imgs, masks = [], []
    for c in range(scene.n_cameras):
        ci, cm = [], []
        for f in range(scene.n_frames):
            img = scene.load_image(c, f)
            m = scene.load_mask(c, f)
            if downscale > 1:
                h, w = img.shape[0] // downscale * downscale, img.shape[1] // downscale * downscale
                img = img[:h, :w].reshape(h // downscale, downscale, w // downscale, downscale, 3).mean((1, 3))
                m = m[:h, :w].reshape(h // downscale, downscale, w // downscale, downscale).mean((1, 3))
            ci.append(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8))
            cm.append(np.round(np.clip(m, 0, 1) * 255).astype(np.uint8))
        imgs.append(np.stack(ci))
        masks.append(np.stack(cm))
    return torch.from_numpy(np.stack(imgs)), torch.from_numpy(np.stack(masks))

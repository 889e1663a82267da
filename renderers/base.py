"""The renderer interface shared by every backend.

Conventions (DESIGN section 5):

* Gaussians live in the world frame, metres. ``quats`` are unit quaternions in ``(w, x, y, z)``
  order; ``log_scales`` are natural logs of the three standard deviations; ``opacity_logits``
  pass through a sigmoid; ``colors`` are linear RGB in [0, 1] (used as given) or, when ``sh`` is
  set, spherical-harmonic coefficients evaluated per camera as in 3DGS (``SH(dir) + 0.5``,
  clamped at 0).
* Cameras are :class:`toolkit.cameras.Cameras` (OpenCV convention: x right, y down, z forward;
  world-to-camera extrinsics; pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)`` so its centre is at
  ``(i + 0.5, j + 0.5)``).
* Images are channel-last: ``rgb (B, H, W, 3)``, ``alpha (B, H, W)``, ``depth (B, H, W)``, one
  per camera of the batch. ``depth`` is the alpha-weighted camera-space z, ``sum_i w_i z_i``
  (not divided by alpha; see :meth:`RenderOutput.expected_depth`). The background colour is
  added as ``rgb + (1 - alpha) * background`` (black by default).

A Gaussian ``i`` contributes to pixel ``p`` iff its centre is in front of the near plane,
``alpha_i(p) = min(0.99, sigmoid(o_i) * exp(-0.5 d^T Sigma'^-1 d)) >= 1/255`` (``Sigma'`` is the
projected covariance plus a 0.3 px low-pass on the diagonal, ``d`` the offset from the projected
centre to the pixel centre), and compositing has not been cut off (it stops before the Gaussian
that would bring the transmittance below 1e-4). Gaussians are composited front to back by the
camera-space depth of their centres. This rule does not depend on tiles, so tile-based backends
can match the dense reference exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Optional

import torch

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.cameras import Cameras

__all__ = ["Gaussians", "RenderOutput", "Renderer", "ALPHA_MIN", "ALPHA_MAX", "T_MIN", "LOW_PASS"]

ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped
ALPHA_MAX = 0.99  # per-Gaussian alpha is clamped to this
T_MIN = 1e-4  # compositing stops before transmittance would fall below this
LOW_PASS = 0.3  # px^2 added to the diagonal of every projected covariance


@dataclass
class Gaussians:
    """A set of N 3D Gaussians.

    Attributes:
        means: (N, 3) float32, world frame, metres.
        log_scales: (N, 3) float32, natural log of the standard deviations (metres).
        quats: (N, 4) float32, unit quaternions (w, x, y, z), rotation local -> world.
        opacity_logits: (N,) float32, opacity = sigmoid(logit).
        colors: (N, 3) float32 linear RGB in [0, 1]; ignored when ``sh`` is given.
        sh: optional (N, K, 3) float32 spherical-harmonic coefficients, K in {1, 4, 9, 16}.
        deformation: optional (N, 3, 3) float32 linear maps ``A`` applied to each Gaussian's shape:
            its covariance becomes ``A R S S^T R^T A^T`` (the material's local deformation since
            the frame the shape was fitted at); ``None`` is the identity.
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    colors: Optional[torch.Tensor] = None
    sh: Optional[torch.Tensor] = None
    deformation: Optional[torch.Tensor] = None

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        return self.means.device

    def replace(self, **changes: torch.Tensor) -> "Gaussians":
        """A copy with some attributes replaced (e.g. ``means`` moved by the simulator)."""
        return replace(self, **changes)

    def to(self, device: torch.device | str) -> "Gaussians":
        return Gaussians(**{f.name: (None if getattr(self, f.name) is None else getattr(self, f.name).to(device)) for f in fields(self)})

    def detach(self) -> "Gaussians":
        return Gaussians(**{f.name: (None if getattr(self, f.name) is None else getattr(self, f.name).detach()) for f in fields(self)})

    def validate(self) -> None:
        """Raise ``ValueError`` naming the attribute for wrong shapes, dtypes, devices or NaNs."""
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expect = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
        }
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"Gaussians.means must have shape (N, 3), got {tuple(self.means.shape)}")
        if self.sh is None and self.colors is None:
            raise ValueError("Gaussians need either colors (N, 3) or sh (N, K, 3)")
        if self.sh is None:
            expect["colors"] = (n, 3)
        for name, shape in expect.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise ValueError(f"Gaussians.{name} must have shape {shape} (N={n}), got {tuple(t.shape)}")
        if self.deformation is not None and tuple(self.deformation.shape) != (n, 3, 3):
            raise ValueError(f"Gaussians.deformation must have shape ({n}, 3, 3) (N={n}), got {tuple(self.deformation.shape)}")
        if self.sh is not None:
            if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 or self.sh.shape[1] not in (1, 4, 9, 16):
                raise ValueError(
                    f"Gaussians.sh must have shape (N, K, 3) with K in 1, 4, 9, 16 (N={n}), got {tuple(self.sh.shape)}"
                )
        for f in fields(self):
            t = getattr(self, f.name)
            if t is None:
                continue
            if not t.is_floating_point():
                raise ValueError(f"Gaussians.{f.name} must be a floating-point tensor, got {t.dtype}")
            if t.device != self.means.device:
                raise ValueError(f"Gaussians.{f.name} is on {t.device} but means are on {self.means.device}")
            if t.numel() and not torch.isfinite(t).all():
                bad = (~torch.isfinite(t)).reshape(t.shape[0], -1).any(dim=1).nonzero()[:5, 0].tolist()
                raise ValueError(f"Gaussians.{f.name} has NaN or inf values (first rows: {bad})")


@dataclass
class RenderOutput:
    """Images for a batch of B cameras.

    Attributes:
        rgb: (B, H, W, 3) float32, background already composited.
        alpha: (B, H, W) float32 accumulated opacity, 1 - final transmittance.
        depth: (B, H, W) float32 alpha-weighted camera-space depth ``sum_i w_i z_i`` (metres).
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor

    def expected_depth(self, eps: float = 1e-6) -> torch.Tensor:
        """(B, H, W) depth normalized by alpha (0 where nothing was rendered)."""
        return torch.where(self.alpha > eps, self.depth / self.alpha.clamp_min(eps), torch.zeros_like(self.depth))


class Renderer:
    """Base class of the renderer backends.

    Subclasses implement :meth:`render`. A renderer holds no learnable state; it is
    differentiable with respect to every tensor attribute of :class:`Gaussians`.
    """

    registry_name: str = ""

    def __init__(self, background: tuple[float, float, float] = (0.0, 0.0, 0.0)):
        self.background = tuple(float(c) for c in background)

    def render(self, gaussians: Gaussians, cameras: "Cameras") -> RenderOutput:
        raise NotImplementedError

    def __call__(self, gaussians: Gaussians, cameras: "Cameras") -> RenderOutput:
        return self.render(gaussians, cameras)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(background={self.background})"

"""The objectives of :class:`~toolkit.discovery.library.LibraryModel`: residuals, losses and
their derivatives at a parameter vector ``q``.

A mixin: :class:`LibraryObjectives` reads the forward model of the class it is mixed into
(``trajectory``, ``gaussian_means``, ``deformations``, ``render``, ``observed_images``) and its
parameter layout (``index_of``, ``steps``, ``low``, ``high``). Two objectives:

* :meth:`LibraryObjectives.residuals`, a residual vector whose half squared norm is the
  Gauss-Newton objective of the ranking and the refits (image: rendered minus observed pixels;
  geometry: the Chamfer nearest-neighbour displacements with the assignment held fixed);
* :meth:`LibraryObjectives.image_losses`, the fit's own per-camera image loss
  ``(1 - w) L1 + w (1 - SSIM)``, used on the held-out cameras for decisions.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
import torch

from toolkit.metrics.geometry import chamfer_loss
from toolkit.metrics.image import ssim_torch

__all__ = ["LibraryObjectives"]


class LibraryObjectives:
    """Residuals, losses, gradient and Jacobian of a library model (see the module docstring)."""

    def train_frames(self) -> list[int]:
        """The frames the objectives fit (:attr:`fit_frames`)."""
        return list(self.fit_frames)

    def _geometry_pairs(self, positions: torch.Tensor, frames: Sequence[int]):
        pairs = []
        si = self.module.surface_index
        for k, f in enumerate(frames):
            target = self.input.surfaces[f].to(positions.device)
            if len(target) == 0:
                pairs.append(None)
                continue
            pts = positions[k][si]
            pairs.append((pts, target))
        return pairs

    def assign(self, q, frames: Optional[Sequence[int]] = None) -> list:
        """Fix the nearest-neighbour assignment of the geometric residuals at ``q``."""
        frames = self.train_frames() if frames is None else list(frames)
        x0, pos = self.trajectory(q, frames)
        out = []
        for pair in self._geometry_pairs(pos, frames):
            if pair is None:
                out.append(None)
                continue
            pts, target = pair
            d = torch.cdist(pts.float(), target.float())
            out.append((d.argmin(1), d.argmin(0)))
        self._assign = out
        return out

    def residuals(self, q, frames: Optional[Sequence[int]] = None, cams: Optional[Sequence[int]] = None,
                  grad: bool = False) -> torch.Tensor:
        """The Gauss-Newton residual vector (R,) (float64 on the CPU unless ``grad``).

        ``0.5 |r|^2`` is ``lambda_img / F sum_{f,c} mean (I - I_obs)^2`` over the fitted cameras
        and training frames, plus ``w_geo lambda_geo / F sum_f`` Chamfer with the fixed
        assignment of :meth:`assign` (made at ``q`` when none is set).
        """
        frames = self.train_frames() if frames is None else list(frames)
        cams = list(self.input.train_cameras) if cams is None else list(cams)
        x0, pos = self.trajectory(q, frames, grad=grad)
        means, deform = self.gaussian_means(q, x0, pos), self.deformations(x0, pos)
        with torch.set_grad_enabled(grad):
            img = self.render(q, means, cams, deform)
            obs = self.observed_images(frames, cams)
            F = len(frames)
            lam_img = self.module.lambda_image
            per = obs[0, 0].numel()
            parts = [(math.sqrt(lam_img / (F * per)) * (img - obs)).reshape(-1)]
            w = self.geometry_weight if self.geometry_weight is not None else 1.0
            lam_geo = self.module.lambda_geometry * w
            if lam_geo > 0:
                if self._assign is None or len(self._assign) != F:
                    self.assign(q, frames)
                for pair, a in zip(self._geometry_pairs(pos, frames), self._assign):
                    if pair is None or a is None:
                        continue
                    pts, target = pair
                    ai, bj = a
                    parts.append((math.sqrt(lam_geo / (F * len(pts))) * (pts - target[ai])).reshape(-1))
                    parts.append((math.sqrt(lam_geo / (F * len(target))) * (target - pts[bj])).reshape(-1))
            r = torch.cat(parts)
        return r if grad else r.detach().double().cpu()

    def objective(self, q, **kw) -> float:
        """``0.5 |r|^2`` of :meth:`residuals`."""
        r = self.residuals(q, **kw)
        return 0.5 * float(r @ r)

    def image_losses(self, q, frames: Sequence[int], cams: Sequence[int], grad: bool = False) -> torch.Tensor:
        """(F, C) the fit's image loss per frame and camera, ``(1 - w) L1 + w (1 - SSIM)`` on the
        masked image (without ``lambda_image``)."""
        x0, pos = self.trajectory(q, frames, grad=grad)
        means, deform = self.gaussian_means(q, x0, pos), self.deformations(x0, pos)
        with torch.set_grad_enabled(grad):
            img = self.render(q, means, cams, deform)
            obs = self.observed_images(frames, cams)
            out = self._image_loss(img, obs)
        return out if grad else out.detach().cpu()

    def _image_loss(self, img: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """(F, C) ``(1 - w) L1 + w (1 - SSIM)`` of renders ``img`` against ``obs`` (F, C, H, W, 3)."""
        F, C = img.shape[:2]
        flat_i, flat_o = img.reshape(F * C, *img.shape[2:]), obs.reshape(F * C, *obs.shape[2:])
        l1 = (flat_i - flat_o).abs().mean(dim=(1, 2, 3))
        ssim = ssim_torch(flat_i, flat_o, reduction="none").reshape(F * C, -1).mean(1)
        w = self.module.ssim_weight
        return ((1 - w) * l1 + w * (1 - ssim)).reshape(F, C)

    def fit_loss(self, q, grad: bool = False) -> torch.Tensor:
        """The module's training loss (image + geometry terms on the fitted cameras and training
        frames) at ``q``; differentiable with respect to ``q`` when ``grad``."""
        frames = self.train_frames()
        cams = list(self.input.train_cameras)
        x0, pos = self.trajectory(q, frames, grad=grad)
        means, deform = self.gaussian_means(q, x0, pos), self.deformations(x0, pos)
        with torch.set_grad_enabled(grad):
            img = self.render(q, means, cams, deform)
            obs = self.observed_images(frames, cams)
            F = img.shape[0]
            total = self.module.lambda_image * self._image_loss(img, obs).sum() / F
            if self.module.lambda_geometry > 0:
                geo = torch.zeros((), device=pos.device)
                for pair in self._geometry_pairs(pos, frames):
                    if pair is not None:
                        geo = geo + chamfer_loss(*pair)
                total = total + self.module.lambda_geometry * geo / F
        return total if grad else total.detach().cpu()

    def gradient(self, q) -> np.ndarray:
        """Gradient of :meth:`fit_loss` with respect to every library parameter at ``q`` (autodiff
        through the simulator and the renderer), in loss units per parameter unit."""
        qt = torch.as_tensor(np.asarray(q, dtype=np.float64)).clone().requires_grad_(True)
        loss = self.fit_loss(qt, grad=True)
        loss.backward()
        return qt.grad.detach().cpu().numpy().copy()

    def image_rows(self) -> int:
        """Number of image rows at the head of :meth:`residuals` (the geometric rows follow)."""
        return len(self.train_frames()) * len(self.input.train_cameras) * self.module.images[0, 0].numel()

    def calibrate_geometry_weight(self, q) -> float:
        """Set :attr:`geometry_weight` so that the geometric share of the Gauss-Newton objective at
        ``q`` equals its share in the module's own loss (L1/SSIM images vs Chamfer), and return it.
        1.0 when either term is absent."""
        m = self.module
        if m.lambda_geometry <= 0:
            self.geometry_weight = 1.0
            return 1.0
        frames = self.train_frames()
        self.geometry_weight = 1.0
        self.assign(q, frames)
        r = self.residuals(q)
        n_img = self.image_rows()
        g_img, g_geo = float(r[:n_img] @ r[:n_img]), float(r[n_img:] @ r[n_img:])
        losses = self.image_losses(q, frames, list(self.input.train_cameras))
        l_img = float(m.lambda_image * losses.sum() / len(frames))
        l_geo = float(self.fit_loss(q)) - l_img
        if g_img <= 0 or g_geo <= 0 or l_img <= 0 or l_geo <= 0:
            self.geometry_weight = 1.0
        else:
            self.geometry_weight = float(np.clip((l_geo / l_img) / (g_geo / g_img), 1e-3, 1e3))
        return self.geometry_weight

    #: parameters differenced downward: a lower density raises the stress as a higher modulus
    #: does, so the two columns share their second-order terms and the projection removes the
    #: density's column to second order (its step, 0.02 ln 10, matches log10 E's 0.02)
    DOWNWARD = ("density.log_ratio",)

    def jacobian(self, q, names: Sequence[str], r0: Optional[torch.Tensor] = None, **kw) -> np.ndarray:
        """One-sided finite-difference Jacobian of :meth:`residuals` (R, k) in *step units*:
        column j is ``r(q + h_j e_j) - r(q)`` with ``h_j`` the parameter's step (backward, sign
        corrected, where the upper bound is in the way and for :attr:`DOWNWARD`)."""
        r0 = self.residuals(q, **kw) if r0 is None else r0
        cols = []
        for n in names:
            i = self.index_of[n]
            h = self.steps[i]
            qp = np.array(q, dtype=np.float64)
            sign = 1.0 if qp[i] + h <= self.high[i] and n not in self.DOWNWARD else -1.0
            if qp[i] - h < self.low[i] and sign < 0:
                sign = 1.0
            qp[i] += sign * h
            cols.append(sign * (self.residuals(qp, **kw) - r0).numpy())
        return np.stack(cols, axis=1) if cols else np.zeros((len(r0), 0))

"""Learnable canonical 3D Gaussians with adaptive density control (clone / split / prune).

Conventions (DESIGN section 5, :mod:`renderers.base`):

* World frame, metres. ``means`` (N, 3); ``log_scales`` natural logs of the standard deviations,
  (N, 1) for isotropic Gaussians (GIC's default: one scale per Gaussian, ``num_attribute = 4``)
  or (N, 3); ``quats`` (N, 4) in (w, x, y, z) order (kept at the identity and not optimized for
  isotropic Gaussians); ``opacity_logits`` (N,) with ``opacity = sigmoid(logit)``.
* Colour is a real spherical-harmonic expansion as in 3DGS: ``sh_dc`` (N, 1, 3) and ``sh_rest``
  (N, K - 1, 3) with ``K = (degree + 1)^2``; the rendered colour is ``max(SH(dir) + 0.5, 0)``.
  An RGB colour ``c`` corresponds to ``sh_dc = (c - 0.5) / SH_C0``.
* Every per-Gaussian tensor has N rows. Densification changes N; it replaces the ``.data`` of
  the *same* :class:`torch.nn.Parameter` objects and edits the optimizer state rows (Adam's
  ``exp_avg``/``exp_avg_sq``) in place, so optimizers built once keep working and resume only has
  to :meth:`GaussianModel.resize_` before loading a state dict.

Adaptive density control follows 3DGS / GIC (``scene/gaussian_model.py``): every
``densify_interval`` iterations, Gaussians whose average screen-space position gradient is at least
``grad_threshold`` are *cloned* (copied in place) when their largest scale is at most
``percent_dense * extent``, or *split* into ``split_count`` samples drawn from the Gaussian with
scales divided by ``split_scale_factor * split_count`` otherwise; then Gaussians with opacity below
``min_opacity`` (and, late in training, Gaussians too large on screen or in the world) are pruned.
The screen-space gradient is accumulated by the training loop (see
:func:`toolkit.scene.stage0_losses.screen_space_stats`) in NDC units as in 3DGS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch
from torch import nn

from renderers.base import Gaussians
from toolkit.settings import DictSettings

__all__ = [
    "SH_C0",
    "DensificationConfig",
    "GaussianModel",
    "rgb_to_sh_dc",
    "sh_dc_to_rgb",
    "inverse_sigmoid",
    "knn_scales",
    "PER_GAUSSIAN_PARAMS",
    "PER_GAUSSIAN_BUFFERS",
]

SH_C0 = 0.28209479177387814

PER_GAUSSIAN_PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")
PER_GAUSSIAN_BUFFERS = ("grad_accum", "denom", "max_radii")


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) RGB in [0, 1] -> degree-0 SH coefficient with ``SH_C0 * dc + 0.5 = rgb``."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_sh_dc`."""
    return dc * SH_C0 + 0.5


def inverse_sigmoid(p: torch.Tensor | float) -> torch.Tensor:
    """``log(p / (1 - p))`` (p clamped to [1e-6, 1 - 1e-6])."""
    p = torch.as_tensor(p, dtype=torch.float32).clamp(1e-6, 1.0 - 1e-6)
    return torch.log(p / (1.0 - p))


def knn_scales(points: torch.Tensor | np.ndarray, k: int = 3, min_dist2: float = 1e-7) -> torch.Tensor:
    """Initial standard deviation per point: ``sqrt(mean squared distance to the k nearest others)``.

    This is 3DGS/GIC's ``distCUDA2`` rule (k = 3, squared distances clamped at 1e-7 m^2), computed
    on the CPU with a k-d tree.

    Args:
        points: (N, 3) positions, metres.
        k: Number of neighbours.
        min_dist2: Lower clamp of the mean squared distance, m^2.

    Returns:
        (N,) float32 tensor (CPU), metres.
    """
    from scipy.spatial import cKDTree

    pts = points.detach().cpu().double().numpy() if isinstance(points, torch.Tensor) else np.asarray(points, np.float64)
    n = pts.shape[0]
    if n == 0:
        return torch.zeros(0)
    if n == 1:
        return torch.full((1,), math.sqrt(min_dist2) * 100.0)
    kk = min(k, n - 1)
    d, _ = cKDTree(pts).query(pts, k=kk + 1)
    d2 = (np.asarray(d).reshape(n, -1)[:, 1:] ** 2).mean(axis=1)
    return torch.from_numpy(np.sqrt(np.maximum(d2, min_dist2))).float()


@dataclass
class DensificationConfig(DictSettings):
    settings_name = "densification settings"

    """Thresholds of adaptive density control. Defaults are GIC's (``arguments/__init__.py``,
    ``train_gs.py``; 3DGS values in parentheses where they differ).

    Attributes:
        grad_threshold: Clone/split when the mean screen-space position gradient (NDC units, as
            3DGS's ``viewspace_points.grad``) is at least this (GIC 1.5e-4; 3DGS 2e-4).
        percent_dense: Clone if ``max scale <= percent_dense * extent``, split otherwise.
        min_opacity: Prune Gaussians with opacity below this.
        split_count: Samples that replace a split Gaussian (3DGS ``N = 2``).
        split_scale_factor: New scale = old / (split_scale_factor * split_count) (3DGS 0.8).
        max_screen_fraction: Late pruning: 2D radius (3 sigma, px) above this fraction of the
            larger image side (3DGS: 20 px at 800 px).
        max_world_fraction: Late pruning: largest scale above this fraction of ``extent`` (3DGS 0.1).
        opacity_reset_value: Opacity reset caps opacities at this value (3DGS 0.01).
        max_gaussians: Optional cap on the number of Gaussians: clone/split candidates with the
            largest gradients are taken first until the cap would be exceeded (None: no cap).
    """

    grad_threshold: float = 1.5e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    split_count: int = 2
    split_scale_factor: float = 0.8
    max_screen_fraction: float = 20.0 / 800.0
    max_world_fraction: float = 0.1
    opacity_reset_value: float = 0.01
    max_gaussians: Optional[int] = None



def _unwrap_optimizers(optimizers: Any) -> list[torch.optim.Optimizer]:
    if optimizers is None:
        return []
    if isinstance(optimizers, torch.optim.Optimizer) or hasattr(optimizers, "optimizer"):
        optimizers = [optimizers]
    return [getattr(o, "optimizer", o) for o in optimizers]


class GaussianModel(nn.Module):
    """N learnable 3D Gaussians (the canonical set of the 4D model).

    Args:
        sh_degree: Maximum SH degree (0..3); the colour has ``(sh_degree + 1)^2`` coefficients.
        isotropic: One scale per Gaussian (GIC) instead of three; rotations are then fixed.
        n: Initial number of Gaussians (parameters are zeros with identity rotations; use
            :meth:`init_from_points`).

    Buffers (saved in the state dict, so resuming restores densification exactly):
        grad_accum: (N,) sum of screen-space gradient norms since the last densification.
        denom: (N,) number of iterations in which each Gaussian was visible.
        max_radii: (N,) largest 2D radius (px) seen since the last densification.
    """

    def __init__(self, sh_degree: int = 3, isotropic: bool = True, n: int = 0):
        super().__init__()
        if not 0 <= int(sh_degree) <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        self.sh_degree = int(sh_degree)
        self.isotropic = bool(isotropic)
        k = (self.sh_degree + 1) ** 2
        self.means = nn.Parameter(torch.zeros(n, 3))
        self.log_scales = nn.Parameter(torch.zeros(n, 1 if self.isotropic else 3))
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        self.quats = nn.Parameter(quats, requires_grad=not self.isotropic)
        self.opacity_logits = nn.Parameter(torch.zeros(n))
        self.sh_dc = nn.Parameter(torch.zeros(n, 1, 3))
        self.sh_rest = nn.Parameter(torch.zeros(n, k - 1, 3))
        self.register_buffer("grad_accum", torch.zeros(n))
        self.register_buffer("denom", torch.zeros(n))
        self.register_buffer("max_radii", torch.zeros(n))

    # ------------------------------------------------------------------ properties

    @property
    def n(self) -> int:
        """Number of Gaussians."""
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.n

    @property
    def num_sh_coeffs(self) -> int:
        return (self.sh_degree + 1) ** 2

    def scales(self, d_log_scales: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(N, 3) standard deviations in metres (isotropic scales broadcast)."""
        ls = self.log_scales if d_log_scales is None else self.log_scales + d_log_scales
        return torch.exp(ls).expand(-1, 3) if ls.shape[1] == 1 else torch.exp(ls)

    @property
    def opacity(self) -> torch.Tensor:
        """(N,) opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh(self) -> torch.Tensor:
        """(N, K, 3) all SH coefficients."""
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    def param_dict(self) -> dict[str, nn.Parameter]:
        return {name: getattr(self, name) for name in PER_GAUSSIAN_PARAMS}

    # ------------------------------------------------------------------ rendering view

    def gaussians(
        self,
        means: Optional[torch.Tensor] = None,
        d_log_scales: Optional[torch.Tensor] = None,
        d_quats: Optional[torch.Tensor] = None,
        sh_degree: Optional[int] = None,
    ) -> Gaussians:
        """The Gaussians in the renderer's format (differentiable).

        Args:
            means: (N, 3) positions to use instead of the canonical ``means`` (e.g. deformed).
            d_log_scales: (N, 1) or (N, 3) offsets added to the log-scales.
            d_quats: (N, 4) offsets added to the (unnormalized) quaternions (anisotropic only).
            sh_degree: Active SH degree (<= ``sh_degree``); only that many coefficients are used.

        Returns:
            :class:`renderers.base.Gaussians` with ``sh`` set (``colors`` None).
        """
        ls = self.log_scales if d_log_scales is None else self.log_scales + d_log_scales
        if ls.shape[1] == 1:
            ls = ls.expand(-1, 3)
        q = self.quats if (d_quats is None or self.isotropic) else self.quats + d_quats
        deg = self.sh_degree if sh_degree is None else max(0, min(int(sh_degree), self.sh_degree))
        k = (deg + 1) ** 2
        sh = self.sh_dc if k == 1 else torch.cat([self.sh_dc, self.sh_rest[:, : k - 1]], dim=1)
        return Gaussians(
            means=self.means if means is None else means,
            log_scales=ls,
            quats=q,
            opacity_logits=self.opacity_logits,
            sh=sh,
        )

    # ------------------------------------------------------------------ initialization

    @torch.no_grad()
    def init_from_points(
        self,
        points: torch.Tensor | np.ndarray,
        colors: Optional[torch.Tensor | np.ndarray] = None,
        *,
        opacity: float = 0.1,
        scales: Optional[torch.Tensor | np.ndarray] = None,
    ) -> None:
        """Replace all Gaussians by one per point (3DGS ``create_from_pcd``).

        Args:
            points: (N, 3) positions, metres.
            colors: (N, 3) RGB in [0, 1]; default mid-grey (GIC: random SH close to 0, i.e. grey).
            opacity: Initial opacity (GIC/3DGS 0.1).
            scales: (N,) initial standard deviations (metres); default :func:`knn_scales`.
        """
        dev = self.means.device
        pts = torch.as_tensor(np.asarray(points) if not isinstance(points, torch.Tensor) else points).float()
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {tuple(pts.shape)}")
        n = pts.shape[0]
        s = knn_scales(pts) if scales is None else torch.as_tensor(scales).float().reshape(n)
        rgb = torch.full((n, 3), 0.5) if colors is None else torch.as_tensor(colors).float().reshape(n, 3)
        self.resize_(n)
        self.means.data.copy_(pts.to(dev))
        self.log_scales.data.copy_(torch.log(s)[:, None].expand(n, self.log_scales.shape[1]).to(dev))
        self.quats.data.zero_()
        self.quats.data[:, 0] = 1.0
        self.opacity_logits.data.fill_(float(inverse_sigmoid(opacity)))
        self.sh_dc.data.copy_(rgb_to_sh_dc(rgb)[:, None, :].to(dev))
        self.sh_rest.data.zero_()

    @torch.no_grad()
    def resize_(self, n: int) -> None:
        """Give every per-Gaussian parameter and buffer ``n`` rows (zeros, identity rotations).

        Used before loading a state dict whose N differs (resume after densification); keeps the
        Parameter objects, so optimizers that reference them stay valid.
        """
        for name in PER_GAUSSIAN_PARAMS:
            p = getattr(self, name)
            p.data = torch.zeros((n,) + tuple(p.shape[1:]), dtype=p.dtype, device=p.device)
            p.grad = None
        self.quats.data[:, 0] = 1.0
        for name in PER_GAUSSIAN_BUFFERS:
            b = getattr(self, name)
            setattr(self, name, torch.zeros(n, dtype=b.dtype, device=b.device))

    # ------------------------------------------------------------------ densification statistics

    @torch.no_grad()
    def add_densification_stats(self, grad_norm: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor) -> None:
        """Accumulate one iteration's statistics (no host synchronization).

        Args:
            grad_norm: (N,) screen-space gradient norm (NDC units) of each Gaussian's position.
            visible: (N,) bool, in view of at least one camera of the iteration.
            radii: (N,) 2D radius in pixels (largest over the cameras).
        """
        vis = visible.to(self.grad_accum.dtype)
        self.grad_accum += grad_norm * vis
        self.denom += vis
        self.max_radii.copy_(torch.maximum(self.max_radii, radii * vis))

    @torch.no_grad()
    def reset_densification_stats(self) -> None:
        self.grad_accum.zero_()
        self.denom.zero_()
        self.max_radii.zero_()

    def mean_grad(self) -> torch.Tensor:
        """(N,) accumulated gradient divided by the visible count (0 where never visible)."""
        return torch.where(self.denom > 0, self.grad_accum / self.denom.clamp_min(1.0), torch.zeros_like(self.denom))

    # ------------------------------------------------------------------ row surgery

    @torch.no_grad()
    def _apply_rows(self, fn_param, fn_state, optimizers: Any) -> None:
        """Apply ``fn_param(name, tensor) -> tensor`` to every per-Gaussian parameter and
        ``fn_state(name, tensor) -> tensor`` to every optimizer state tensor with N rows."""
        n_old = self.n
        opts = _unwrap_optimizers(optimizers)
        for name in PER_GAUSSIAN_PARAMS:
            p = getattr(self, name)
            for opt in opts:
                st = opt.state.get(p)
                if not st:
                    continue
                for key, val in list(st.items()):
                    if isinstance(val, torch.Tensor) and val.ndim >= 1 and val.shape[0] == n_old:
                        st[key] = fn_state(name, val)
            p.data = fn_param(name, p.data)
            p.grad = None

    @torch.no_grad()
    def prune(self, remove: torch.Tensor, optimizers: Any = None) -> int:
        """Remove the Gaussians where ``remove`` (N,) bool is True; returns how many."""
        keep = ~remove.to(torch.bool)
        n_removed = int(remove.sum())
        if n_removed == 0:
            return 0
        idx = keep.nonzero()[:, 0]
        self._apply_rows(lambda _, t: t[idx], lambda _, t: t[idx], optimizers)
        for name in PER_GAUSSIAN_BUFFERS:
            setattr(self, name, getattr(self, name)[idx])
        return n_removed

    @torch.no_grad()
    def append(self, new: dict[str, torch.Tensor], optimizers: Any = None) -> int:
        """Append Gaussians given by a dict with one (M, ...) tensor per parameter name.

        Optimizer moments and densification statistics of the new rows are zeros (3DGS
        ``densification_postfix``).
        """
        m = int(new["means"].shape[0])
        if m == 0:
            return 0
        self._apply_rows(
            lambda name, t: torch.cat([t, new[name].to(t)], 0),
            lambda name, t: torch.cat([t, torch.zeros((m,) + tuple(t.shape[1:]), dtype=t.dtype, device=t.device)], 0),
            optimizers,
        )
        for name in PER_GAUSSIAN_BUFFERS:
            b = getattr(self, name)
            setattr(self, name, torch.cat([b, torch.zeros(m, dtype=b.dtype, device=b.device)]))
        return m

    @torch.no_grad()
    def clone(self, mask: torch.Tensor, optimizers: Any = None) -> int:
        """Append an exact copy of every Gaussian where ``mask`` is True; returns how many."""
        idx = mask.nonzero()[:, 0]
        return self.append({name: getattr(self, name).data[idx] for name in PER_GAUSSIAN_PARAMS}, optimizers)

    @torch.no_grad()
    def split(
        self,
        mask: torch.Tensor,
        optimizers: Any = None,
        *,
        count: int = 2,
        scale_factor: float = 0.8,
        generator: Optional[torch.Generator] = None,
    ) -> int:
        """Replace every Gaussian where ``mask`` is True by ``count`` samples drawn from it.

        New positions are ``mean + R (s * eps)`` with ``eps ~ N(0, I)``, new scales
        ``s / (scale_factor * count)``; rotation, opacity and colour are copied (3DGS
        ``densify_and_split``). Returns the number of Gaussians split.
        """
        idx = mask.nonzero()[:, 0]
        k = int(idx.numel())
        if k == 0:
            return 0
        from renderers.torch_reference import quat_to_rotmat

        s = self.scales()[idx].repeat(count, 1)  # (k*count, 3)
        eps = torch.randn(s.shape, generator=generator, dtype=torch.float32).to(s)
        R = quat_to_rotmat(self.quats.data[idx]).repeat(count, 1, 1)
        new = {name: getattr(self, name).data[idx].repeat((count,) + (1,) * (getattr(self, name).ndim - 1)) for name in PER_GAUSSIAN_PARAMS}
        new["means"] = new["means"] + (R @ (s * eps)[..., None])[..., 0]
        new["log_scales"] = new["log_scales"] - math.log(scale_factor * count)
        n_old = self.n
        self.append(new, optimizers)
        remove = torch.zeros(self.n, dtype=torch.bool, device=self.means.device)
        remove[idx] = True
        self.prune(remove, optimizers)
        assert self.n == n_old + k * (count - 1)
        return k

    @torch.no_grad()
    def reset_opacity(self, value: float = 0.01, optimizers: Any = None) -> None:
        """Cap every opacity at ``value`` and zero its optimizer moments (3DGS ``reset_opacity``)."""
        cap = float(inverse_sigmoid(value))
        self.opacity_logits.data.clamp_(max=cap)
        for opt in _unwrap_optimizers(optimizers):
            st = opt.state.get(self.opacity_logits)
            if st:
                for key, val in st.items():
                    if isinstance(val, torch.Tensor) and val.ndim >= 1:
                        val.zero_()

    @torch.no_grad()
    def densify_and_prune(
        self,
        config: DensificationConfig,
        extent: float,
        optimizers: Any = None,
        *,
        max_screen_px: Optional[float] = None,
        generator: Optional[torch.Generator] = None,
    ) -> dict[str, int]:
        """One round of adaptive density control (3DGS ``densify_and_prune``), then reset the stats.

        Args:
            config: Thresholds.
            extent: Scene extent in metres (GIC: half the cameras' nerf++ radius).
            optimizers: Optimizers whose state rows follow the Gaussians.
            max_screen_px: When given, also prune Gaussians whose 2D radius exceeded this many
                pixels or whose largest scale exceeds ``max_world_fraction * extent``.
            generator: CPU generator for the split samples (reproducible densification).

        Returns:
            ``{"cloned", "split", "pruned", "n"}``.
        """
        grads = self.mean_grad()
        max_scale = self.scales().max(dim=1).values
        big = max_scale > config.percent_dense * extent
        selected = grads >= config.grad_threshold
        clone_mask = selected & ~big
        split_mask = selected & big
        if config.max_gaussians is not None:
            budget = int(config.max_gaussians) - self.n
            n_c, n_s = int(clone_mask.sum()), int(split_mask.sum())
            growth = n_c + n_s * (config.split_count - 1)
            if growth > max(budget, 0):
                # take candidates by decreasing gradient until the budget is used up
                order = torch.argsort(torch.where(selected, grads, torch.full_like(grads, -1.0)), descending=True)
                cost = torch.where(split_mask, float(config.split_count - 1), 1.0)[order]
                take = (torch.cumsum(cost, 0) <= max(budget, 0)) & selected[order]
                chosen = torch.zeros_like(selected)
                chosen[order[take]] = True
                clone_mask &= chosen
                split_mask &= chosen
        n_clone = self.clone(clone_mask, optimizers)
        # the clones are appended at the end with zero gradient: they are never split this round
        split_mask = torch.cat([split_mask, torch.zeros(n_clone, dtype=torch.bool, device=split_mask.device)])
        n_split = self.split(
            split_mask, optimizers, count=config.split_count, scale_factor=config.split_scale_factor, generator=generator
        )
        remove = self.opacity < config.min_opacity
        if max_screen_px is not None:
            remove |= self.max_radii > max_screen_px
            remove |= self.scales().max(dim=1).values > config.max_world_fraction * extent
        if bool(remove.all()):  # never prune everything
            remove = torch.zeros_like(remove)
        n_pruned = self.prune(remove, optimizers)
        self.reset_densification_stats()
        return {"cloned": n_clone, "split": n_split, "pruned": n_pruned, "n": self.n}

    # ------------------------------------------------------------------ state

    def get_extra_state(self) -> dict:
        return {"sh_degree": self.sh_degree, "isotropic": self.isotropic, "n": self.n}

    def set_extra_state(self, state: dict) -> None:
        if state.get("sh_degree", self.sh_degree) != self.sh_degree or state.get("isotropic", self.isotropic) != self.isotropic:
            raise ValueError(
                f"checkpoint Gaussians have sh_degree={state.get('sh_degree')}, isotropic={state.get('isotropic')} "
                f"but this model has sh_degree={self.sh_degree}, isotropic={self.isotropic}"
            )

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs):
        # Resize to the checkpoint's N first so that loading a densified model just works.
        key = prefix + "means"
        if key in state_dict and state_dict[key].shape[0] != self.n:
            self.resize_(int(state_dict[key].shape[0]))
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)

    def extra_repr(self) -> str:
        return f"n={self.n}, sh_degree={self.sh_degree}, isotropic={self.isotropic}"

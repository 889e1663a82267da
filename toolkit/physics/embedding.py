"""Gaussians carried by the simulated particles.

Each Gaussian follows the displacement of its K nearest particles at frame 0:
``x_g(t) = x_g(0) + sum_k c_gk (p_k(t) - p_k(0))`` with fixed coefficients ``c_gk`` summing to 1.
The simulation then runs on a uniform-density particle set (the continuum), the number of Gaussians
does not change its cost, and gradients reach the particles' trajectories (hence x0, v0 and the
material) and the Gaussians' own positions.

Two choices of coefficients (:func:`embed`, ``mode``):

* ``"idw"`` (default): inverse-distance weights. They average the neighbours' displacements,
  which is exact for translations only: under a stretch ``A`` a Gaussian at ``x_g`` moves to the
  *neighbours' mean* ``A p_mean + b`` instead of ``A x_g + b``, so a Gaussian outside its
  neighbours' mean (on the surface) lags a stretch of the body.
* ``"affine"``: moving least squares with linear precision. ``c_gk`` are the weights of the value
  at ``x_g(0)`` of the weighted least-squares *affine* map that takes the neighbours' frame-0
  positions to their current ones, so any affine motion of the neighbourhood (translation,
  rotation, stretch, shear) moves the Gaussian exactly as it moves the material around it. It
  uses at least :data:`AFFINE_MIN_NEIGHBOURS` neighbours (3x the default's memory in
  :func:`carry`). Measured on a Newtonian scene of issue #20's benchmark (CPU, oracle and stage-0
  geometry), it did not change the fit: log10 mu ended 1.94 and 1.44 decades low with it, 1.88
  and 1.43 without. It is not the default for that reason.

A Gaussian's *shape* can follow the material too (:func:`local_deformation`,
:func:`carry_deformation`): its covariance becomes ``A Sigma A^T`` with ``A`` the least-squares
deformation gradient of its neighbourhood since frame 0 (``gaussian_shape="deformed"`` in the fit).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from toolkit.mls import mls_neighbourhoods

__all__ = ["embed", "carry", "local_deformation", "carry_deformation", "EMBEDDING_MODES", "GAUSSIAN_SHAPES",
           "AFFINE_MIN_NEIGHBOURS"]

#: values of :func:`embed`'s ``mode``
EMBEDDING_MODES = ("affine", "idw")
#: how a carried Gaussian's shape changes: ``"rigid"`` (never) or ``"deformed"`` (:func:`carry_deformation`)
GAUSSIAN_SHAPES = ("rigid", "deformed")
#: the affine fit reaches at least this many neighbours: past the outer particle layer, so that a
#: Gaussian outside the body has neighbours in depth and the fit is well-posed in 3D (measured on a
#: 1 cm lattice: 16 neighbours lose the stretch normal to a flat face 1.5 spacings out, 24 do not)
AFFINE_MIN_NEIGHBOURS = 24


def embed(gaussian_means: torch.Tensor, particles: torch.Tensor, k: int = 8, eps: float = 1e-4,
          mode: str = "idw", ridge: float = 1e-6):
    """Embedding weights of Gaussians in the particle set at frame 0 (see the module docstring).

    Args:
        gaussian_means: (G, 3) metres.
        particles: (N, 3) metres.
        k: neighbours per Gaussian (clamped to N); ``"affine"`` uses at least
            :data:`AFFINE_MIN_NEIGHBOURS`.
        eps: metres added to distances so a Gaussian on a particle does not divide by zero (``idw``).
        mode: ``"idw"`` (inverse distance, default) or ``"affine"`` (linear precision).
        ridge: Tikhonov weight on the affine fit's linear part, relative to the neighbourhood's
            scale: a guard against flat (coplanar) neighbourhoods only.

    Returns:
        ``(index (G, k) int64, weight (G, k) float32)``, weights summing to 1 per Gaussian;
        ``"affine"`` weights can be negative (extrapolation to a Gaussian outside its neighbours).

    Raises:
        ValueError: an unknown ``mode``.
    """
    if mode not in EMBEDDING_MODES:
        raise ValueError(f"embedding mode must be one of {EMBEDDING_MODES}, got {mode!r}")
    n = particles.shape[0]
    if mode == "affine" and n >= 4:
        k = max(k, AFFINE_MIN_NEIGHBOURS)
    k = min(k, n)
    P = particles.detach().cpu().numpy().astype(np.float64)
    V = gaussian_means.detach().cpu().numpy().astype(np.float64)
    if mode == "affine" and n >= 4:
        idx, w = _affine_weights(P, V, k, ridge)
    else:
        dist, idx = cKDTree(P).query(V, k=k)
        dist = np.asarray(dist).reshape(len(V), k)
        idx = np.asarray(idx).reshape(len(V), k)
        w = 1.0 / (dist + eps)
        w = w / w.sum(1, keepdims=True)
    return torch.as_tensor(idx, dtype=torch.int64), torch.as_tensor(w, dtype=torch.float32)


def _affine_weights(P: np.ndarray, V: np.ndarray, k: int, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour indices (G, k) and the affine fit's value at each ``v`` as weights of their positions."""
    fit = mls_neighbourhoods(P, V, k, ridge)
    c = fit.value_coefficients()
    return fit.indices, c / c.sum(axis=1, keepdims=True)


def local_deformation(gaussian_means: torch.Tensor, particles0: torch.Tensor, k: int = AFFINE_MIN_NEIGHBOURS,
                      ridge: float = 1e-6):
    """Each Gaussian's local deformation gradient as a fixed linear map of the particle positions.

    Args:
        gaussian_means: (G, 3) means at frame 0, metres.
        particles0: (N, 3) particle positions at frame 0, metres (N >= 4).
        k: neighbours of the fit (at least 4).
        ridge: see :func:`embed`.

    Returns:
        ``(index (G, k) int64, gradient (G, k, 3) float32)``: for particle positions ``p`` (N, 3)
        at any frame, ``A_g = sum_k p[index[g, k]] outer gradient[g, k]`` (3x3) is the gradient of the
        weighted least-squares affine map from the frame-0 neighbourhood to the current one: exactly
        ``A`` when the neighbourhood moved by ``x -> A x + b``, the identity at frame 0. A Gaussian's
        covariance follows the material as ``A Sigma A^T``.
    """
    n = particles0.shape[0]
    if n < 4:
        raise ValueError(f"a local deformation needs at least 4 particles, got {n}")
    k = min(max(k, 4), n)
    fit = mls_neighbourhoods(particles0.detach().cpu().numpy(), gaussian_means.detach().cpu().numpy(), k, ridge)
    return torch.as_tensor(fit.indices, dtype=torch.int64), torch.as_tensor(fit.gradient_coefficients(), dtype=torch.float32)


def carry(gaussian_means0: torch.Tensor, positions: torch.Tensor, positions0: torch.Tensor, index: torch.Tensor,
          weight: torch.Tensor) -> torch.Tensor:
    """Gaussian means at the frames of ``positions``.

    Args:
        gaussian_means0: (G, 3) means at frame 0.
        positions: (F, N, 3) particle positions at F frames.
        positions0: (N, 3) particle positions at frame 0.
        index, weight: from :func:`embed`.

    Returns:
        (F, G, 3) means.
    """
    disp = positions - positions0.unsqueeze(0)  # (F, N, 3)
    return gaussian_means0.unsqueeze(0) + (disp[:, index] * weight[None, :, :, None]).sum(2)


def carry_deformation(positions: torch.Tensor, positions0: torch.Tensor, index: torch.Tensor,
                      gradient: torch.Tensor) -> torch.Tensor:
    """Each Gaussian's deformation gradient since frame 0 at the frames of ``positions``.

    ``A_g(t) = L_g(p(t)) L_g(p(0))^-1`` with ``L_g(p) = sum_k p[index[g, k]] outer gradient[g, k]``
    (:func:`local_deformation`): the identity at frame 0 even when ``positions0`` moved away from the
    positions the coefficients were fitted on (a fit's position offsets), and exactly ``A`` when a
    neighbourhood moved by ``x -> A x + b``. Differentiable in ``positions`` and ``positions0``.

    Args:
        positions: (F, N, 3) particle positions at F frames, metres.
        positions0: (N, 3) particle positions at frame 0, metres.
        index, gradient: from :func:`local_deformation`, (G, k) and (G, k, 3).

    Returns:
        (F, G, 3, 3) linear maps, for :attr:`renderers.base.Gaussians.deformation`.
    """
    # the coefficients sum to zero over k: positions relative to the first neighbour give the same
    # maps with less float32 cancellation (metres from the origin against centimetres apart)
    rel0 = positions0[index] - positions0[index[:, :1]]
    rel = positions[:, index] - positions[:, index[:, :1]]
    L0 = torch.einsum("gki,gkj->gij", rel0, gradient)
    Lt = torch.einsum("fgki,gkj->fgij", rel, gradient)
    return Lt @ torch.linalg.inv(L0).unsqueeze(0)

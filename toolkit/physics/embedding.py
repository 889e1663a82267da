"""Gaussians carried by the simulated particles.

Each Gaussian follows the displacement of its K nearest particles at frame 0, weighted by
inverse distance: ``x_g(t) = x_g(0) + sum_k w_gk (p_k(t) - p_k(0))``. The simulation then runs
on a uniform-density particle set (the continuum), the number of Gaussians does not change its
cost, and gradients reach the particles' trajectories (hence x0, v0 and the material) and the
Gaussians' own positions.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

__all__ = ["embed", "carry"]


def embed(gaussian_means: torch.Tensor, particles: torch.Tensor, k: int = 8, eps: float = 1e-4):
    """Embedding weights of Gaussians in the particle set at frame 0.

    Args:
        gaussian_means: (G, 3) metres.
        particles: (N, 3) metres.
        k: neighbours per Gaussian (clamped to N).
        eps: metres added to distances so a Gaussian on a particle does not divide by zero.

    Returns:
        ``(index (G, k) int64, weight (G, k) float32)``, weights summing to 1 per Gaussian.
    """
    k = min(k, particles.shape[0])
    tree = cKDTree(particles.detach().cpu().numpy().astype(np.float64))
    dist, idx = tree.query(gaussian_means.detach().cpu().numpy().astype(np.float64), k=k)
    dist = np.asarray(dist).reshape(len(gaussian_means), k)
    idx = np.asarray(idx).reshape(len(gaussian_means), k)
    w = 1.0 / (dist + eps)
    w = w / w.sum(1, keepdims=True)
    return torch.as_tensor(idx, dtype=torch.int64), torch.as_tensor(w, dtype=torch.float32)


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

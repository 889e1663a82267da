"""Carrying surface vertices with the simulated particles (moving-least-squares embedding).

Each rest vertex ``v`` is tied to its ``k`` nearest rest particles ``p_j``. At time t its position
is the value at ``v`` of the weighted least-squares *affine* map that best takes the
neighbours' rest positions to their current ones::

    x_v(t) = sum_j c_vj p_j(t),    c_vj = w_j [p_j - v, 1]^T (sum_i w_i [p_i - v, 1][p_i - v, 1]^T)^-1 e_4

with weights ``w_j = (1 - r_j^2 / R^2)^3`` of the rest distances (R just beyond the k-th
neighbour). The coefficients are computed once; they sum to 1 and reproduce any affine motion
(translation, rotation, stretch) of the neighbourhood exactly (the rest pose included), so the
surface follows the body however fast it moves and can never detach from it.

Why not the simulator's passive tracers (``MPMSimulator.rollout(tracers=...)``)? Those move with
the grid velocity interpolated over all 27 stencil nodes, and empty nodes count as velocity 0:
a point more than ~0.7 dx outside the particles lags behind (3 % at 0.75 dx, 61 % at 1 dx in
uniform motion), so at an impact surface vertices fall behind, detach and freeze in the air.
"""

from __future__ import annotations

import numpy as np

from toolkit.mls import mls_neighbourhoods

__all__ = ["SurfaceEmbedding"]


class SurfaceEmbedding:
    """Fixed linear map from particle positions to surface vertex positions (see the module docstring).

    Args:
        rest_particles: (N, 3) particle positions at rest, metres.
        rest_vertices: (V, 3) surface vertex positions at rest, metres.
        k: neighbours per vertex (>= 4; capped at N). The default 24 reaches past the outer
            particle layer, so the fit is well-posed in 3D (measured: ``sum |c_vj| <= 3.4`` over the
            built-in shapes, i.e. little amplification of particle noise).
        ridge: Tikhonov weight on the linear part of the fit, relative to the neighbourhood
            scale; only a guard against singular neighbourhoods (a large value shrinks the
            extrapolation from the particles to the surface and pulls the surface inward).
    """

    def __init__(self, rest_particles: np.ndarray, rest_vertices: np.ndarray, k: int = 24, ridge: float = 1e-8):
        P = np.asarray(rest_particles, dtype=np.float64)
        V = np.asarray(rest_vertices, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3 or len(P) < 4:
            raise ValueError(f"rest_particles must have shape (N, 3) with N >= 4, got {P.shape}")
        if V.ndim != 2 or V.shape[1] != 3:
            raise ValueError(f"rest_vertices must have shape (V, 3), got {V.shape}")
        k = int(min(max(k, 4), len(P)))
        fit = mls_neighbourhoods(P, V, k, ridge)
        self.indices = fit.indices
        self.coefficients = fit.value_coefficients()  # (V, k), rows sum to 1

    def __call__(self, particles: np.ndarray) -> np.ndarray:
        """(N, 3) or (T, N, 3) particle positions -> (V, 3) or (T, V, 3) float32 vertex positions."""
        p = np.asarray(particles, dtype=np.float64)
        out = np.einsum("...vkc,vk->...vc", p[..., self.indices, :], self.coefficients)
        return out.astype(np.float32)

"""Moving least squares with linear precision: a point's value and gradient as fixed weights of
its neighbours' values.

For a point ``v`` and its ``k`` nearest points ``p_j`` (rest positions), the weighted least-squares
affine fit of any per-neighbour quantity ``y_j`` is ``y(x) = sum_j y_j (g_j . (x - v) + c_j)`` with

    c_j = w_j [p_j - v, 1]^T M^-1 e_4,    g_j = (w_j M^-1 [p_j - v, 1])[:3],
    M = sum_j w_j [p_j - v, 1][p_j - v, 1]^T,    w_j = (1 - d_j^2 / R^2)^3 (R just beyond the k-th),

so ``sum_j c_j y_j`` is the fit's value at ``v`` and ``sum_j y_j g_j^T`` its gradient. Both reproduce
any affine field exactly. A ridge on the linear part of ``M`` guards against flat (coplanar)
neighbourhoods. Used to carry the generator's surface with its particles
(:mod:`toolkit.synthetic.embedding`) and the fit's Gaussians with theirs
(:mod:`toolkit.physics.embedding`). Plain numpy, float64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["MLSNeighbourhoods", "mls_neighbourhoods"]


class MLSNeighbourhoods:
    """The fits of every point's neighbourhood (see the module docstring).

    Attributes:
        indices: (V, k) int neighbour indices into the rest points.
        weights: (V, k) float64 ``w_j``.
        X: (V, k, 4) float64 rows ``[p_j - v, 1]``.
        M: (V, 4, 4) float64 moment matrices, ridge included.
    """

    def __init__(self, indices: np.ndarray, weights: np.ndarray, X: np.ndarray, M: np.ndarray):
        self.indices, self.weights, self.X, self.M = indices, weights, X, M

    def value_coefficients(self) -> np.ndarray:
        """(V, k) ``c_j``; rows sum to 1 (up to round-off)."""
        e4 = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), (len(self.M), 4))[..., None]
        q = np.linalg.solve(self.M, e4)[..., 0]
        return self.weights * np.einsum("vki,vi->vk", self.X, q)

    def gradient_coefficients(self) -> np.ndarray:
        """(V, k, 3) ``g_j``; ``sum_j g_j = 0`` and ``sum_j p_j g_j^T = I`` (up to the ridge)."""
        Minv = np.linalg.inv(self.M)
        return self.weights[..., None] * np.einsum("vij,vkj->vki", Minv, self.X)[..., :3]


def mls_neighbourhoods(points: np.ndarray, queries: np.ndarray, k: int, ridge: float) -> MLSNeighbourhoods:
    """Fits around each of ``queries`` (V, 3) from its ``k`` nearest ``points`` (N, 3), metres.

    Args:
        points: (N, 3) rest positions, N >= k.
        queries: (V, 3) where the value and gradient are wanted.
        k: neighbours per query.
        ridge: Tikhonov weight on the linear part, relative to the neighbourhood's scale.
    """
    P = np.asarray(points, dtype=np.float64)
    V = np.asarray(queries, dtype=np.float64)
    dist, idx = cKDTree(P).query(V, k=k)
    dist = np.asarray(dist).reshape(len(V), k)
    idx = np.asarray(idx).reshape(len(V), k)
    R = 1.05 * dist[:, -1:] + 1e-12
    w = (1.0 - (dist / R) ** 2) ** 3 + 1e-9  # (V, k)
    X = np.concatenate([P[idx] - V[:, None, :], np.ones((len(V), k, 1))], axis=2)  # (V, k, 4)
    M = np.einsum("vk,vki,vkj->vij", w, X, X)
    reg = ridge * (R[:, 0] ** 2) * w.sum(axis=1)
    M[:, 0, 0] += reg
    M[:, 1, 1] += reg
    M[:, 2, 2] += reg
    return MLSNeighbourhoods(idx, w, X, M)

"""SVD-based isotropic updates with a gradient that is exact at repeated singular values.

The plasticity models (plasticine, sand, non-Newtonian) act on the principal stretches: with
``F_tmp = U diag(sigma) V^T`` they compute new stretches ``g(sigma)`` (return mapping) and
principal Kirchhoff stresses ``h(sigma)``, and return

    F_new = U diag(g) V^T,        tau = U diag(h) U^T.

Differentiating through ``wp.svd3`` loses the shear part of the derivative where singular values
coincide (at rest every particle has F = I): the textbook SVD adjoint divides by
``sigma_i^2 - sigma_j^2``, and a guard such as ``d / (d^2 + eps)`` silently zeroes the term. We
instead differentiate the whole isotropic map. In the frame of the singular vectors, with
``P = U^T dF V``, the off-diagonal part of the differential is (i != j)::

    (U^T dF_new V)_ij = 1/2 [(A + B) P_ij + (A - B) P_ji],   A = (g_i - g_j)/(s_i - s_j),
                                                              B = (g_i + g_j)/(s_i + s_j),
    (U^T dtau U)_ij   = D (s_j P_ij + s_i P_ji),             D = (h_i - h_j)/(s_i^2 - s_j^2),

and the diagonal part is the ordinary derivative of g and h (done by Warp's autodiff). The
divided differences A and D have finite limits at ``s_i = s_j``; near coincidence we evaluate
the principal map again at a point where the pair is pulled apart by a relative 1e-3, which
gives the limit to that accuracy (for the smooth branches; on a yield kink it gives the mean
slope across it).

Two private custom-gradient Warp functions implement this: ``_svd_iso`` (whose U-adjoint
carries ``U Z`` with Z the rotation-frame adjoint) and ``iso_compose`` (generated per material,
since its adjoint re-evaluates that material's principal map).
"""

from __future__ import annotations

import warp as wp

__all__ = [
    "make_isotropic_update",
    "MIN_SINGULAR_VALUE",
    "clamp_singular_values",
    "safe_norm",
    "lame_from_young",
    "hencky_stress",
    "log_stretch",
    "exp_stretch",
]

#: singular values of F_tmp are clamped at this value before the return mapping (DESIGN 4).
MIN_SINGULAR_VALUE = 0.05
#: relative separation of a near-repeated pair of singular values in the divided differences.
_SEPARATION = 1.0e-3


@wp.func
def clamp_singular_values(s: wp.vec3):
    return wp.vec3(
        wp.max(s[0], MIN_SINGULAR_VALUE), wp.max(s[1], MIN_SINGULAR_VALUE), wp.max(s[2], MIN_SINGULAR_VALUE)
    )


@wp.func
def safe_norm(x: wp.vec3):
    """sqrt(x.x + 1e-8): differentiable at 0 (DESIGN 4)."""
    return wp.sqrt(wp.dot(x, x) + 1.0e-8)


@wp.func
def lame_from_young(E: float, nu: float):
    """(mu, lambda) in Pa from Young's modulus E (Pa) and Poisson's ratio nu."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@wp.func
def log_stretch(s: wp.vec3):
    """Principal Hencky strain ln(sigma)."""
    return wp.vec3(wp.log(s[0]), wp.log(s[1]), wp.log(s[2]))


@wp.func
def exp_stretch(e: wp.vec3):
    """Principal stretches exp(epsilon)."""
    return wp.vec3(wp.exp(e[0]), wp.exp(e[1]), wp.exp(e[2]))


@wp.func
def hencky_stress(e: wp.vec3, mu: float, lam: float):
    """Principal Kirchhoff stress of the Hencky (St. Venant-Kirchhoff in log strain) model, Pa."""
    tr = e[0] + e[1] + e[2]
    return e * (2.0 * mu) + wp.vec3(lam * tr)


@wp.func
def _svd_iso(F: wp.mat33):
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    return U, s, V


@wp.func_grad(_svd_iso)
def _adj_svd_iso(F: wp.mat33, adj_U: wp.mat33, adj_s: wp.vec3, adj_V: wp.mat33):
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    # adj_U holds U @ Z (written by iso_compose); adj_V is never written.
    Z = wp.transpose(U) @ adj_U + wp.diag(adj_s)
    wp.adjoint[F] += U @ Z @ wp.transpose(V)


@wp.func
def _nonzero(x: float):
    if wp.abs(x) < 1.0e-6:
        if x >= 0.0:
            return 1.0e-6
        return -1.0e-6
    return x


def make_isotropic_update(principal):
    """Build a material update from a principal-space map.

    Args:
        principal: a ``@wp.func`` ``(s: vec3, dt: float, p: array2d(float), row: int) -> (g: vec3, h: vec3)``
            taking the clamped singular values of ``F_tmp`` and returning the new elastic
            stretches ``g`` and the principal Kirchhoff stresses ``h`` (Pa) of the new state.
            It must be symmetric under permutations of the three axes.

    Returns:
        A ``@wp.func`` ``update(F_tmp, C, J, dt, p, row) -> (F_new, J, tau)``.
    """

    @wp.func
    def iso_compose(
        U: wp.mat33, s: wp.vec3, V: wp.mat33, g: wp.vec3, h: wp.vec3, dt: float, p: wp.array2d(dtype=float), row: int
    ):
        return U @ wp.diag(g) @ wp.transpose(V), U @ wp.diag(h) @ wp.transpose(U)

    @wp.func_grad(iso_compose)
    def adj_iso_compose(
        U: wp.mat33,
        s: wp.vec3,
        V: wp.mat33,
        g: wp.vec3,
        h: wp.vec3,
        dt: float,
        p: wp.array2d(dtype=float),
        row: int,
        adj_G: wp.mat33,
        adj_T: wp.mat33,
    ):
        Q = wp.transpose(U) @ adj_G @ V
        R = wp.transpose(U) @ adj_T @ U
        wp.adjoint[g] += wp.vec3(Q[0, 0], Q[1, 1], Q[2, 2])
        wp.adjoint[h] += wp.vec3(R[0, 0], R[1, 1], R[2, 2])
        Z = wp.mat33(0.0)
        for i in range(3):
            for j in range(3):
                if i != j:
                    si = s[i]
                    sj = s[j]
                    scale = wp.max(wp.max(wp.abs(si), wp.abs(sj)), MIN_SINGULAR_VALUE)
                    A = float(0.0)
                    Dh = float(0.0)
                    if wp.abs(si - sj) < _SEPARATION * scale:
                        m = 0.5 * (si + sj)
                        ss = s
                        ss[i] = m + 0.5 * _SEPARATION * scale
                        ss[j] = m - 0.5 * _SEPARATION * scale
                        g2, h2 = principal(clamp_singular_values(ss), dt, p, row)
                        A = (g2[i] - g2[j]) / (ss[i] - ss[j])
                        Dh = (h2[i] - h2[j]) / (ss[i] - ss[j])
                    else:
                        A = (g[i] - g[j]) / (si - sj)
                        Dh = (h[i] - h[j]) / (si - sj)
                    B = (g[i] + g[j]) / _nonzero(si + sj)
                    D = Dh / _nonzero(si + sj)
                    Z[i, j] = 0.5 * ((A + B) * Q[i, j] + (A - B) * Q[j, i]) + sj * D * (R[i, j] + R[j, i])
        wp.adjoint[U] += U @ Z

    @wp.func
    def update(F_tmp: wp.mat33, C: wp.mat33, J: float, dt: float, p: wp.array2d(dtype=float), row: int):
        U, s, V = _svd_iso(F_tmp)
        g, h = principal(clamp_singular_values(s), dt, p, row)
        F_new, tau = iso_compose(U, s, V, g, h, dt, p, row)
        return F_new, J, tau

    return update

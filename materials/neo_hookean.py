"""Compressible neo-Hookean elasticity (the PAC-NeRF / GIC elastic model)."""

from __future__ import annotations

import warp as wp

from materials import register_material
from materials.base import Material, MaterialParam
from materials.isotropic import lame_from_young

__all__ = ["NeoHookean", "YOUNGS_MODULUS", "POISSON_RATIO", "MIN_VOLUME_RATIO"]

#: det(F) is floored here so ln J stays finite if an element inverts (J <= 0 is a failed step).
MIN_VOLUME_RATIO = 1.0e-4

YOUNGS_MODULUS = MaterialParam(
    "E", 10**5.5, "log10", low=0.0, high=1e12, units="Pa", description="Young's modulus", search=(10**3.5, 10**6.5)
)
#: valid down to -0.99 (auxetic foams); a fit keeps it in [0, 0.49] unless its fit range is widened
POISSON_RATIO = MaterialParam(
    "nu", 0.25, "tanh", low=-0.99, high=0.49, description="Poisson's ratio (tanh-bounded)", search=(0.05, 0.45),
    fit_range=(0.0, 0.49),
)


@wp.func
def _update(F_tmp: wp.mat33, C: wp.mat33, J: float, dt: float, p: wp.array2d(dtype=float), row: int):
    mu, lam = lame_from_young(p[row, 0], p[row, 1])
    det = wp.max(wp.determinant(F_tmp), MIN_VOLUME_RATIO)
    tau = mu * (F_tmp @ wp.transpose(F_tmp)) + (lam * wp.log(det) - mu) * wp.identity(n=3, dtype=float)
    return F_tmp, J, tau


@register_material("neo_hookean")
class NeoHookean(Material):
    """Neo-Hookean elasticity, no plasticity.

    Kirchhoff stress ``tau = mu F F^T + (lambda ln J - mu) I`` with ``J = det F``,
    ``mu = E / (2 (1 + nu))``, ``lambda = E nu / ((1 + nu)(1 - 2 nu))``. Computed without an SVD,
    so its gradient is exact everywhere (J is floored at 1e-4 for inverted elements).

    Parameters: ``E`` (Pa, optimized as log10, default 10^5.5), ``nu`` (tanh-bounded to
    [-0.99, 0.49], default 0.25).
    """

    params = (YOUNGS_MODULUS, POISSON_RATIO)

    def build_update(self):
        return _update

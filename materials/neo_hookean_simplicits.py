"""Neo-Hookean elasticity in the Simplicits / Vid2Sim (Kaolin) form."""

from __future__ import annotations

import warp as wp

from materials import register_material
from materials.base import Material
from materials.isotropic import lame_from_young
from materials.neo_hookean import POISSON_RATIO, YOUNGS_MODULUS


@wp.func
def _update(F_tmp: wp.mat33, C: wp.mat33, J: float, dt: float, p: wp.array2d(dtype=float), row: int):
    mu, lam = lame_from_young(p[row, 0], p[row, 1])
    det = wp.determinant(F_tmp)
    tau = mu * (F_tmp @ wp.transpose(F_tmp)) + det * (lam * (det - 1.0) - mu) * wp.identity(n=3, dtype=float)
    return F_tmp, J, tau


@register_material("neo_hookean_simplicits")
class NeoHookeanSimplicits(Material):
    """Neo-Hookean elasticity as in Simplicits / Vid2Sim.

    Energy ``psi = mu/2 (tr(F^T F) - 3) - mu (J - 1) + lambda/2 (J - 1)^2`` gives the Kirchhoff
    stress ``tau = mu F F^T + J (lambda (J - 1) - mu) I``. Defined for any J (no logarithm).
    Same parameters as :class:`~materials.neo_hookean.NeoHookean`.
    """

    params = (YOUNGS_MODULUS, POISSON_RATIO)

    def build_update(self):
        return _update

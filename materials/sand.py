"""Sand: Hencky elasticity with Drucker-Prager plasticity (Klar et al. 2016)."""

from __future__ import annotations

import math

import warp as wp

from materials import register_material
from materials.base import Material, MaterialParam
from materials.isotropic import exp_stretch, hencky_stress, lame_from_young, log_stretch, make_isotropic_update, safe_norm
from materials.neo_hookean import POISSON_RATIO

__all__ = ["Sand"]

_SQRT_2_3 = 0.816496580927726
_DEG = math.pi / 180.0


@wp.func
def _principal(s: wp.vec3, dt: float, p: wp.array2d(dtype=float), row: int):
    sin_phi = wp.sin(p[row, 0] * _DEG)
    mu, lam = lame_from_young(p[row, 1], p[row, 2])
    alpha = _SQRT_2_3 * 2.0 * sin_phi / (3.0 - sin_phi)
    e = log_stretch(s)
    tr = e[0] + e[1] + e[2]
    if tr >= 0.0:
        # tension: sand cannot hold it, the elastic strain is removed entirely
        e = wp.vec3(0.0)
    else:
        dev = e - wp.vec3(tr / 3.0)
        dev_norm = safe_norm(dev)
        dgamma = dev_norm + (3.0 * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
        if dgamma > 0.0:
            e = e - dev * (dgamma / dev_norm)
    return exp_stretch(e), hencky_stress(e, mu, lam)


@register_material("sand")
class Sand(Material):
    """Drucker-Prager sand (PAC-NeRF / GIC).

    ``alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi))``; with ``eps = ln sigma``: if ``tr eps >= 0``
    (tension) ``eps <- 0``; otherwise ``dgamma = |eps_hat| + (3 lambda + 2 mu) / (2 mu) tr(eps) alpha``
    and ``eps <- eps - max(dgamma, 0) eps_hat / |eps_hat|``. Hencky stress.

    Parameters: ``friction_angle`` phi (degrees, linear, default 10, optimized), ``E`` (Pa,
    default 1e6 as PAC-NeRF, fixed) and ``nu`` (default 0.3, fixed).
    """

    params = (
        MaterialParam(
            "friction_angle", 10.0, "linear", low=0.0, high=89.0, units="deg", description="friction angle phi",
            search=(10.0, 50.0),
        ),
        MaterialParam("E", 1e6, "log10", low=0.0, high=1e12, optimize=False, units="Pa", description="Young's modulus"),
        MaterialParam(
            "nu", 0.3, "tanh", low=POISSON_RATIO.low, high=POISSON_RATIO.high, optimize=False,
            description="Poisson's ratio",
        ),
    )
    uses_svd = True

    def build_update(self):
        return make_isotropic_update(_principal)

"""Non-Newtonian (viscoplastic, Herschel-Bulkley-like) fluid with a von Mises yield surface."""

from __future__ import annotations

import numpy as np
import warp as wp

from materials import register_material
from materials.base import Material, MaterialParam
from materials.isotropic import exp_stretch, hencky_stress, log_stretch, make_isotropic_update, safe_norm

__all__ = ["NonNewtonian"]

_SQRT_2_3 = 0.816496580927726


@wp.func
def _principal(s: wp.vec3, dt: float, p: wp.array2d(dtype=float), row: int):
    mu = p[row, 0]
    kappa = p[row, 1]
    yield_stress = p[row, 2]
    eta = p[row, 3]
    lam = kappa - 2.0 * mu / 3.0
    e = log_stretch(s)
    tr = e[0] + e[1] + e[2]
    dev = e - wp.vec3(tr / 3.0)
    s_dev = dev * (2.0 * mu)
    s_norm = safe_norm(s_dev)
    y = s_norm - _SQRT_2_3 * yield_stress
    if y > 0.0:
        mu_hat = mu * wp.dot(s, s) / 3.0
        s_norm_new = s_norm - y / (1.0 + eta / (2.0 * mu_hat * dt))
        e = s_dev * (s_norm_new / s_norm) / (2.0 * mu) + wp.vec3(tr / 3.0)
    return exp_stretch(e), hencky_stress(e, mu, lam)


@register_material("non_newtonian")
class NonNewtonian(Material):
    """Viscoplastic fluid (PAC-NeRF / GIC non-Newtonian model).

    With ``lambda = kappa - 2 mu / 3`` and principal Hencky strain ``eps = ln sigma``: the
    deviatoric stress ``s = 2 mu (eps - tr(eps)/3)`` is compared with the yield surface
    ``y = |s| - sqrt(2/3) tau_Y``; when ``y > 0`` its norm is reduced by
    ``y / (1 + eta / (2 mu_hat dt))`` with ``mu_hat = mu sum(sigma^2) / 3`` (viscous return
    mapping) and the strain rebuilt from it. Kirchhoff stress ``tau = U diag(2 mu eps + lambda tr eps) U^T``.

    Parameters (all log10): ``mu`` shear modulus (Pa, default 100), ``kappa`` bulk
    modulus (default 1e5), ``yield_stress`` tau_Y (Pa, default 10), ``plastic_viscosity`` eta
    (default 1).
    """

    params = (
        MaterialParam("mu", 100.0, "log10", low=0.0, high=1e9, units="Pa", description="shear modulus",
                      search=(10**1.5, 10**4.5)),
        MaterialParam("kappa", 1e5, "log10", low=0.0, high=1e12, units="Pa", description="bulk modulus",
                      search=(10**3.5, 10**6.5)),
        MaterialParam("yield_stress", 10.0, "log10", low=0.0, high=1e9, units="Pa", description="yield stress tau_Y",
                      search=(10**0.5, 10**3.5)),
        MaterialParam("plastic_viscosity", 1.0, "log10", low=0.0, high=1e9, units="Pa s",
                      description="plastic viscosity eta", search=(10**-1.5, 10**1.5)),
    )
    uses_svd = True

    def wave_speed(self, values, density):
        """P-wave ``sqrt((kappa + 4 mu / 3) / rho)`` (m/s); the viscous return mapping is implicit,
        so the plastic viscosity sets no limit."""
        modulus = np.asarray(values["kappa"], np.float64) + 4.0 / 3.0 * np.asarray(values["mu"], np.float64)
        return np.sqrt(np.maximum(modulus, 0.0) / density)

    def build_update(self):
        return make_isotropic_update(_principal)

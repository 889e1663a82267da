"""Newtonian fluid: viscosity and a bulk modulus, state is the volume ratio J."""

from __future__ import annotations

import numpy as np
import warp as wp

from materials import register_material
from materials.base import Material, MaterialParam

__all__ = ["Newtonian", "VISCOSITY", "BULK_MODULUS", "MIN_FLUID_VOLUME_RATIO"]

#: the tracked volume ratio J is clamped at this value (DESIGN 4).
MIN_FLUID_VOLUME_RATIO = 0.05

VISCOSITY = MaterialParam("mu", 10.0, "log10", low=0.0, high=1e9, units="Pa s", description="dynamic viscosity",
                          search=(10**-1.5, 10**2.5))
BULK_MODULUS = MaterialParam("kappa", 1e4, "log10", low=0.0, high=1e12, units="Pa", description="bulk modulus",
                             search=(1e3, 1e6))


@wp.func
def _update(F_tmp: wp.mat33, C: wp.mat33, J: float, dt: float, p: wp.array2d(dtype=float), row: int):
    mu = p[row, 0]
    kappa = p[row, 1]
    J_new = wp.max((1.0 + dt * wp.trace(C)) * J, MIN_FLUID_VOLUME_RATIO)
    pressure_term = kappa * (J_new - wp.pow(J_new, -6.0))
    tau = pressure_term * wp.identity(n=3, dtype=float) + (mu * J_new * 0.5) * (C + wp.transpose(C))
    return wp.identity(n=3, dtype=float), J_new, tau


@register_material("newtonian")
class Newtonian(Material):
    """Newtonian fluid (PAC-NeRF / GIC form).

    The volume ratio is tracked as ``J <- (1 + dt tr C) J`` (clamped at 0.05) and the Kirchhoff
    stress is ``tau = kappa (J - J^-6) I + mu J (C + C^T) / 2`` with C the APIC velocity gradient.
    F is not tracked (kept at the identity).

    Parameters: ``mu`` viscosity (Pa s, log10, default 10), ``kappa`` bulk modulus (Pa, log10,
    default 1e4).
    """

    params = (VISCOSITY, BULK_MODULUS)
    tracks_volume_only = True

    def wave_speed(self, values, density):
        """Pressure wave ``sqrt(7 kappa / rho)``: ``d/dJ kappa (J - J^-6) = 7 kappa`` at J = 1 (m/s)."""
        return np.sqrt(7.0 * np.asarray(values["kappa"], np.float64) / density)

    def viscous_dt(self, values, density, dx):
        """Explicit diffusion limit ``dt <= rho dx^2 / (6 mu)`` (s); ``tau = mu J sym(C)`` is a
        viscosity of mu / 2 in ``2 mu_s D`` form, so this keeps a factor 2 of margin."""
        mu = np.asarray(values["mu"], np.float64)
        return density * dx**2 / (6.0 * np.maximum(mu, 1e-30))

    def build_update(self):
        return _update

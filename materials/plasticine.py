"""Plasticine: Hencky elasticity with von Mises plasticity."""

from __future__ import annotations

import warp as wp

from materials import register_material
from materials.base import Material, MaterialError, MaterialParam
from materials.isotropic import exp_stretch, hencky_stress, lame_from_young, log_stretch, make_isotropic_update, safe_norm
from materials.neo_hookean import POISSON_RATIO

__all__ = ["Plasticine"]

_SQRT_2_3 = 0.816496580927726


def _make_principal(yield_factor: float):
    @wp.func
    def principal(s: wp.vec3, dt: float, p: wp.array2d(dtype=float), row: int):
        mu, lam = lame_from_young(p[row, 0], p[row, 1])
        yield_stress = p[row, 2]
        e = log_stretch(s)
        tr = e[0] + e[1] + e[2]
        dev = e - wp.vec3(tr / 3.0)
        dev_norm = safe_norm(dev)
        y = dev_norm - yield_factor * yield_stress / (2.0 * mu)
        if y > 0.0:
            e = e - dev * (y / dev_norm)
        return exp_stretch(e), hencky_stress(e, mu, lam)

    return principal


@register_material("plasticine")
class Plasticine(Material):
    """Von Mises plasticity on Hencky strain (PAC-NeRF / GIC plasticine).

    With ``eps = ln sigma`` and ``eps_hat = eps - tr(eps)/3``: ``y = |eps_hat| - c tau_Y / (2 mu)``;
    if ``y > 0`` the strain is projected back, ``eps <- eps - y eps_hat / |eps_hat|``. Kirchhoff
    stress ``tau = U diag(2 mu eps + lambda tr eps) U^T``.

    Options:
        yield_rule: ``"gic"`` (default, c = 1) or ``"pacnerf"`` (c = sqrt(2/3)).

    Parameters: ``E`` (Pa, log10, default 1e4), ``nu`` (tanh, default 0.25), ``yield_stress``
    tau_Y (Pa, log10, default 1e3).
    """

    params = (
        MaterialParam("E", 1e4, "log10", low=0.0, high=1e12, units="Pa", description="Young's modulus",
                      search=(10**3.5, 10**6.5)),
        POISSON_RATIO,
        MaterialParam("yield_stress", 1e3, "log10", low=0.0, high=1e12, units="Pa", description="yield stress tau_Y",
                      search=(10**1.5, 10**4.5)),
    )
    uses_svd = True
    option_defaults = {"yield_rule": "gic"}

    def __init__(self, yield_rule: str = "gic"):
        super().__init__(yield_rule=yield_rule)
        if self.options["yield_rule"] not in ("gic", "pacnerf"):
            raise MaterialError(f"plasticine yield_rule must be 'gic' or 'pacnerf', got {self.options['yield_rule']!r}")

    def build_update(self):
        factor = 1.0 if self.options["yield_rule"] == "gic" else _SQRT_2_3
        return make_isotropic_update(_make_principal(factor))

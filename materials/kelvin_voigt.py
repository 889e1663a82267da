"""Kelvin-Voigt viscoelasticity: any registered material plus internal (viscous) damping.

The discovery library's ``internal_damping`` candidate, as a material a run config can name
(``material: kelvin_voigt``, ``material_options: {base: neo_hookean}``), so that a discovered
damping is replayed by ``projo4d run`` / ``projo4d fit``.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np
import warp as wp

from materials import get_material, register_material
from materials.base import Material, MaterialError, MaterialParam

__all__ = ["KelvinVoigt", "DAMPING", "NEGLIGIBLE_DAMPING", "MIN_DAMPING_VOLUME_RATIO"]

#: a damping that stands for none (Pa s): its time scale ``eta / E`` is 1e-10 s or less for E >= 1e4 Pa
NEGLIGIBLE_DAMPING = 1e-6

#: J is floored here in the viscous term (an inverted element would flip its sign).
MIN_DAMPING_VOLUME_RATIO = 1.0e-4

#: optimized in decades like the moduli (scale-free steps); it must be > 0, so "none" is written as
#: :data:`NEGLIGIBLE_DAMPING`
DAMPING = MaterialParam("damping", 1.0, "log10", low=0.0, high=1e6, units="Pa s",
                        description="internal (Kelvin-Voigt) damping viscosity")


@register_material("kelvin_voigt")
class KelvinVoigt(Material):
    """The ``base`` material's Kirchhoff stress plus a viscous one that damps deformation rates.

    ``tau = tau_base + eta J (C + C^T)``, with ``C`` the APIC velocity gradient (1/s), ``J`` the
    volume ratio (``det F``; the tracked ``J`` for fluids) and ``eta`` the ``damping`` parameter
    (Pa s). The viscous stress vanishes under rigid
    motion (``C`` antisymmetric), unlike air drag, so it damps vibrations and rebounds but not
    flight.

    Parameters: the base material's, then ``damping`` (Pa s, optimized as log10 in (0, 1e6],
    default 1: next to moduli of 1e4-1e6 Pa its time scale ``eta / E`` is a
    microsecond or less, i.e. no damping to speak of).

    Options:
        base: registered name of the wrapped material (default ``neo_hookean``), or a material
            instance (then without ``base_options``).
        base_options: options of the wrapped material.
    """

    option_defaults = {"base": "neo_hookean", "base_options": {}}

    def __init__(self, base: str | Material = "neo_hookean", base_options: Optional[Mapping[str, Any]] = None, **unknown: Any):
        if unknown:
            super().__init__(**unknown)  # raises MaterialError naming the unknown options and the known ones
        if isinstance(base, Material):
            if base_options:
                raise MaterialError("kelvin_voigt: base_options can only be given with a base material name")
            self.base: Material = base
            name, opts = base.name, dict(base.options)
        elif isinstance(base, str):
            self.base, name, opts = get_material(base, **dict(base_options or {})), base, dict(base_options or {})
        else:
            raise MaterialError(f"kelvin_voigt: base must be a registered material name, got {type(base).__name__}")
        if isinstance(self.base, KelvinVoigt):
            raise MaterialError("kelvin_voigt: base cannot be kelvin_voigt itself")
        super().__init__(base=name, base_options=opts)
        self.params = tuple(self.base.params) + (DAMPING,)  # instance-level: the base's, then damping
        self.uses_svd = self.base.uses_svd
        self.tracks_volume_only = self.base.tracks_volume_only

    def wave_speed(self, values: Mapping[str, Any], density: float) -> np.ndarray:
        return self.base.wave_speed(values, density)

    def viscous_dt(self, values: Mapping[str, Any], density: float, dx: float) -> np.ndarray:
        """The base's limit and the damping's explicit diffusion limit ``rho dx^2 / (6 eta)`` (the
        stress has the form of :mod:`materials.newtonian`'s viscosity), seconds."""
        eta = np.asarray(values.get("damping", 0.0), np.float64)
        own = np.where(eta > 0, density * dx**2 / (6.0 * np.maximum(eta, 1e-30)), np.inf)
        return np.minimum(self.base.viscous_dt(values, density, dx), own)

    def cache_key(self) -> tuple:
        return ("KelvinVoigt", self.base.cache_key())

    def build_update(self):
        base_update = self.base.warp_update()
        k_eta = len(self.base.params)
        volume_only = bool(self.base.tracks_volume_only)

        @wp.func
        def update(F_tmp: wp.mat33, C: wp.mat33, J: float, dt: float, p: wp.array2d(dtype=float), row: int):
            F_new, J_new, tau = base_update(F_tmp, C, J, dt, p, row)
            det = float(0.0)
            if wp.static(volume_only):
                det = wp.max(J_new, MIN_DAMPING_VOLUME_RATIO)
            else:
                det = wp.max(wp.determinant(F_new), MIN_DAMPING_VOLUME_RATIO)
            return F_new, J_new, tau + (p[row, k_eta] * det) * (C + wp.transpose(C))

        return update

    def __repr__(self) -> str:
        return f"KelvinVoigt(base={self.base!r})"

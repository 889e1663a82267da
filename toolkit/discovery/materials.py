"""A material wrapper that adds internal (Kelvin-Voigt) damping and a density ratio to any material.

Two of the discovery library's candidates change the constitutive update rather than the grid
update, so they cannot be effects (an effect only sees one grid node's velocity, and internal
damping needs the velocity *gradient*):

* **internal damping** (strength ``damping`` = eta, Pa s): a Kelvin-Voigt viscous stress added
  to the material's Kirchhoff stress, ``tau += eta J (C + C^T)``, with ``C`` the APIC velocity
  gradient and ``J = det F``. It damps deformation rates (vibrations after an impact) but not
  rigid motion, unlike air drag.
* **density** (control, ``log_density_ratio`` = s): the body's true density is ``rho e^s``.
  Because the P2G momentum is ``m v`` and the stress term is ``V tau``, a density ratio scales
  the stress's effect on the motion by ``e^-s``; it is applied as ``tau <- e^-s tau``. Under
  gravity-only motion it is confounded with the material's moduli (only E / rho is
  identifiable), which is why the library treats it as a control.

Both parameters are zero for "absent", so ``AugmentedMaterial(base)`` with zero extras moves a
body exactly as ``base`` does.

Example:
    >>> from toolkit.discovery.materials import AugmentedMaterial
    >>> m = AugmentedMaterial("neo_hookean")
    >>> m.param_names
    ['E', 'nu', 'damping', 'log_density_ratio']
"""

from __future__ import annotations

from typing import Any, Optional

import warp as wp

from materials import Material, MaterialParam, get_material

__all__ = ["AugmentedMaterial", "DAMPING", "LOG_DENSITY_RATIO", "EXTRA_PARAMS", "register_for_generation",
           "GENERATION_NAME"]

#: Kelvin-Voigt viscosity of the internal-damping candidate (0 = absent).
DAMPING = MaterialParam("damping", 0.0, "linear", low=0.0, high=1e9, optimize=False, lr=1.0, units="Pa s",
                        description="internal (Kelvin-Voigt) damping viscosity")
#: log of (true density / assumed density) of the density control (0 = absent).
LOG_DENSITY_RATIO = MaterialParam("log_density_ratio", 0.0, "linear", low=-5.0, high=5.0, optimize=False, lr=0.05,
                                  description="ln(true density / assumed density); scales the stress by exp(-s)")
EXTRA_PARAMS = (DAMPING, LOG_DENSITY_RATIO)

#: registry name used by :func:`register_for_generation` (never registered by importing this module).
GENERATION_NAME = "discovery_augmented"


class AugmentedMaterial(Material):
    """``base`` plus Kelvin-Voigt damping and a density ratio (see the module docstring).

    The parameters are the base material's, followed by ``damping`` (Pa s, linear) and
    ``log_density_ratio`` (linear); both default to 0 and are not optimized by default. The
    Warp update calls the base update, then returns
    ``tau = exp(-s) (tau_base + eta J (C + C^T))`` with ``J = det F_new`` (floored at 1e-4; the
    tracked J for fluids).

    Options:
        base: registered name of the wrapped material (or a :class:`~materials.base.Material`).
        base_options: options of the wrapped material when ``base`` is a name.
    """

    option_defaults = {"base": "neo_hookean", "base_options": {}}

    def __init__(self, base: str | Material = "neo_hookean", base_options: Optional[dict[str, Any]] = None):
        if isinstance(base, Material):
            self.base = base
            name = base.registry_name or type(base).__name__
            opts = dict(base.options)
        else:
            self.base = get_material(base, **dict(base_options or {}))
            name, opts = base, dict(base_options or {})
        super().__init__(base=name, base_options=opts)
        # instance-level parameters: the base's, then the extras
        self.params = tuple(self.base.params) + EXTRA_PARAMS
        self.uses_svd = self.base.uses_svd
        self.tracks_volume_only = self.base.tracks_volume_only

    @property
    def n_base(self) -> int:
        """Number of the base material's parameters (the extras follow them)."""
        return len(self.base.params)

    def cache_key(self) -> tuple:
        return ("AugmentedMaterial", self.base.cache_key())

    def build_update(self):
        from materials.kelvin_voigt import KelvinVoigt

        damped = KelvinVoigt(self.base).warp_update()  # base stress + eta J (C + C^T), eta at the same column
        k_s = len(self.base.params) + 1

        @wp.func
        def update(F_tmp: wp.mat33, C: wp.mat33, J: float, dt: float, p: wp.array2d(dtype=float), row: int):
            F_new, J_new, tau = damped(F_tmp, C, J, dt, p, row)
            return F_new, J_new, wp.exp(-p[row, k_s]) * tau

        return update

    def __repr__(self) -> str:
        return f"AugmentedMaterial({self.base!r})"


class _GenerationMaterial(AugmentedMaterial):
    """:class:`AugmentedMaterial` with keyword-only options, constructible by the registry."""

    def __init__(self, base: str = "neo_hookean", base_options: Optional[dict[str, Any]] = None):
        super().__init__(base, base_options)


def register_for_generation() -> str:
    """Register the augmented material as ``"discovery_augmented"`` so that the synthetic
    generator (which looks materials up by name) can simulate hidden internal damping or a
    density error. Idempotent; returns the registered name.

    Importing :mod:`toolkit.discovery` never does this: only the hidden-effect scene generator
    (:mod:`toolkit.discovery.hidden`) calls it, so the material list seen elsewhere is unchanged.
    """
    from materials import MATERIALS

    MATERIALS.register(GENERATION_NAME, overwrite=True)(_GenerationMaterial)
    return GENERATION_NAME

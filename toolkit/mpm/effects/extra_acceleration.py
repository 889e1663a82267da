"""A constant extra acceleration (wind, or an error in the assumed gravity)."""

from __future__ import annotations

import warp as wp

from toolkit.mpm.effects import register_effect
from toolkit.mpm.effects.base import Effect, EffectContext, EffectParam


@register_effect("extra_acceleration")
class ExtraAcceleration(Effect):
    """Adds ``dt a`` to every grid node's velocity.

    Parameters: ``ax``, ``ay``, ``az`` (m/s^2, any sign; all zero = absent).
    """

    params = tuple(
        EffectParam(n, 0.0, low=-100.0, high=100.0, lr=0.05, units="m/s^2", description=f"extra acceleration, {n[1]} component")
        for n in ("ax", "ay", "az")
    )

    def build(self, offset: int, ctx: EffectContext):
        @wp.func
        def apply(v: wp.vec3, x: wp.vec3, dt: float, ep: wp.array(dtype=float)):
            return v + dt * wp.vec3(ep[offset], ep[offset + 1], ep[offset + 2])

        return apply

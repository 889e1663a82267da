"""Linear and quadratic air drag."""

from __future__ import annotations

import warp as wp

from toolkit.mpm.effects import register_effect
from toolkit.mpm.effects.base import Effect, EffectContext, EffectParam


@register_effect("air_drag")
class AirDrag(Effect):
    """Drag deceleration ``a = -(k1 + k2 |v|) v`` on every grid node with mass.

    Integrated semi-implicitly, ``v <- v / (1 + dt (k1 + k2 |v|))``, which is stable for any
    strength and equals explicit Euler to first order in dt.

    Parameters: ``linear`` k1 (1/s) and ``quadratic`` k2 (1/m), per unit mass.
    """

    params = (
        EffectParam("linear", 0.0, low=0.0, high=1e3, lr=0.05, units="1/s", description="linear drag coefficient"),
        EffectParam("quadratic", 0.0, low=0.0, high=1e3, lr=0.05, units="1/m", description="quadratic drag coefficient"),
    )

    def build(self, offset: int, ctx: EffectContext):
        @wp.func
        def apply(v: wp.vec3, x: wp.vec3, dt: float, ep: wp.array(dtype=float)):
            speed = wp.sqrt(wp.dot(v, v) + 1.0e-12)
            return v / (1.0 + dt * (ep[offset] + ep[offset + 1] * speed))

        return apply

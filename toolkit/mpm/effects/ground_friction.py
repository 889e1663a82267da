"""Coulomb friction between the body and the ground plane."""

from __future__ import annotations

import warp as wp

from toolkit.mpm.effects import register_effect
from toolkit.mpm.effects.base import Effect, EffectContext, EffectError, EffectParam


@register_effect("ground_friction")
class GroundFriction(Effect):
    """Coulomb friction at grid nodes in contact with the ground (the layers with y <= ground height).

    For a contact node moving into the ground (normal velocity ``v_n < 0``) the tangential
    velocity ``v_t`` is reduced by ``mu |v_n|``, and stops if it would reverse:
    ``v_t <- max(0, 1 + mu v_n / |v_t|) v_t``. The boundary condition then removes ``v_n``.
    Meaningful with the ``slip`` and ``separate`` boundaries (``sticky`` is infinite friction).

    Parameters: ``mu`` friction coefficient (dimensionless, 0 = frictionless).
    """

    params = (EffectParam("mu", 0.0, low=0.0, high=10.0, lr=0.02, description="Coulomb friction coefficient"),)

    def build(self, offset: int, ctx: EffectContext):
        if ctx.ground_height is None:
            raise EffectError("ground_friction needs a ground plane (SimConfig.ground_height is None)")
        # the simulator's ground layers (robust to float32 node positions), else the plane itself
        ground = float(ctx.ground_top if ctx.ground_top is not None else ctx.ground_height)

        @wp.func
        def apply(v: wp.vec3, x: wp.vec3, dt: float, ep: wp.array(dtype=float)):
            out = v
            if x[1] <= ground and v[1] < 0.0:
                vt = wp.vec3(v[0], 0.0, v[2])
                vt_norm = wp.sqrt(wp.dot(vt, vt) + 1.0e-12)
                scale = wp.max(1.0 + ep[offset] * v[1] / vt_norm, 0.0)
                out = wp.vec3(v[0] * scale, v[1], v[2] * scale)
            return out

        return apply

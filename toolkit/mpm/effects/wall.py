"""An extra collision plane (a wall or an obstacle face)."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from toolkit.mpm.effects import register_effect
from toolkit.mpm.effects.base import Effect, EffectContext, EffectError, EffectParam


@register_effect("wall")
class Wall(Effect):
    """A plane ``n . x = offset`` that the body cannot pass; the solid side is ``n . x < offset``.

    At grid nodes on or behind the plane, the velocity into the wall is removed by the fraction
    ``strength``: ``separate`` mode removes only an approaching normal velocity, ``slip`` any
    normal velocity, ``sticky`` the whole velocity. ``strength = 0`` is no wall, 1 a rigid one.

    Options:
        normal: unit normal (3,) pointing into the free side (normalized here). Default +x.
        mode: ``separate`` (default), ``slip`` or ``sticky``.

    Parameters: ``strength`` in [0, 1]; ``offset`` (metres, not optimized by default: its
    gradient is zero almost everywhere, so a discovery search scans it).
    """

    params = (
        EffectParam("strength", 0.0, low=0.0, high=1.0, lr=0.05, description="fraction of the velocity into the wall removed"),
        EffectParam("offset", 0.0, low=-math.inf, high=math.inf, optimize=False, lr=0.01, units="m", description="plane position along the normal"),
    )
    option_defaults = {"normal": (1.0, 0.0, 0.0), "mode": "separate"}

    def __init__(self, **options):
        super().__init__(**options)
        n = np.asarray(self.options["normal"], dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-8:
            raise EffectError(f"wall normal must be a non-zero 3-vector, got {self.options['normal']!r}")
        self.options["normal"] = tuple(float(c) for c in n / np.linalg.norm(n))
        if self.options["mode"] not in ("separate", "slip", "sticky"):
            raise EffectError(f"wall mode must be 'separate', 'slip' or 'sticky', got {self.options['mode']!r}")

    def build(self, offset: int, ctx: EffectContext):
        nx, ny, nz = self.options["normal"]
        mode = {"separate": 0, "slip": 1, "sticky": 2}[self.options["mode"]]

        @wp.func
        def apply(v: wp.vec3, x: wp.vec3, dt: float, ep: wp.array(dtype=float)):
            n = wp.vec3(nx, ny, nz)
            out = v
            if wp.dot(n, x) <= ep[offset + 1]:
                s = ep[offset]
                vn = wp.dot(v, n)
                if wp.static(mode == 2):
                    out = v * (1.0 - s)
                elif wp.static(mode == 1):
                    out = v - s * vn * n
                else:
                    if vn < 0.0:
                        out = v - s * vn * n
            return out

        return apply

"""The physical-effect hook of the grid update.

An effect is a small class with its parameters and one Warp function that modifies the
velocity of a grid node after gravity and before the ground boundary condition::

    v = apply(v, x_node, dt, effect_params)

``x_node`` is the node's world position (metres), ``v`` its velocity (m/s), ``dt`` the substep
(s), ``effect_params`` the flat array of every active effect's parameters (each effect reads its
own slice, at the offset it is built with). Every effect has a strength parameter for which
zero means absent, so "is this effect there?" is a question about one number, and every
parameter receives a gradient through the simulator (except where the effect's math has none,
e.g. the position of a wall).

A new effect is one file::

    @register_effect("my_effect")
    class MyEffect(Effect):
        params = (EffectParam("k", units="1/s"),)

        def build(self, offset, ctx):
            @wp.func
            def apply(v: wp.vec3, x: wp.vec3, dt: float, ep: wp.array(dtype=float)):
                return v * (1.0 - dt * ep[offset])
            return apply
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping, Optional

__all__ = ["Effect", "EffectParam", "EffectContext", "EffectError"]


class EffectError(ValueError):
    """An invalid effect option or parameter."""


@dataclass(frozen=True)
class EffectParam:
    """One parameter of an effect.

    Attributes:
        name: key (``mu``, ``linear``, ...); reported as ``<effect>.<name>``.
        default: value when not given (0 = absent for the strength parameters).
        low, high: valid range (inclusive).
        optimize: optimized by default when the effect is added to a fit.
        lr: Adam learning rate (linear space).
        units: physical units.
        description: one line for docs and reports.
    """

    name: str
    default: float = 0.0
    low: float = 0.0
    high: float = math.inf
    optimize: bool = True
    lr: float = 0.01
    units: str = ""
    description: str = ""

    def check(self, value: float, effect: str) -> None:
        v = float(value)
        if not math.isfinite(v) or not (self.low <= v <= self.high):
            raise EffectError(
                f"{effect}.{self.name} = {v:g} is out of range: expected {self.low:g} <= {self.name} <= {self.high:g}"
                + (f" {self.units}" if self.units else "")
            )


@dataclass(frozen=True)
class EffectContext:
    """Scene constants an effect may need when it is built (compile-time constants)."""

    ground_height: Optional[float]
    boundary: str
    dx: float
    #: y threshold of the ground nodes: half a cell above the highest ground layer of the dx lattice,
    #: so ``x_node[1] <= ground_top`` picks exactly the simulator's ground layers whatever the float32
    #: rounding of the node position (``None`` without a ground)
    ground_top: Optional[float] = None


class Effect:
    """Base class of the physical effects (see the module docstring)."""

    registry_name: ClassVar[str] = ""
    params: ClassVar[tuple[EffectParam, ...]] = ()
    option_defaults: ClassVar[Mapping[str, Any]] = {}

    def __init__(self, **options: Any):
        unknown = set(options) - set(self.option_defaults)
        if unknown:
            raise EffectError(
                f"{type(self).__name__} has no option(s) {sorted(unknown)}; known options: {sorted(self.option_defaults) or 'none'}"
            )
        self.options: dict[str, Any] = {**self.option_defaults, **options}

    @property
    def name(self) -> str:
        return self.registry_name or type(self).__name__

    @property
    def param_names(self) -> list[str]:
        return [p.name for p in self.params]

    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self.params}

    def validate(self, values: Mapping[str, float]) -> None:
        unknown = set(values) - set(self.param_names)
        if unknown:
            raise EffectError(f"effect {self.name!r} has no parameter(s) {sorted(unknown)}; its parameters are {self.param_names}")
        for p in self.params:
            if p.name in values:
                p.check(values[p.name], self.name)

    def build(self, offset: int, ctx: EffectContext):  # pragma: no cover - abstract
        """Return the ``@wp.func`` ``apply(v, x, dt, ep) -> v`` reading ``ep[offset:offset+len(params)]``."""
        raise NotImplementedError

    def cache_key(self) -> tuple:
        return (type(self).__qualname__, tuple(sorted((k, repr(v)) for k, v in self.options.items())))

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items())
        return f"{type(self).__name__}({opts})"

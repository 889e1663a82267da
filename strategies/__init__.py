"""Strategy registry: curricula over the parameter groups X, A, S, M.

>>> from strategies import get_strategy
>>> get_strategy("progressive").schedule_string("neo_hookean")
'XAS:100@3/3x3,XA[S]M:150/3x20'
>>> get_strategy("XAS:100@3,XASM:150").total_iterations()
250

``get_strategy`` accepts a registered name, a schedule string, a :class:`Strategy` instance or a
class. Third-party strategies register through the ``projo4d.strategies`` entry-point group and are
usable from YAML by name or ``class_path``.
"""

from __future__ import annotations

from typing import Any

from strategies.base import GROUPS, LOSSES, Stage, Strategy, StrategyError, expand_groups
from toolkit.registry import Registry, UnknownNameError

STRATEGIES: Registry[type[Strategy]] = Registry(
    "strategy",
    entry_point_group="projo4d.strategies",
    builtin_modules=("strategies.sequential", "strategies.joint", "strategies.progressive", "strategies.cyclic",
                     "strategies.scheduled"),
)
register_strategy = STRATEGIES.register

__all__ = [
    "STRATEGIES",
    "register_strategy",
    "get_strategy",
    "Strategy",
    "Stage",
    "StrategyError",
    "GROUPS",
    "LOSSES",
    "expand_groups",
]


def get_strategy(spec: "str | Strategy | type[Strategy]", **options: Any) -> Strategy:
    """A strategy from a registered name, a schedule string, an instance or a class."""
    if isinstance(spec, Strategy):
        if options:
            raise StrategyError("options can only be given with a strategy name or class, not with an instance")
        return spec
    if isinstance(spec, type) and issubclass(spec, Strategy):
        return spec(**options)
    if not isinstance(spec, str):
        raise StrategyError(f"a strategy is a name, a schedule string, a Strategy or a Strategy class; got {spec!r}")
    if ":" in spec:
        from strategies.scheduled import Scheduled

        if options:
            raise StrategyError("a schedule string takes no options")
        return Scheduled(schedule=spec)
    try:
        cls = STRATEGIES.get(spec)
    except UnknownNameError as err:
        raise UnknownNameError(f"{err} (or write a schedule string such as 'XAS:100@3,XASM:150')") from None
    return cls(**options)

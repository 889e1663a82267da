"""Physical effects of the grid update: ground friction, air drag, extra acceleration, walls.

>>> from toolkit.mpm.effects import get_effect
>>> drag = get_effect("air_drag")
"""

from __future__ import annotations

from typing import Any

from toolkit.mpm.effects.base import Effect, EffectContext, EffectError, EffectParam
from toolkit.registry import Registry

EFFECTS: Registry[type[Effect]] = Registry(
    "effect",
    entry_point_group="projo4d.effects",
    builtin_modules=(
        "toolkit.mpm.effects.ground_friction",
        "toolkit.mpm.effects.air_drag",
        "toolkit.mpm.effects.extra_acceleration",
        "toolkit.mpm.effects.wall",
    ),
)
register_effect = EFFECTS.register

__all__ = ["EFFECTS", "register_effect", "get_effect", "Effect", "EffectParam", "EffectContext", "EffectError"]


def get_effect(name: str | Effect, **options: Any) -> Effect:
    """An effect instance from its registered name (or the instance itself)."""
    if isinstance(name, Effect):
        return name
    return EFFECTS.get(name)(**options)

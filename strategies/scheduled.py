"""A strategy given by a schedule string (see :mod:`strategies.schedule`)."""

from __future__ import annotations

from strategies import register_strategy
from strategies.base import Stage, Strategy, StrategyError
from strategies.schedule import parse_schedule


@register_strategy("schedule")
class Scheduled(Strategy):
    """Any curriculum written as a schedule string, e.g. ``SG:100@4,SMG:150``.

    Options:
        schedule: the schedule string (required).
    """

    option_defaults = {"schedule": ""}

    def __init__(self, schedule: str = ""):
        super().__init__(schedule=schedule)
        if not self.options["schedule"]:
            raise StrategyError("the 'schedule' strategy needs schedule='...', e.g. 'XAS:100@3,XASM:150'")
        self._stages = parse_schedule(self.options["schedule"])

    def build_stages(self, material: str | None = None) -> list[Stage]:
        return list(self._stages)

"""A user-defined strategy living in its own module (used by tests through ``class_path``)."""

from __future__ import annotations

from strategies import Stage, Strategy


class VelocityThenAll(Strategy):
    """S alone on the first two frames, then everything."""

    def __init__(self, warmup: int = 5, rest: int = 7):
        super().__init__()
        self.warmup = warmup
        self.rest = rest

    def build_stages(self, material=None):
        return [Stage(frozenset("S"), self.warmup, frames=2, name="warmup:S"), Stage(frozenset("XASM"), self.rest, name="all")]

"""Cyclic optimization: parameter groups one at a time, repeated (paper Table 7)."""

from __future__ import annotations

from typing import Optional

from strategies import register_strategy
from strategies.base import Stage, Strategy, StrategyError
from strategies.defaults import EARLY_FRAMES, STAGE1_ITERATIONS, STAGE2_BATCH, stage2_iterations

PATTERNS = ("(XA-S-M)xN-A", "XA-(S-M-A)xN")


@register_strategy("cyclic")
class Cyclic(Strategy):
    """Optimize one group at a time over several cycles, at a constant total budget.

    Options:
        pattern: ``"(XA-S-M)xN-A"`` (default) or ``"XA-(S-M-A)xN"``.
        cycles: N, default 4.
        iterations: total budget (default ProJo4D's: 100 + the material's Stage-2 count),
            split evenly over the stages.
        early_frames: frame window of the S stages (default 3; "free_flight": the frames before ground contact).
        batch: (cameras, frames) per iteration, default (3, 20).
    """

    option_defaults = {"pattern": PATTERNS[0], "cycles": 4, "iterations": None, "early_frames": EARLY_FRAMES,
                       "batch": STAGE2_BATCH}

    def __init__(self, pattern: str = PATTERNS[0], cycles: int = 4, iterations: Optional[int] = None,
                 early_frames: int | str = EARLY_FRAMES, batch: tuple[int, int] = STAGE2_BATCH):
        super().__init__(pattern=pattern, cycles=cycles, iterations=iterations, early_frames=early_frames, batch=tuple(batch))
        if self.options["pattern"] not in PATTERNS:
            raise StrategyError(f"cyclic pattern must be one of {PATTERNS}, got {self.options['pattern']!r}")
        if not isinstance(self.options["cycles"], int) or self.options["cycles"] < 1:
            raise StrategyError(f"cyclic cycles must be an integer >= 1, got {self.options['cycles']!r}")

    def build_stages(self, material: str | None = None) -> list[Stage]:
        o = self.options
        n = o["cycles"]
        if o["pattern"] == PATTERNS[0]:
            groups = ["XA", "S", "M"] * n + ["A"]
        else:
            groups = ["XA"] + ["S", "M", "A"] * n
        total = o["iterations"] or STAGE1_ITERATIONS + stage2_iterations(material)
        each = max(1, total // len(groups))
        b = o["batch"]
        return [
            Stage(frozenset(g), each, frames=o["early_frames"] if g == "S" else None, cameras_per_step=b[0],
                  frames_per_step=b[1], name=f"cycle:{g}")
            for g in groups
        ]

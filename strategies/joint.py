"""Full joint optimization (Vid2Sim-style): every group from the start."""

from __future__ import annotations

from typing import Optional

from strategies import register_strategy
from strategies.base import Stage, Strategy
from strategies.defaults import STAGE1_ITERATIONS, STAGE2_BATCH, stage2_iterations


@register_strategy("joint")
class Joint(Strategy):
    """XASM on all training frames for the same total budget as ProJo4D (Stage 1 + Stage 2).

    Options:
        iterations: total iterations (default 100 + the material's Stage-2 count).
        batch: (cameras, frames) per iteration, default (3, 20).
    """

    option_defaults = {"iterations": None, "batch": STAGE2_BATCH}

    def __init__(self, iterations: Optional[int] = None, batch: tuple[int, int] = STAGE2_BATCH):
        super().__init__(iterations=iterations, batch=tuple(batch))

    def build_stages(self, material: str | None = None) -> list[Stage]:
        n = self.options["iterations"] or STAGE1_ITERATIONS + stage2_iterations(material)
        b = self.options["batch"]
        return [Stage(frozenset("XASM"), n, cameras_per_step=b[0], frames_per_step=b[1], name="joint:XASM")]

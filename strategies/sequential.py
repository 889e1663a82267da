"""Sequential optimization (PAC-NeRF / GIC): one parameter group after another."""

from __future__ import annotations

from typing import Optional

from strategies import register_strategy
from strategies.base import Stage, Strategy
from strategies.defaults import (
    APPEARANCE_ITERATIONS,
    EARLY_FRAMES,
    STAGE1_BATCH,
    STAGE1_ITERATIONS,
    STAGE2_BATCH,
    stage2_iterations,
)


@register_strategy("sequential")
class Sequential(Strategy):
    """GIC's schedule: S with the geometric loss on the first frames, then M with the Gaussians
    frozen on all frames, then appearance refinement (A) on the simulated trajectory.

    Options:
        stage1_iterations (100), stage2_iterations (per material), appearance_iterations
        (40000, GIC's "Stage 3"; 0 skips it), early_frames (3, or "free_flight": the frames before
        ground contact), stage1_batch (3, 3), stage2_batch (3, 20), appearance_batch (1, 1).
    """

    option_defaults = {
        "stage1_iterations": STAGE1_ITERATIONS,
        "stage2_iterations": None,
        "appearance_iterations": APPEARANCE_ITERATIONS,
        "early_frames": EARLY_FRAMES,
        "stage1_batch": STAGE1_BATCH,
        "stage2_batch": STAGE2_BATCH,
        "appearance_batch": (1, 1),
    }

    def __init__(
        self,
        stage1_iterations: int = STAGE1_ITERATIONS,
        stage2_iterations: Optional[int] = None,
        appearance_iterations: int = APPEARANCE_ITERATIONS,
        early_frames: int | str = EARLY_FRAMES,
        stage1_batch: tuple[int, int] = STAGE1_BATCH,
        stage2_batch: tuple[int, int] = STAGE2_BATCH,
        appearance_batch: tuple[int, int] = (1, 1),
    ):
        super().__init__(stage1_iterations=stage1_iterations, stage2_iterations=stage2_iterations,
                         appearance_iterations=appearance_iterations, early_frames=early_frames,
                         stage1_batch=tuple(stage1_batch), stage2_batch=tuple(stage2_batch),
                         appearance_batch=tuple(appearance_batch))

    def build_stages(self, material: str | None = None) -> list[Stage]:
        o = self.options
        stages = [
            Stage(frozenset("S"), o["stage1_iterations"], frames=o["early_frames"], cameras_per_step=o["stage1_batch"][0],
                  frames_per_step=o["stage1_batch"][1], losses=("geometry",), name="stage1:S"),
            Stage(frozenset("M"), o["stage2_iterations"] or stage2_iterations(material), cameras_per_step=o["stage2_batch"][0],
                  frames_per_step=o["stage2_batch"][1], name="stage2:M"),
        ]
        if o["appearance_iterations"]:
            stages.append(Stage(frozenset("A"), o["appearance_iterations"], cameras_per_step=o["appearance_batch"][0],
                                frames_per_step=o["appearance_batch"][1], losses=("image",), name="stage3:A"))
        return stages

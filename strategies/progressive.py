"""ProJo4D: progressive joint optimization."""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

from strategies import register_strategy
from strategies.base import Stage, Strategy
from strategies.defaults import EARLY_FRAMES, STAGE1_BATCH, STAGE1_ITERATIONS, STAGE2_BATCH, stage2_iterations


@register_strategy("progressive")
class Progressive(Strategy):
    """ProJo4D (Rho et al., TMLR 2026): grow the jointly optimized set of parameter groups.

    Stage 1 optimizes positions, appearance and the initial state (XAS) on the first frames, where
    the motion is set by v0 alone; Stage 2 adds the material on all training frames (XASM in the
    paper; here v0 stays at Stage 1's value when stage 0 measured it, see ``hold_velocity``).

    Options:
        stage1_iterations: default 100.
        stage2_iterations: default per material (elastic/sand 150, Newtonian 250,
            non-Newtonian 350, plasticine 300; paper appendix); an int overrides it.
        early_frames: Stage-1 frame window, default 3; ``"free_flight"``: the clip's frames before
            ground contact, found by the stage-0 ballistic estimate when the fit starts (at least 3;
            schedule string ``@ff``). With ``hold_velocity`` it makes stage 1 fit v0 on every frame
            that determines it without the material, and stage 2 keep it.
        stage1_batch, stage2_batch: (cameras, frames) per iteration, default (3, 3) and (3, 20).
        hold_velocity: whether Stage 2 keeps v0 (and a learnt gravity) at Stage 1's value
            (``XAM`` instead of the paper's ``XASM``). Default ``"auto"`` (``XA[S]M``, set when the
            fit starts): hold v0 when it starts from a measurement (the stage-0 ballistic estimate,
            or a given ``v0_init``), fit it in Stage 2 when it starts at zero (stage 0 lost the
            body, or ``"zero"`` was asked for). ``True`` always holds, ``False`` is the paper's
            curriculum. Measured (``docs/results/paper_size.md``): on 400 px clips holding v0 made
            it closer on 19 of 22 scene fits (rounds 19, 21-23; mean error 0.016 -> 0.002 m/s on
            the fluids), left the material errors where they were, lowered the future CD where a
            free v0 ran away (newtonian/003: 50.3 -> 3.0); with it in place of the free fits the
            paper-table count went 7 -> 12 of 27. On 64 px CPU clips it is about even: it lowered
            the mean future CD of four elastic and plasticine scenes by 6 % and raised that of six
            fluid scenes by 7 %, where a free v0 absorbs some of the coarse grid's model error.
    """

    option_defaults = {
        "stage1_iterations": STAGE1_ITERATIONS,
        "stage2_iterations": None,
        "early_frames": EARLY_FRAMES,
        "stage1_batch": STAGE1_BATCH,
        "stage2_batch": STAGE2_BATCH,
        "hold_velocity": "auto",
    }

    def __init__(
        self,
        stage1_iterations: int = STAGE1_ITERATIONS,
        stage2_iterations: Optional[int] = None,
        early_frames: int | str = EARLY_FRAMES,
        stage1_batch: tuple[int, int] = STAGE1_BATCH,
        stage2_batch: tuple[int, int] = STAGE2_BATCH,
        hold_velocity: bool | str = "auto",
    ):
        if not isinstance(hold_velocity, bool) and hold_velocity != "auto":
            raise ValueError(f"progressive: hold_velocity must be true, false or 'auto' (hold v0 when it starts from a "
                             f"measurement), got {hold_velocity!r}")
        super().__init__(stage1_iterations=stage1_iterations, stage2_iterations=stage2_iterations, early_frames=early_frames,
                         stage1_batch=tuple(stage1_batch), stage2_batch=tuple(stage2_batch), hold_velocity=hold_velocity)

    def build_stages(self, material: str | None = None) -> list[Stage]:
        o = self.options
        n2 = o["stage2_iterations"] or stage2_iterations(material)
        hold = o["hold_velocity"]
        second = Stage(frozenset("XAM" if hold else "XASM"), n2, cameras_per_step=o["stage2_batch"][0],
                       frames_per_step=o["stage2_batch"][1], velocity_if_unmeasured=hold == "auto")
        return [
            Stage(frozenset("XAS"), o["stage1_iterations"], frames=o["early_frames"], cameras_per_step=o["stage1_batch"][0],
                  frames_per_step=o["stage1_batch"][1], name="stage1:XAS"),
            replace(second, name=f"stage2:{second.groups_label()}"),
        ]

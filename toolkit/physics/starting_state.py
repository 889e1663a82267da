"""Where the physics fit starts: the initial velocity, the surface particles the geometric loss
reads, the learning-rate schedule and the step stream Lightning iterates over.

Pieces of :class:`~toolkit.physics.InversePhysicsModule`'s set-up that need nothing of the module
itself.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np
import torch

from strategies import Stage, Strategy
from strategies.base import FREE_FLIGHT_MIN_FRAMES, free_flight_window
from toolkit.mpm import SimConfig
from toolkit.physics.inputs import PhysicsInput

__all__ = ["StartingVelocity", "describe_start", "free_flight_curriculum", "initial_v0", "velocity_start_curriculum", "velocity_held_after",
           "warn_if_zero_start_is_held", "surface_particles", "cosine_with_warmup", "StepStream"]

log = logging.getLogger(__name__)


@dataclass
class StartingVelocity:
    """v0 to start from.

    Attributes:
        v0: 3 components, m/s, canonical frame.
        hparam: ``(value,)`` to store as the module's ``v0_init`` hyperparameter (``None`` for
            "estimate again on resume", or 3 numbers), or ``None`` to keep what was given.
        estimate: the stage-0 ballistic estimate's record when v0 starts there, else ``None``.
    """

    v0: list[float]
    hparam: Optional[tuple] = None
    estimate: Optional[dict] = None

    @property
    def measured(self) -> bool:
        """Whether v0 starts from a measurement: the stage-0 ballistic estimate or a given v0 (not
        zero for lack of an estimate, nor ``"zero"``)."""
        return self.estimate is not None or self.hparam is None

    @property
    def source(self) -> str:
        """Where v0 starts: ``"estimate"`` (stage-0 ballistic fit), ``"given"`` (``v0_init``),
        ``"zero"`` (asked for) or ``"no estimate"`` (zero, stage 0 gave too few free-flight frames)."""
        if self.estimate is not None:
            return "estimate"
        if self.hparam is None:
            return "given"
        return "no estimate" if self.hparam == (None,) else "zero"


def initial_v0(v0_init: Union[None, str, list[float]], inp: PhysicsInput, cfg: SimConfig) -> StartingVelocity:
    """v0 to start from: explicit (3 numbers, m/s), ``"zero"``, or ``None``/``"auto"``: the stage-0
    ballistic estimate (:mod:`toolkit.physics.initial_velocity`), zero when it has too few frames.

    Raises:
        ValueError: ``v0_init`` is none of those.
    """
    if v0_init is None or (isinstance(v0_init, str) and v0_init == "auto"):
        from toolkit.physics.initial_velocity import initial_velocity_from_input

        est = initial_velocity_from_input(inp, cfg)
        if est is None:
            log.info("v0 starts at zero: fewer than 3 stage-0 frames before ground contact to estimate it from")
            return StartingVelocity([0.0, 0.0, 0.0], hparam=(None,))
        from toolkit.physics.initial_velocity import describe_estimate

        record = est.to_dict()
        log.info("v0 starts at the %s, rms %.2g m", describe_estimate(record), est.rms_residual)
        return StartingVelocity(list(est.v0), hparam=(None,), estimate=record)
    if isinstance(v0_init, str):
        if v0_init == "zero":
            return StartingVelocity([0.0, 0.0, 0.0], hparam=([0.0, 0.0, 0.0],))
        raise ValueError(f"v0_init must be 3 numbers (m/s), 'auto' or 'zero', got {v0_init!r}")
    v = [float(c) for c in v0_init]
    if len(v) != 3:
        raise ValueError(f"v0_init must have 3 components (m/s), got {v0_init!r}")
    return StartingVelocity(v)


def free_flight_curriculum(curriculum: Strategy, material: Optional[str], estimate: Optional[dict], inp: PhysicsInput,
                           cfg: SimConfig) -> Strategy:
    """``curriculum`` with its ``free_flight`` windows (``@ff``) set to this clip's training frames
    before ground contact: those of the stage-0 ballistic estimate ``estimate`` (a
    ``V0Estimate.to_dict()`` record; made here from ``inp`` when ``None``, e.g. v0 was given), and
    at least :data:`~strategies.base.FREE_FLIGHT_MIN_FRAMES`. Without such windows it is returned
    as it is. The estimate is deterministic, so a resume sets the same window."""
    if not curriculum.has_free_flight_window(material):
        return curriculum
    from toolkit.physics.initial_velocity import free_flight_frames, initial_velocity_from_input

    if estimate is None:
        found = initial_velocity_from_input(inp, cfg)
        estimate = found.to_dict() if found is not None else None
    n = free_flight_frames(estimate)
    log.info("free-flight window (@ff): the first %d training frames (%s)", free_flight_window(n),
             f"the stage-0 estimate found frames 0-{n - 1} before ground contact" if n else
             f"no free-flight frames found, so the first {FREE_FLIGHT_MIN_FRAMES}")
    return curriculum.with_free_flight(n)


def velocity_start_curriculum(curriculum: Strategy, material: Optional[str],
                              start: StartingVelocity) -> tuple[Strategy, dict]:
    """``curriculum`` with its ``[S]`` stages (fit v0 only when it was not measured, e.g.
    progressive's ``hold_velocity="auto"``) resolved for this start: held when v0 starts from the
    stage-0 estimate or a given value, fitted when it starts at zero. Without such stages it is
    returned as it is. The estimate is deterministic, so a resume resolves them the same way.

    Returns:
        The resolved curriculum, and where v0 started with how the ``[S]`` stages went
        (``{"source": start.source, "rule": "held" | "fitted" | None}``; None without such stages),
        the module's ``v0_origin``."""
    if not curriculum.has_velocity_rule(material):
        return curriculum, {"source": start.source, "rule": None}
    log.info("v0 %s", "starts from a measurement, so the [S] stages hold it" if start.measured else
             "starts at zero (no stage-0 estimate), so the [S] stages fit it")
    origin = {"source": start.source, "rule": "held" if start.measured else "fitted"}
    return curriculum.with_velocity_start(start.measured), origin


def velocity_held_after(stages: list[Stage]) -> Optional[int]:
    """Index of the last stage that fits v0 (``S``) when a later stage fits the material (``M``)
    without it: v0 is held from then on (progressive with ``hold_velocity``, GIC's sequential).
    ``None`` when every material stage also fits v0, or no stage fits it."""
    fits_v0 = [i for i, st in enumerate(stages) if "S" in st.groups]
    if not fits_v0:
        return None
    last = fits_v0[-1]
    return last if any("M" in st.groups for st in stages[last + 1:]) else None


def warn_if_zero_start_is_held(start: StartingVelocity, stages: list[Stage]) -> Optional[str]:
    """Warn (and return the message) when v0 was to start at the stage-0 estimate, there was none,
    so it starts at zero, and the curriculum holds v0 after its first stages. Then those stages
    alone must bring v0 from zero, and a fit of 64 px scenes imaged differently ended 0.12 m/s off
    that way (``docs/results/paper_size.md``). ``None`` (no warning) otherwise."""
    if start.estimate is not None or start.hparam != (None,):
        return None
    k = velocity_held_after(stages)
    if k is None:
        return None
    st = stages[k]
    msg = (f"v0 starts at zero (stage 0 gave fewer than 3 frames before contact to estimate it from) and is fitted "
           f"only up to stage {k + 1} ({st.name}, {st.iterations} iterations); the later stages keep it where that "
           "stage leaves it. Give v0 (v0_init), or fit it in the later stages too (progressive's default hold_velocity='auto' "
           "does when v0 starts at zero)")
    log.warning(msg)
    return msg


def surface_particles(inp: PhysicsInput) -> torch.Tensor:
    """Indices (int64, sorted) of the particles within 1.5 particle spacings of the first frame's
    stage-0 surface (at least 8, or the nearest quarter); every particle when there is no surface."""
    from scipy.spatial import cKDTree

    parts = inp.particles.detach().cpu().numpy()
    surf = inp.surfaces[0].detach().cpu().numpy()
    if len(surf) == 0:
        return torch.arange(len(parts))
    spacing = float(inp.particle_volume) ** (1 / 3)
    d, _ = cKDTree(surf).query(parts, k=1)
    idx = np.nonzero(d <= 1.5 * spacing)[0]
    if len(idx) < 8:
        idx = np.argsort(d)[: max(8, len(parts) // 4)]
    return torch.as_tensor(np.sort(idx), dtype=torch.int64)


def cosine_with_warmup(k: int, total: int, warmup_fraction: float = 0.1, floor: float = 0.01) -> float:
    """LR multiplier at the k-th active iteration of ``total``: linear warm-up, cosine decay to ``floor``."""
    if total <= 1:
        return 1.0
    warm = max(1, int(round(warmup_fraction * total)))
    if k < warm:
        return (k + 1) / warm
    t = (k - warm) / max(1, total - warm)
    return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(t, 1.0)))


class StepStream(torch.utils.data.IterableDataset):
    """An endless stream of placeholders: the module samples its own batches from the strategy."""

    def __iter__(self):
        while True:
            yield 0


def describe_start(origin: Optional[dict], estimate: Optional[dict] = None) -> Optional[str]:
    """One line on where v0 started and how a ``[S]`` stage resolved, for the closing table.

    Args:
        origin: a module's ``v0_origin`` (``{"source": ..., "rule": ...}``; ``None`` in a summary
            written before it existed).
        estimate: the stage-0 ballistic estimate's record (``V0Estimate.to_dict()``) v0 started
            from, if any; its line is :func:`toolkit.physics.initial_velocity.describe_estimate`'s.

    Returns:
        The line, or ``None`` when there is nothing to say (v0 given, or no record, and no rule).
    """
    source, rule = (origin or {}).get("source"), (origin or {}).get("rule")
    if estimate and estimate.get("frames"):
        from toolkit.physics.initial_velocity import describe_estimate

        said = "v0 started at the " + describe_estimate(estimate)
    else:
        said = {"no estimate": "v0 started at zero: stage 0 gave fewer than 3 usable frames before contact for a "
                               "ballistic estimate",
                "zero": "v0 started at zero, as asked (v0_init 'zero')",
                "given": "v0 started at the given v0_init"}.get(source)
    if rule == "fitted":
        said = (said or "v0 started unmeasured") + "; the [S] stages fitted it"
    elif rule == "held" and said:
        said += "; the [S] stages held it at stage 1's value"
    return said


def rigid_shift(value) -> torch.Tensor:
    """The module's ``body_shift`` (``None`` or 3 finite numbers, metres) as a (3,) float32
    tensor, zeros for ``None``; anything else is a ValueError naming the value."""
    if value is None:
        return torch.zeros(3)
    try:
        t = torch.as_tensor([float(v) for v in value], dtype=torch.float32)
    except (TypeError, ValueError):
        t = None
    if t is None or t.shape != (3,) or not bool(torch.isfinite(t).all()):
        raise ValueError(f"body_shift must be 3 finite numbers [dx, dy, dz] in metres (a rigid translation of the "
                         f"starting body), got {value!r}")
    return t

"""Optimization curricula over parameter groups: :class:`Stage` and :class:`Strategy`.

Parameter groups (DESIGN section 6): ``X`` particle/Gaussian positions, ``A`` appearance (colour,
opacity, scale, rotation), ``S`` initial state (v0; gravity when enabled), ``M`` material and
effect parameters. ``G`` is shorthand for ``X`` + ``A``.

A strategy is a sequence of stages. Each stage names the groups that are optimized, how many
iterations it runs, which training frames it sees (a window of the first frames or all of
them), how many cameras and frames each iteration samples, which loss terms are on, and
optional learning-rate multipliers. The trainer asks the strategy which stage an iteration
belongs to; the strategy itself holds no mutable state, so resuming a run only needs the
iteration counter (kept by the trainer, saved in checkpoints).

Note: Lightning's ``Trainer(strategy=...)`` is about distributed training (DDP etc.); projo4d's
strategies are curricula, configured under the model's ``curriculum`` argument.
"""

from __future__ import annotations

import bisect
import copy
from dataclasses import asdict, dataclass, field, replace
from typing import Any, ClassVar, Mapping, Optional, Sequence

__all__ = ["FREE_FLIGHT", "FREE_FLIGHT_MIN_FRAMES", "GROUPS", "LOSSES", "Stage", "Strategy", "StrategyError", "expand_groups",
           "free_flight_window"]

GROUPS = ("X", "A", "S", "M")
LOSSES = ("image", "geometry")
#: a stage's frame window that the fit sets per clip: the training frames before ground contact
#: (the stage-0 ballistic estimate's free-flight frames, :mod:`toolkit.physics.initial_velocity`)
FREE_FLIGHT = "free_flight"
#: the fewest frames a ``free_flight`` window holds (the paper's first-frames window, 3)
FREE_FLIGHT_MIN_FRAMES = 3


def free_flight_window(free_flight_frames: Optional[int]) -> int:
    """The frames a ``free_flight`` window holds for a clip with ``free_flight_frames`` frames before
    contact: that many, at least :data:`FREE_FLIGHT_MIN_FRAMES` (that many when ``None``)."""
    return max(int(free_flight_frames or 0), FREE_FLIGHT_MIN_FRAMES)


class StrategyError(ValueError):
    """A malformed stage, schedule string or strategy option."""


def expand_groups(groups: str | Sequence[str]) -> frozenset[str]:
    """``"SG"`` -> ``{"S", "X", "A"}``; letters from X, A, S, M and G (= X + A)."""
    letters = list(groups) if not isinstance(groups, str) else list(groups.replace(" ", ""))
    out: set[str] = set()
    for g in letters:
        if g == "G":
            out |= {"X", "A"}
        elif g in GROUPS:
            out.add(g)
        else:
            raise StrategyError(f"unknown parameter group {g!r} in {groups!r}: use X, A, S, M or G (= X + A)")
    if not out:
        raise StrategyError("a stage needs at least one parameter group (X, A, S, M or G)")
    return frozenset(out)


@dataclass(frozen=True)
class Stage:
    """One stage of a curriculum.

    Attributes:
        groups: active parameter groups, a subset of ``{"X", "A", "S", "M"}``.
        iterations: optimizer iterations of this stage (>= 1).
        frames: frame window: the first ``frames`` training frames, ``None`` for all of them, or
            ``"free_flight"`` (:data:`FREE_FLIGHT`): the frames before ground contact, set per clip
            when the fit starts (:meth:`Strategy.with_free_flight`; at least
            :data:`FREE_FLIGHT_MIN_FRAMES`).
        cameras_per_step: training cameras sampled per iteration (``None``: all).
        frames_per_step: frames sampled per iteration from the window (``None``: all of it).
        losses: loss terms that are on: ``"image"`` and/or ``"geometry"``.
        lr_scale: learning-rate multiplier per group (e.g. ``{"S": 0.5}``).
        name: a label for logs and plots (default: derived from the groups).
        velocity_if_unmeasured: the stage also fits v0 (``S``) when v0 did not start from a
            measurement (the stage-0 ballistic estimate or a given v0), and holds it when it did;
            set per clip when the fit starts (:meth:`Strategy.with_velocity_start`). Schedule
            string ``XA[S]M``. Needs ``S`` not in ``groups``.
    """

    groups: frozenset[str]
    iterations: int
    frames: Optional[int | str] = None
    cameras_per_step: Optional[int] = None
    frames_per_step: Optional[int] = None
    losses: tuple[str, ...] = LOSSES
    lr_scale: Mapping[str, float] = field(default_factory=dict)
    name: str = ""
    velocity_if_unmeasured: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "groups", expand_groups(self.groups) if not isinstance(self.groups, frozenset) else self.groups)
        bad = set(self.groups) - set(GROUPS)
        if bad:
            raise StrategyError(f"unknown parameter group(s) {sorted(bad)}; groups are X, A, S, M")
        if not isinstance(self.iterations, int) or self.iterations < 1:
            raise StrategyError(f"a stage needs iterations >= 1, got {self.iterations!r}")
        if self.frames != FREE_FLIGHT and self.frames is not None and (not isinstance(self.frames, int) or self.frames < 1):
            raise StrategyError(f"stage frames must be a positive integer, None (all) or {FREE_FLIGHT!r}, got {self.frames!r}")
        for label, v in (("cameras_per_step", self.cameras_per_step), ("frames_per_step", self.frames_per_step)):
            if v is not None and (not isinstance(v, int) or v < 1):
                raise StrategyError(f"stage {label} must be a positive integer or None, got {v!r}")
        losses = tuple(self.losses)
        if not losses or set(losses) - set(LOSSES):
            raise StrategyError(f"stage losses must be a non-empty subset of {LOSSES}, got {losses!r}")
        object.__setattr__(self, "losses", losses)
        bad_lr = set(self.lr_scale) - set(GROUPS)
        if bad_lr:
            raise StrategyError(f"lr_scale has unknown group(s) {sorted(bad_lr)}")
        object.__setattr__(self, "lr_scale", dict(self.lr_scale))
        if not isinstance(self.velocity_if_unmeasured, bool):
            raise StrategyError(f"stage velocity_if_unmeasured must be true or false, got {self.velocity_if_unmeasured!r}")
        if self.velocity_if_unmeasured and "S" in self.groups:
            raise StrategyError("a stage that fits v0 only when it was not measured ([S]) must not also fit it always (S)")
        if not self.name:
            object.__setattr__(self, "name", self.label())

    def label(self) -> str:
        """Compact label, e.g. ``XAS@3``, ``XAS@ff`` or ``XA[S]M`` (the schedule-string form without
        iterations)."""
        return self.groups_label() + (f"@{self.window_label()}" if self.frames else "")

    def groups_label(self) -> str:
        """The groups as the schedule string writes them: ``XASM``, or ``XA[S]M`` with
        :attr:`velocity_if_unmeasured`."""
        return "".join(x if x in self.groups else "[S]" if x == "S" and self.velocity_if_unmeasured else ""
                       for x in GROUPS)

    def window_label(self) -> str:
        """The window as the schedule string writes it: ``"3"``, ``"ff"`` (free flight) or ``""`` (all)."""
        return "ff" if self.frames == FREE_FLIGHT else str(self.frames or "")

    def window(self, n_train: int) -> int:
        """How many of ``n_train`` training frames the stage sees: its window, capped at ``n_train``;
        all of them for ``None`` and for a ``free_flight`` window not yet set (its upper bound)."""
        return min(self.frames if isinstance(self.frames, int) else n_train, n_train)

    def with_free_flight(self, free_flight_frames: Optional[int]) -> "Stage":
        """This stage with a ``free_flight`` window set to ``max(free_flight_frames,
        FREE_FLIGHT_MIN_FRAMES)`` frames (``FREE_FLIGHT_MIN_FRAMES`` when ``None``: no estimate, or
        the body touches the ground at frame 0); any other stage unchanged."""
        if self.frames != FREE_FLIGHT:
            return self
        return replace(self, frames=free_flight_window(free_flight_frames))

    def with_velocity_start(self, measured: bool) -> "Stage":
        """This stage with a :attr:`velocity_if_unmeasured` rule resolved: it holds v0 (groups
        unchanged) when v0 started from a measurement, and fits it (``S`` added) when it did not;
        its name's ``[S]`` follows. Any other stage unchanged."""
        if not self.velocity_if_unmeasured:
            return self
        derived = self.name == self.label()  # a derived name is derived again from the resolved groups
        return replace(self, groups=self.groups if measured else self.groups | {"S"}, velocity_if_unmeasured=False,
                       name="" if derived else self.name.replace("[S]", "" if measured else "S"))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["groups"] = "".join(x for x in GROUPS if x in self.groups)
        d["losses"] = list(self.losses)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Stage":
        d = dict(d)
        d["groups"] = expand_groups(d["groups"])
        d["losses"] = tuple(d.get("losses", LOSSES))
        return cls(**d)


@dataclass(frozen=True)
class StageAt:
    """Where an iteration falls: stage index, the stage, and the iteration within it."""

    index: int
    stage: Stage
    step_in_stage: int


class Strategy:
    """Base class of the curricula. Subclass it and implement :meth:`build_stages`.

    Example::

        @register_strategy("velocity_first")
        class VelocityFirst(Strategy):
            def build_stages(self, material=None):
                return [Stage(frozenset("S"), 50, frames=3), Stage(frozenset("XASM"), 200)]

    Args:
        **options: strategy options (see :attr:`option_defaults` of each subclass).
    """

    registry_name: ClassVar[str] = ""
    option_defaults: ClassVar[Mapping[str, Any]] = {}

    def __init__(self, **options: Any):
        unknown = set(options) - set(self.option_defaults)
        if unknown:
            raise StrategyError(
                f"{type(self).__name__} has no option(s) {sorted(unknown)}; known options: {sorted(self.option_defaults) or 'none'}"
            )
        self.options: dict[str, Any] = {**self.option_defaults, **options}
        self._cache: dict = {}
        #: ``(frames,)`` once :meth:`with_free_flight` set the clip's free-flight window, else None
        self._free_flight: Optional[tuple[Optional[int]]] = None
        #: whether v0 started from a measurement, once :meth:`with_velocity_start` set it, else None
        self._velocity_measured: Optional[bool] = None

    @property
    def name(self) -> str:
        return self.registry_name or type(self).__name__

    def build_stages(self, material: str | None = None) -> list[Stage]:  # pragma: no cover - abstract
        """The stages for a material (built-ins use per-material iteration counts)."""
        raise NotImplementedError

    def stages(self, material: str | None = None) -> list[Stage]:
        """Validated stages (cached per material)."""
        if material not in self._cache:
            stages = list(self.build_stages(material))
            if not stages:
                raise StrategyError(f"strategy {self.name!r} produced no stages")
            for s in stages:
                if not isinstance(s, Stage):
                    raise StrategyError(f"strategy {self.name!r} produced {s!r}, expected a Stage")
            if self._free_flight is not None:
                stages = [s.with_free_flight(self._free_flight[0]) for s in stages]
            if self._velocity_measured is not None:
                stages = [s.with_velocity_start(self._velocity_measured) for s in stages]
            self._cache[material] = stages
        return self._cache[material]

    def has_free_flight_window(self, material: str | None = None) -> bool:
        """Whether a stage's window is ``free_flight`` and not yet set (:meth:`with_free_flight`)."""
        return any(s.frames == FREE_FLIGHT for s in self.stages(material))

    def with_free_flight(self, free_flight_frames: Optional[int]) -> "Strategy":
        """A copy of this strategy whose ``free_flight`` windows hold ``free_flight_frames`` training
        frames (at least :data:`FREE_FLIGHT_MIN_FRAMES`; that many when ``None``). The fit calls it
        with the stage-0 ballistic estimate's free-flight frames
        (:func:`toolkit.physics.initial_velocity.free_flight_frames`); this strategy is unchanged."""
        out = self._copy_for_clip()
        out._free_flight = (free_flight_frames,)
        return out

    def has_velocity_rule(self, material: str | None = None) -> bool:
        """Whether a stage fits v0 only when it was not measured (``[S]``) and that is not yet set
        (:meth:`with_velocity_start`)."""
        return any(s.velocity_if_unmeasured for s in self.stages(material))

    def with_velocity_start(self, measured: bool) -> "Strategy":
        """A copy of this strategy whose ``[S]`` stages hold v0 (``measured``: v0 started from the
        stage-0 ballistic estimate or was given) or fit it (v0 started at zero, a guess). The fit
        calls it once v0's start is known; this strategy is unchanged."""
        out = self._copy_for_clip()
        out._velocity_measured = bool(measured)
        return out

    def _copy_for_clip(self) -> "Strategy":
        """A copy with its own options and an empty stage cache, for a per-clip setting."""
        out = copy.copy(self)
        out.options = dict(self.options)
        out._cache = {}
        return out

    def total_iterations(self, material: str | None = None) -> int:
        return sum(s.iterations for s in self.stages(material))

    def boundaries(self, material: str | None = None) -> list[int]:
        """Cumulative iteration counts: stage i covers ``[b[i], b[i+1])``."""
        out = [0]
        for s in self.stages(material):
            out.append(out[-1] + s.iterations)
        return out

    def stage_at(self, step: int, material: str | None = None) -> StageAt:
        """The stage that iteration ``step`` (0-based, over the whole curriculum) belongs to."""
        b = self.boundaries(material)
        if not 0 <= step < b[-1]:
            raise StrategyError(f"iteration {step} is outside the curriculum [0, {b[-1]})")
        i = bisect.bisect_right(b, step) - 1
        return StageAt(i, self.stages(material)[i], step - b[i])

    def group_active_steps(self, group: str, material: str | None = None) -> int:
        """How many iterations optimize ``group`` (its learning-rate schedule spans these)."""
        return sum(s.iterations for s in self.stages(material) if group in s.groups)

    def group_progress(self, group: str, step: int, material: str | None = None) -> int:
        """How many iterations before ``step`` optimized ``group`` (drives its LR schedule)."""
        b = self.boundaries(material)
        return sum(max(0, min(step, b[i + 1]) - b[i]) for i, s in enumerate(self.stages(material)) if group in s.groups)

    def describe(self, material: str | None = None) -> list[dict]:
        """Stages as plain data with their iteration ranges (for logs, checkpoints and plots)."""
        b = self.boundaries(material)
        return [{**s.to_dict(), "start": b[i], "end": b[i + 1]} for i, s in enumerate(self.stages(material))]

    def schedule_string(self, material: str | None = None) -> str:
        """The stages in the compact schedule-string form (see :mod:`strategies.schedule`)."""
        from strategies.schedule import format_stage

        return ",".join(format_stage(s) for s in self.stages(material))

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items())
        return f"{type(self).__name__}({opts})"

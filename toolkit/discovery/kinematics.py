"""What the observed body's first phase of motion says about a missing force.

The clip's first phase is either a **flight** (the body starts off the ground; the phase ends
at the base model's first ground contact) or a **slide** (the body starts on the ground; the
phase lasts while it stays there). Gravity does not act sideways and the base model's ground is
frictionless, so without a missing force the centroid of the observed (stage-0) surfaces moves
on a straight horizontal line. A missing force leaves a signature in that line:

* a **body force** (a constant extra acceleration, air drag) bends it *smoothly* (a parabola),
  in a flight and on a slide alike; so does **ground friction** on a slide, while it cannot act
  in a flight at all;
* a **wall** bends it *abruptly*: two straight segments.

A smooth bend has a second signature, its **force law** (:func:`force_law`): a constant
acceleration (an extra acceleration; ground friction while the body slides) keeps bending the
track at the same rate, while a drag fades with the speed. Over every fit frame (the ground of
the base model is flat and frictionless, so the horizontal centroid feels only the missing
force), a parabola and a linear drag (``x(t) = x0 + v0 (1 - exp(-k t)) / k``, ``k`` scanned)
are compared by the same leave-one-frame-out error; one counts when it predicts at least
:data:`BEND_FACTOR` times better than the other. Over a short clip a weak drag and a constant
deceleration look alike (the law is then ``"either"``); a strong constant acceleration, or one
that does not point against the motion, is told from a drag.

:func:`observed_motion` fits the centroid over the phase's frames with three models of the
horizontal (x, z) motion, a straight line, a parabola and two straight segments meeting at a
frame, and compares them by their leave-one-frame-out prediction error (the same reason as
:mod:`toolkit.discovery.selection`: cross-validation instead of an information criterion). A
bent model is preferred only when it predicts the left-out frames at least :data:`BEND_FACTOR`
times better than the line.

Two uses in discovery (:mod:`toolkit.discovery.workflow`):

* **a tie-break by kind** (:func:`preferred_candidates`): among candidates the validation data
  cannot tell apart, a smooth bend prefers the forces that act smoothly in that phase (body
  forces; on a slide also ground friction), narrowed by the force law (a constant one drops air
  drag, a fading one keeps air drag alone), an abrupt one the wall;
* **a start for the extra acceleration's refit** (flights only): the parabola's acceleration
  less gravity, and its initial velocity. A first-order prediction from a base fit that absorbed
  the force (a slower throw) can point the wrong way; the observed flight does not depend on the
  base fit.
* **a start for air drag's refit** (:func:`drag_start`): the linear drag rate the force law
  fitted to the observed track. A base fit that absorbed a drag into a slower throw leaves air
  drag's first-order score near zero, so its prediction starts the refit at no drag at all.


Smooth forces are confirmed as a family (:func:`body_force_partners`): when the ranking sends
one of them to a refit (the body forces; on a slide also ground friction), the others are
refitted too, so that the validation, not the first-order score of a base fit that absorbed the
force, decides between a drag, a constant pull and friction.

Units: metres, seconds; the world frame of the physics input (gravity along its ``gravity``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

__all__ = ["ObservedMotion", "MIN_PHASE_FRAMES", "BEND_FACTOR", "BODY_FORCES", "CONSTANT_FORCES", "fit_motion",
           "force_law", "leading_phase", "observed_motion", "preferred_candidates", "loo_errors", "acceleration_start",
           "drag_start", "smooth_forces", "body_force_partners", "motion_sentence", "law_sentence"]

log = logging.getLogger(__name__)

#: at least this many frames in the phase for a shape (a parabola left one frame out needs 3 more)
MIN_PHASE_FRAMES = 5
#: a bent model must predict left-out frames this many times better than the straight line
BEND_FACTOR = 2.0
#: candidates that act on the body everywhere, in flight too
BODY_FORCES = ("extra_acceleration", "air_drag")
#: candidates whose horizontal pull does not fade with the speed (friction only while sliding)
CONSTANT_FORCES = ("extra_acceleration", "ground_friction")
#: drag rates (1/s) scanned by :func:`force_law`; 0 is the straight line
DRAG_RATES = np.concatenate([[0.0], np.geomspace(0.05, 30.0, 120)])


@dataclass
class ObservedMotion:
    """The observed centroid over the clip's first phase (a flight or a slide).

    Attributes:
        frames: the phase's frames (indices into the physics input's frames).
        acceleration: (3,) constant acceleration of the parabola fitted to the centroid, m/s^2.
        extra: (3,) ``acceleration - gravity``: what gravity does not explain, m/s^2.
        v0: (3,) the parabola's velocity at time 0 (the clip's first frame), m/s.
        shape: ``"straight"``, ``"smooth"`` (a parabola) or ``"kink"`` (two segments), horizontal only.
        loo: leave-one-frame-out root-mean-square error (m) of each horizontal model
            (``line``, ``parabola``, ``segments``).
        kink_frame: where the two segments meet (a frame index) when ``shape == "kink"``.
        phase: ``"flight"`` (off the ground) or ``"slide"`` (on it).
        law: the horizontal force law over :attr:`law_frames` (:func:`force_law`):
            ``"constant"``, ``"drag"`` or ``"either"``.
        law_loo: leave-one-frame-out RMS error (m) of the ``constant`` and the ``drag`` model.
        drag_rate: the linear drag rate ``k`` (1/s) fitted to every law frame.
        law_frames: the frames the law was judged on (every fit frame with observed surfaces).
    """

    frames: list[int]
    acceleration: np.ndarray
    extra: np.ndarray
    v0: np.ndarray
    shape: str
    loo: dict[str, float] = field(default_factory=dict)
    kink_frame: Optional[int] = None
    phase: str = "flight"
    law: str = "either"
    law_loo: dict[str, float] = field(default_factory=dict)
    drag_rate: Optional[float] = None
    law_frames: list[int] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"phase": self.phase, "frames": list(self.frames), "acceleration": [float(a) for a in self.acceleration],
                "extra": [float(a) for a in self.extra], "v0": [float(v) for v in self.v0], "shape": self.shape,
                "loo": {k: float(v) for k, v in self.loo.items()}, "kink_frame": self.kink_frame, "law": self.law,
                "law_loo": {k: float(v) for k, v in self.law_loo.items()},
                "drag_rate": None if self.drag_rate is None else float(self.drag_rate),
                "law_frames": list(self.law_frames)}

    @classmethod
    def from_dict(cls, d: dict) -> "ObservedMotion":
        """The motion :meth:`to_dict` wrote (a stored discovery record's ``motion``); fields a
        record written before they existed lack take their defaults."""
        return cls(frames=list(d["frames"]), acceleration=np.asarray(d["acceleration"], dtype=float),
                   extra=np.asarray(d["extra"], dtype=float), v0=np.asarray(d["v0"], dtype=float), shape=d["shape"],
                   loo=dict(d.get("loo") or {}), kink_frame=d.get("kink_frame"), phase=d.get("phase", "flight"),
                   law=d.get("law", "either"), law_loo=dict(d.get("law_loo") or {}), drag_rate=d.get("drag_rate"),
                   law_frames=list(d.get("law_frames") or []))


def _design(t: np.ndarray, model: str, knot: Optional[float] = None) -> np.ndarray:
    one = np.ones_like(t)
    if model == "line":
        return np.stack([one, t], 1)
    if model == "parabola":
        return np.stack([one, t, 0.5 * t * t], 1)
    if model == "drag":  # the knot is the drag rate k (1/s): y0 + v0 (1 - exp(-k t)) / k
        return np.stack([one, t if knot <= 0 else -np.expm1(-knot * t) / knot], 1)
    return np.stack([one, t, np.maximum(t - knot, 0.0)], 1)  # segments: a slope change at the knot


def _fit(t: np.ndarray, y: np.ndarray, model: str) -> tuple[np.ndarray, Optional[float], float]:
    """Least squares of ``y`` (T, D) on ``t`` (T,): ``(coefficients, knot, rss)``; for
    ``segments`` the knot is the interior time that fits best, for ``drag`` the rate of
    :data:`DRAG_RATES` that fits best (one rate for every column)."""
    knots = {"segments": list(t[1:-1]), "drag": [float(k) for k in DRAG_RATES]}.get(model, [None])
    best = None
    for knot in knots:
        A = _design(t, model, knot)
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        rss = float(((A @ coef - y) ** 2).sum())
        if best is None or rss < best[2]:
            best = (coef, knot, rss)
    return best


def loo_errors(t: np.ndarray, y: np.ndarray, models: Sequence[str] = ("line", "parabola", "segments")) -> dict[str, float]:
    """Leave-one-frame-out RMS prediction error (units of ``y``) of each of ``models`` (the line,
    the parabola, two segments; ``drag`` on request) fitted to ``y`` (T, D) against times ``t``
    (T,). Each model is refitted without the frame it predicts (segments choose their knot, the
    drag its rate, again each time)."""
    out = {}
    T = len(t)
    for model in models:
        err = []
        for k in range(T):
            keep = np.arange(T) != k
            if model == "segments" and keep.sum() < 4:
                continue
            coef, knot, _ = _fit(t[keep], y[keep], model)
            pred = _design(t[k:k + 1], model, knot) @ coef
            err.append(float(((pred - y[k:k + 1]) ** 2).sum()))
        out[model] = float(np.sqrt(np.mean(err) / y.shape[1])) if err else float("inf")
    return out


def force_law(times: np.ndarray, y: np.ndarray, factor: float = BEND_FACTOR) -> tuple[str, dict[str, float], float]:
    """Whether the pull on a horizontal track ``y`` (T, D), m, at ``times`` (T,), s, is constant
    or fades with the speed: ``(law, loo, k)``.

    ``loo``: leave-one-frame-out RMS error (m) of a parabola (``constant``) and of a linear drag
    (``drag``: ``y0 + v0 (1 - exp(-k t)) / k``, one rate for all columns, refitted without each
    frame). ``law`` is ``"constant"`` or ``"drag"`` when that model predicts at least ``factor``
    times better than the other, else ``"either"``; ``k`` (1/s) is the drag rate fitted to every
    frame. Needs at least :data:`MIN_PHASE_FRAMES` frames (``"either"`` otherwise)."""
    t = np.asarray(times, np.float64)
    y = np.asarray(y, np.float64)
    if len(t) < MIN_PHASE_FRAMES:
        return "either", {}, float("nan")
    e = loo_errors(t, y, ("parabola", "drag"))
    loo = {"constant": e["parabola"], "drag": e["drag"]}
    law = "either"
    if loo["constant"] * factor <= loo["drag"]:
        law = "constant"
    elif loo["drag"] * factor <= loo["constant"]:
        law = "drag"
    return law, loo, float(_fit(t, y, "drag")[1])


def fit_motion(centroids: np.ndarray, times: np.ndarray, gravity: Sequence[float],
               frames: Optional[Sequence[int]] = None, bend_factor: float = BEND_FACTOR,
               phase: str = "flight") -> Optional[ObservedMotion]:
    """Classify and measure a phase from centroids ``(T, 3)`` (m) at ``times`` ``(T,)`` (s).

    ``frames`` names the rows (default ``0..T-1``). ``None`` when there are fewer than
    :data:`MIN_PHASE_FRAMES`. The shape compares the horizontal (x, z) models by
    :func:`loo_errors`: the line unless the parabola or the segments predict at least
    ``bend_factor`` times better; then whichever of the two predicts better.
    """
    c = np.asarray(centroids, np.float64)
    t = np.asarray(times, np.float64)
    if len(c) < MIN_PHASE_FRAMES:
        return None
    coef, _, _ = _fit(t, c, "parabola")
    acc, v0 = coef[2], coef[1]
    loo = loo_errors(t, c[:, [0, 2]])
    bent = min(loo["parabola"], loo["segments"])
    shape, kink = "straight", None
    if bent * bend_factor <= loo["line"]:
        shape = "smooth" if loo["parabola"] <= loo["segments"] else "kink"
    frames = list(frames) if frames is not None else list(range(len(c)))
    if shape == "kink":
        _, knot, _ = _fit(t, c[:, [0, 2]], "segments")
        kink = int(frames[int(np.argmin(np.abs(t - knot)))])
    return ObservedMotion(frames=frames, acceleration=acc, extra=acc - np.asarray(gravity, np.float64), v0=v0,
                          shape=shape, loo=loo, kink_frame=kink, phase=phase)


def leading_phase(lib, q: np.ndarray, frames: Sequence[int], contact_cells: float = 1.0,
                  min_frames: int = MIN_PHASE_FRAMES) -> tuple[list[int], str]:
    """The clip's first phase of at least ``min_frames`` frames among ``frames`` in the base
    prediction ``q``: ``(frames, "flight")`` for a run of frames with the body farther than
    ``contact_cells`` grid cells from the ground (every frame when there is no ground), or
    ``(frames, "slide")`` for a run within that distance. A shorter first run (a slide's box
    dropping 6 cm onto the ground) is skipped; ``([], "flight")`` when no run is long enough."""
    ground = lib.sim.config.ground_height
    if ground is None:
        return list(frames), "flight"
    _, pos = lib.trajectory(q, list(frames))
    near = (pos[..., 1].amin(1).double().cpu().numpy() - ground) <= contact_cells * float(lib.sim.config.dx)
    runs: list[tuple[list[int], bool]] = []
    for f, on in zip(frames, near):
        if runs and runs[-1][1] == bool(on):
            runs[-1][0].append(int(f))
        else:
            runs.append(([int(f)], bool(on)))
    for fr, on in runs:
        if len(fr) >= min_frames:
            return fr, "slide" if on else "flight"
    return [], "flight"


def observed_motion(lib, q: np.ndarray, frames: Optional[Sequence[int]] = None) -> Optional[ObservedMotion]:
    """:func:`fit_motion` on the stage-0 surfaces' centroids over the first long enough phase of
    the base prediction ``q`` (:func:`leading_phase`; among ``frames``, default the library's fit
    frames). ``None`` without enough frames in the phase or observed surfaces."""
    inp = lib.input
    frames = list(lib.fit_frames if frames is None else frames)
    try:
        fl, phase = leading_phase(lib, q, frames)
    except Exception as exc:  # no estimate is no reason to stop discovery
        log.info("no leading phase: %s", exc)
        return None
    lf = [f for f in frames if len(inp.surfaces[f])]  # the law's frames; the phase's are among them
    fl = [f for f in fl if f in lf]
    if len(fl) < MIN_PHASE_FRAMES:
        return None
    centroid = {f: inp.surfaces[f].detach().double().cpu().numpy().mean(0) for f in lf}
    t0 = float(inp.times[0])
    c = np.stack([centroid[f] for f in fl])
    t = np.array([float(inp.times[f]) for f in fl]) - t0
    g = lib.gravity(q).detach().double().cpu().numpy()
    motion = fit_motion(c, t, g, frames=fl, phase=phase)
    if motion is not None:
        cl = np.stack([centroid[f] for f in lf])
        tl = np.array([float(inp.times[f]) for f in lf]) - t0
        motion.law, motion.law_loo, motion.drag_rate = force_law(tl, cl[:, [0, 2]])
        motion.law_frames = lf
    return motion


def acceleration_start(lib, q: np.ndarray, motion: Optional[ObservedMotion]) -> Optional[np.ndarray]:
    """``q`` with the extra acceleration at the flight's unexplained acceleration
    (:attr:`ObservedMotion.extra`) and v0 at the flight's, clipped to the library's bounds;
    ``None`` unless a flight bends smoothly, or without an extra-acceleration candidate."""
    if (motion is None or motion.phase != "flight" or motion.shape != "smooth"
            or "extra_acceleration.ax" not in lib.index_of):
        return None
    q = np.asarray(q, np.float64).copy()
    for a, v in zip(("ax", "ay", "az"), motion.extra):
        q[lib.index_of[f"extra_acceleration.{a}"]] = v
    for a, v in zip("xyz", motion.v0):
        q[lib.index_of[f"v0.{a}"]] = v
    return lib.clip(q)


def drag_start(lib, q: np.ndarray, motion: Optional[ObservedMotion]) -> Optional[np.ndarray]:
    """``q`` with air drag's linear rate (1/s) at the drag rate the force law fitted to the
    observed track (:attr:`ObservedMotion.drag_rate`), its quadratic rate at 0 and, in a flight,
    v0 at the flight's; clipped to the library's bounds. ``None`` without a motion, without a
    positive fitted rate, or without an air-drag candidate."""
    if (motion is None or not motion.drag_rate or motion.drag_rate <= 0.0
            or "air_drag.linear" not in lib.index_of):
        return None
    q = np.asarray(q, np.float64).copy()
    q[lib.index_of["air_drag.linear"]] = float(motion.drag_rate)
    if "air_drag.quadratic" in lib.index_of:
        q[lib.index_of["air_drag.quadratic"]] = 0.0
    if motion.phase == "flight":
        for a, v in zip("xyz", motion.v0):
            q[lib.index_of[f"v0.{a}"]] = v
    return lib.clip(q)


def smooth_forces(phase: Optional[str]) -> tuple[str, ...]:
    """The candidates that bend the track smoothly in ``phase``: the body forces, and on a
    ``"slide"`` ground friction too (it cannot act in a flight)."""
    return BODY_FORCES + (("ground_friction",) if phase == "slide" else ())


def body_force_partners(chosen: Sequence[str], available: Sequence[str], phase: Optional[str] = None) -> list[str]:
    """The other members of the smooth-force family among ``available`` when ``chosen`` holds
    one of them; else ``[]``. The family is the body forces (:data:`BODY_FORCES`) and, when the
    observed phase is a ``"slide"``, ground friction, which acts smoothly while the body slides
    (as in :func:`preferred_candidates`)."""
    family = smooth_forces(phase)
    if not any(n in family for n in chosen):
        return []
    return [n for n in family if n in available and n not in chosen]


def preferred_candidates(motion: Optional[ObservedMotion], names: Sequence[str]) -> list[str]:
    """Of ``names``, those the phase's shape supports: after a smooth bend the body forces (and
    ground friction on a slide), narrowed by the force law (``"constant"``: not air drag;
    ``"drag"``: air drag alone); after a kink the wall; none when the track is straight or there
    is no phase to judge."""
    if motion is None or motion.shape == "straight":
        return []
    if motion.shape == "smooth":
        smooth = smooth_forces(motion.phase)
        if motion.law == "constant":
            smooth = tuple(n for n in smooth if n in CONSTANT_FORCES)
        elif motion.law == "drag":
            smooth = ("air_drag",)
        return [n for n in names if n in smooth]
    return [n for n in names if n == "wall"]


def motion_sentence(motion: dict) -> str:
    """One sentence for the report from :meth:`ObservedMotion.to_dict`."""
    a = ", ".join(f"{v:+.2f}" for v in motion["extra"])
    loo = motion["loo"]
    kink = f" at frame {motion['kink_frame']}" if motion.get("kink_frame") is not None else ""
    return (f"Observed {motion['phase']} (frames {motion['frames'][0]}-{motion['frames'][-1]}, stage-0 centroid): "
            f"horizontal track {motion['shape']}{kink}; leave-one-frame-out error: line {1e3 * loo['line']:.2f} mm, "
            f"parabola {1e3 * loo['parabola']:.2f} mm, two segments {1e3 * loo['segments']:.2f} mm; acceleration "
            f"not explained by gravity ({a}) m/s^2." + law_sentence(motion))


def law_sentence(motion: dict) -> str:
    """What the force law says (empty without one), for the report and the verdict."""
    lo = motion.get("law_loo") or {}
    if not lo or not motion.get("law_frames"):
        return ""
    fr = motion["law_frames"]
    what = {"constant": "a constant pull (not a drag, which fades with the speed)",
            "drag": "a pull that fades with the speed, as a drag does",
            "either": "no preference between a constant pull and a drag"}[motion.get("law", "either")]
    return (f" Over frames {fr[0]}-{fr[-1]} the horizontal track shows {what}: leave-one-frame-out error "
            f"{1e3 * lo['constant']:.2f} mm for a constant acceleration, {1e3 * lo['drag']:.2f} mm for a linear "
            f"drag (k = {motion.get('drag_rate') or 0.0:.2f} /s).")

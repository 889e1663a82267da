"""The initial velocity v0 from stage-0 motion: a least-squares ballistic fit of the body's centroid.

Before the body touches anything, its centre of mass moves on the parabola

    x_c(t) = x_c(0) + v0 t + g t^2 / 2

whatever it does inside (an elastic body wobbles, a fluid splashes: momentum is conserved and only
gravity acts). With gravity ``g`` known from the world (the fit's :class:`~toolkit.mpm.SimConfig`),
each component of ``x_c(0)`` and ``v0`` follows from a linear least-squares fit over the free-flight
frames. That is :func:`estimate_initial_velocity`; :func:`initial_velocity_from_input` applies it to
a :class:`~toolkit.physics.inputs.PhysicsInput` (the per-frame pseudo-ground-truth surfaces of
stage 0, never the dataset's ground truth, training frames only).

Free flight ends at ground contact, found two ways (the earlier wins):

* the lowest surface point comes within ``contact_cells * dx`` of the ground plane
  ``y = ground_height`` (the quadratic B-spline of a particle below 1.5 cells reaches a ground
  node). The first such frame is still used when its centroid lies within
  ``touch_tolerance * dx`` (default a quarter cell) of the parabola of the frames before it: the
  body entered the band less than one frame interval ago and has barely been pushed;
* the trajectory bends away from the parabola: a frame and the next both further than
  ``bend_tolerance`` (m, default one grid cell) from the prediction of the fit to the frames before
  it (a wall, an obstacle, a ground that is not where the world says). Requiring two frames keeps
  centroid jitter of a few mm, amplified by extrapolation from few frames, from cutting the fit.

A body already in contact at frame 0 (resting or sliding on the ground) has no free-flight frames;
its velocity then comes from a quadratic fit with a free acceleration over the first few frames
(``method="contact"``): about zero for a body at rest, the initial slide for a sliding one.

Bias. The centroid used is that of the *surface points*, not of the mass. For a partial surface
(stage 0 sees only the camera-facing side) the two differ by an offset that is constant while the
body translates, so v0 is unbiased; when the body rotates or deforms the offset changes and v0
picks up roughly (offset change between the first and last fitted frame) / (their time span):
about 0.1 m/s for a 5 cm offset turning by 30 degrees over a quarter second. Too few free frames
(fewer than ``min_frames``, default 3 with frame 0) give ``None``: the caller keeps its own guess.

Conventions: canonical world (metres, seconds, y up, ground normal +y), v0 in m/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from toolkit.physics.world_checks import fit_free_parabola

__all__ = ["describe_estimate", "free_flight_frames", "V0Estimate", "estimate_initial_velocity", "initial_velocity_from_input",
           "CONTACT_BAND_CELLS",
           "CONTACT_FIT_FRAMES", "TOUCH_TOLERANCE_CELLS"]

#: a frame whose lowest surface point is within this many grid cells of the ground is in contact
CONTACT_BAND_CELLS = 1.5
#: grid cells the first frame in the contact band may lie off the free-flight parabola and still count
TOUCH_TOLERANCE_CELLS = 0.25
#: frames (from frame 0) of the free-acceleration fit of a body in contact at frame 0
CONTACT_FIT_FRAMES = 4


@dataclass
class V0Estimate:
    """An estimated initial velocity.

    Attributes:
        v0: (3,) m/s, canonical world.
        x0: (3,) m, the fitted centroid at frame 0.
        frames: indices of the frames used (frame 0 first).
        method: ``"ballistic"`` (known gravity, free flight) or ``"contact"`` (free acceleration,
            body on the ground at frame 0).
        rms_residual: root-mean-square distance (m) of the used centroids from the fitted curve.
        stop_reason: why later frames were left out (``"ground contact at frame k"``,
            ``"trajectory bends at frame k"``, ``"last frame"``).
    """

    v0: tuple[float, float, float]
    x0: tuple[float, float, float]
    frames: list[int]
    method: str
    rms_residual: float
    stop_reason: str

    def to_dict(self) -> dict:
        return {"v0": list(self.v0), "x0": list(self.x0), "frames": list(self.frames), "method": self.method,
                "rms_residual": self.rms_residual, "stop_reason": self.stop_reason}


def describe_estimate(est: dict) -> str:
    """One line on a :meth:`V0Estimate.to_dict` record: the v0 it gives and the frames it was fitted
    over, e.g. ``stage-0 ballistic estimate (0.5, -1, 0.2) m/s, fitted over frames 0-5 (6 frames;
    ground contact at frame 6)``."""
    f = est["frames"]
    return (f"stage-0 {est['method']} estimate ({', '.join(f'{c:.3g}' for c in est['v0'])}) m/s, fitted over frames "
            f"{f[0]}-{f[-1]} ({len(f)} frames; {est['stop_reason']})")


def free_flight_frames(est: Optional[dict]) -> Optional[int]:
    """How many training frames, from frame 0, a :meth:`V0Estimate.to_dict` record found in free
    flight (its last fitted frame + 1), or ``None`` without a ballistic estimate (none, or a body on
    the ground at frame 0). A ``free_flight`` stage window (:data:`strategies.base.FREE_FLIGHT`)
    is set from it."""
    if not est or est.get("method") != "ballistic" or not est.get("frames"):
        return None
    return int(est["frames"][-1]) + 1


def _fit(t: np.ndarray, x: np.ndarray, gravity: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of x (K, 3) on t (K,): ``x0 + v t + g t^2/2`` (g known) or with a free
    acceleration when ``gravity`` is None. Returns (x0, v, fitted (K, 3))."""
    if gravity is None:
        coef, A = fit_free_parabola(x, t)
        return coef[0], coef[1], A @ coef
    y = x - 0.5 * np.outer(t * t, gravity)
    A = np.stack([np.ones_like(t), t], axis=1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return coef[0], coef[1], A @ coef + 0.5 * np.outer(t * t, gravity)


def estimate_initial_velocity(
    surfaces: Sequence[torch.Tensor | np.ndarray],
    times: Sequence[float] | torch.Tensor | np.ndarray,
    gravity: Sequence[float] = (0.0, -9.8, 0.0),
    ground_height: Optional[float] = 0.0,
    dx: float = 0.02,
    contact_cells: float = CONTACT_BAND_CELLS,
    bend_tolerance: Optional[float] = None,
    max_frames: Optional[int] = None,
    touch_tolerance: float = TOUCH_TOLERANCE_CELLS,
    min_frames: int = 3,
) -> Optional[V0Estimate]:
    """Estimate v0 (m/s) from the centroids of per-frame surface points.

    Args:
        surfaces: per frame t, (M_t, 3) surface points in metres (canonical world, y up); an empty
            frame is skipped.
        times: (T,) frame times in seconds (frame 0 first; only differences matter).
        gravity: (3,) m/s^2, known.
        ground_height: y of the ground plane (normal +y), metres; ``None``: no ground.
        dx: the fit's grid spacing, metres (sets the contact band and the default bend tolerance).
        contact_cells: contact band above the ground, in grid cells.
        bend_tolerance: metres a frame's centroid (and the next one's) may lie off the parabola
            fitted to the frames before it; default ``dx``.
        max_frames: use at most the first ``max_frames`` frames (the training frames).
        touch_tolerance: grid cells the first frame in the contact band may lie off the parabola of
            the frames before it and still be used.
        min_frames: fewest frames (frame 0 included) to fit; 3 by default (2 after frame 0, so the
            fit has a residual); 2 allows the two-frame estimate ``(x_1 - x_0)/dt - g dt/2``.

    Returns:
        A :class:`V0Estimate`, or ``None`` when fewer than ``min_frames`` usable frames (frame 0
        included) precede contact, or frame 0 is empty.
    """
    if min_frames < 2:
        raise ValueError(f"min_frames must be >= 2 (frame 0 and one more), got {min_frames}")
    n = len(surfaces) if max_frames is None else min(len(surfaces), int(max_frames))
    t_all = np.asarray(torch.as_tensor(times).detach().cpu().double().numpy() if torch.is_tensor(times) else times,
                       dtype=np.float64)
    if len(t_all) < n:
        raise ValueError(f"times has {len(t_all)} entries but {n} surface frames are used; expected one time per frame")
    g = np.asarray(gravity, dtype=np.float64).reshape(3)
    tol = float(dx) if bend_tolerance is None else float(bend_tolerance)
    band = None if ground_height is None else float(ground_height) + contact_cells * float(dx)

    frames, cents, lows = [], [], []
    for f in range(n):
        s = surfaces[f]
        s = s.detach().cpu().double().numpy() if torch.is_tensor(s) else np.asarray(s, dtype=np.float64)
        if s.size == 0:
            continue
        frames.append(f)
        cents.append(s.reshape(-1, 3).mean(0))
        lows.append(float(s.reshape(-1, 3)[:, 1].min()))
    if not frames or frames[0] != 0:
        return None
    t = t_all[frames] - t_all[0]
    x = np.stack(cents)

    # a body on the ground at frame 0: free acceleration over the first frames (gravity is balanced)
    if band is not None and lows[0] <= band:
        k = min(len(frames), CONTACT_FIT_FRAMES)
        if k < 3:
            return None
        x0, v, fitted = _fit(t[:k], x[:k], None)
        rms = float(np.sqrt(((fitted - x[:k]) ** 2).sum(1).mean()))
        return V0Estimate(tuple(map(float, v)), tuple(map(float, x0)), frames[:k], "contact", rms,
                          f"in contact with the ground at frame 0; free-acceleration fit over {k} frames")

    # free flight: frames before the first one in the contact band ...
    end, reason, contact = len(frames), "last frame", None
    if band is not None:
        contact = next((i for i, low in enumerate(lows) if low <= band), None)
        if contact is not None:
            end, reason = contact, f"ground contact at frame {frames[contact]}"
    # ... and before the trajectory bends away from the parabola of the frames before
    for j in range(2, end):
        x0, v, _ = _fit(t[:j], x[:j], g)
        off = np.linalg.norm(x0 + np.outer(t, v) + 0.5 * np.outer(t * t, g) - x, axis=1)
        # a bend persists: frame j and the next (if any) both leave the parabola of frames < j
        if off[j] > tol and (j + 1 >= end or off[j + 1] > tol):
            end, reason, contact = j, f"trajectory bends at frame {frames[j]}", None
            break
    # the first frame in the band joins when the body has only just touched (still on the parabola)
    if contact is not None and contact == end and end >= 2:
        x0, v, _ = _fit(t[:end], x[:end], g)
        if np.linalg.norm(x0 + v * t[end] + 0.5 * g * t[end] ** 2 - x[end]) <= touch_tolerance * dx:
            end, reason = end + 1, f"ground contact at frame {frames[contact]} (kept: still on the parabola)"
    if end < min_frames:
        return None
    x0, v, fitted = _fit(t[:end], x[:end], g)
    rms = float(np.sqrt(((fitted - x[:end]) ** 2).sum(1).mean()))
    return V0Estimate(tuple(map(float, v)), tuple(map(float, x0)), frames[:end], "ballistic", rms, reason)


def initial_velocity_from_input(inp, sim_config, **options) -> Optional[V0Estimate]:
    """:func:`estimate_initial_velocity` on a :class:`~toolkit.physics.inputs.PhysicsInput`'s stage-0
    surfaces over its training frames, with the gravity, ground and ``dx`` of ``sim_config``
    (a :class:`~toolkit.mpm.SimConfig`). ``options`` go to :func:`estimate_initial_velocity`."""
    return estimate_initial_velocity(
        inp.surfaces, inp.times, gravity=tuple(float(c) for c in sim_config.gravity),
        ground_height=getattr(sim_config, "ground_height", 0.0), dx=float(sim_config.dx),
        max_frames=int(inp.n_train), **options)

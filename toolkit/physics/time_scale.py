"""Does the body fall at g? A check of a clip's frame times (and units) from stage-0 motion.

Before the body touches anything its centre of mass moves on ``x(t) = x0 + v0 t + a t^2 / 2`` with
``a = g`` (:mod:`toolkit.physics.initial_velocity`). Here the acceleration is *fitted* instead of
assumed, over the frames before ground contact, in the folder's own units:

* a folder whose frame times claim ``s`` times the true frame rate (a 30 fps video labelled 24 fps:
  ``s = 0.8``) stretches every time by ``1 / s``, so the fitted acceleration is ``s^2 g``;
* a world whose lengths are not metres (centimetres: factor 100) scales it by the unit factor.

So ``ratio = (a . g_hat) / |g|`` is 1 for a consistent clip. When it is not, the fit would explain
a body falling too slowly or too fast with the wrong physics (drag, a softer material, a different
v0), so the run says so before the physics starts. Only the component along gravity is used: the
sideways components measure nothing here and are noisier (the surface centroid of a partial,
rotating surface; up to 3 m/s^2 at 64 px).

The frames are those before the lowest surface point enters the contact band (1.5 grid cells
above the ground, as for v0); the bend test of :func:`~toolkit.physics.initial_velocity.estimate_initial_velocity`
is not used because it presupposes ``g``. At least :data:`MIN_FRAMES` frames are needed (three
unknowns per axis and one degree of freedom); with fewer, or a body on the ground at frame 0, the
check is not made (``None``).

Measured (2026-12-03, 64 px, 3 views, stage-0 surfaces; ``docs/results/time_scale_check/``): on
26 scenes of all five families drawn two ways with true frame times the ratios were 0.89-1.08.
The default tolerance (0.2) flags a frame rate off by more than about 11 % (ratio ``s^2`` outside
0.8-1.2): on 12-13 scenes per variant through the whole pipeline it flagged none with true times,
all with the times claiming 0.8x or 1.25x the true rate, and 3 of 13 at 0.9x (ratio 0.81, at the
edge); the implied frame rate was 22.3-25.5 fps for a true 24 in every case.

The direction of the fall (gravity pointing the wrong way) is :mod:`toolkit.physics.world_checks`'s.

Conventions: canonical world (metres, seconds, y up), gravity in m/s^2.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from toolkit.physics.initial_velocity import CONTACT_BAND_CELLS
from toolkit.physics.world_checks import fit_free_parabola

__all__ = ["MIN_FRAMES", "RATIO_TOLERANCE", "SE_MIN_DOF", "TimeScaleCheck", "check_time_scale", "time_scale_from_input",
           "time_scale_message", "report_time_scale"]

log = logging.getLogger(__name__)

#: fewest free-flight frames (frame 0 included) the check fits: 3 unknowns per axis + 1 degree of freedom
MIN_FRAMES = 4
#: ``abs(ratio - 1)`` above which the clip's time scale (or units) is reported as wrong
RATIO_TOLERANCE = 0.2
#: degrees of freedom of the fit (frames - 3) from which a noisy track (3 standard errors) widens the tolerance
SE_MIN_DOF = 2


@dataclass
class TimeScaleCheck:
    """The fitted free-fall acceleration of a clip against its world's gravity.

    Attributes:
        frames: the free-flight frames fitted (frame 0 first).
        acceleration: (3,) fitted acceleration, m/s^2 in the folder's units and times.
        ratio: ``(acceleration . g_hat) / |g|``; 1 for consistent frame times and metres.
        ratio_se: standard error of ``ratio`` from the fit's residuals (rough with few frames).
        fps_claimed: the frame rate the folder's times say (1 / median frame interval), Hz.
        fps_implied: the frame rate that makes the body fall at ``g``: ``fps_claimed / sqrt(ratio)``
            (``None`` when the ratio is not positive).
        tolerance: the ``abs(ratio - 1)`` allowed.
        agrees: ``|ratio - 1| <= tolerance``, or within ``3 ratio_se`` when the fit has at least
            :data:`SE_MIN_DOF` degrees of freedom (with one, four frames, the residuals say too little
            about the noise to widen the tolerance).
    """

    frames: list[int]
    acceleration: tuple[float, float, float]
    ratio: float
    ratio_se: float
    fps_claimed: float
    fps_implied: Optional[float]
    tolerance: float
    agrees: bool

    def to_dict(self) -> dict:
        d = {"frames": list(self.frames), "acceleration": list(self.acceleration), "ratio": self.ratio,
             "ratio_se": self.ratio_se, "fps_claimed": self.fps_claimed, "fps_implied": self.fps_implied,
             "tolerance": self.tolerance, "agrees": self.agrees}
        d["message"] = time_scale_message(d)
        return d


def time_scale_message(record: dict) -> str:
    """One sentence on a :meth:`TimeScaleCheck.to_dict` record, saying what to check when it disagrees."""
    g_frac = record["ratio"]
    head = (f"before ground contact (frames {record['frames'][0]}-{record['frames'][-1]}) the body falls at "
            f"{g_frac:.3g} g (standard error {record['ratio_se']:.2g}) in the folder's times")
    if record["agrees"]:
        return head + ": consistent with its frame times and metres"
    fps = record.get("fps_implied")
    fix = (f"its frame times say {record['fps_claimed']:.4g} fps; {fps:.4g} fps would make it fall at g"
           if fps else "no frame rate makes it fall at g (it rises)")
    return (head + f": the frame times or the units are off. {fix[0].upper() + fix[1:]}; or the world's lengths are "
            f"{g_frac:.3g} times their size in metres (centimetres would give 100). Check the frame times "
            f"(all_data.json), the video's frame rate and the world's scale: otherwise the fit explains the wrong "
            f"fall with the wrong physics")


def check_time_scale(surfaces: Sequence[torch.Tensor | np.ndarray], times: Sequence[float] | torch.Tensor | np.ndarray,
                     gravity: Sequence[float] = (0.0, -9.8, 0.0), ground_height: Optional[float] = 0.0, dx: float = 0.02,
                     max_frames: Optional[int] = None, tolerance: float = RATIO_TOLERANCE,
                     contact_cells: float = CONTACT_BAND_CELLS) -> Optional[TimeScaleCheck]:
    """Fit the free-fall acceleration of the per-frame surface centroids and compare it with gravity.

    Args:
        surfaces: per frame, (M_t, 3) surface points in metres (canonical world, y up); an empty
            frame ends the free-flight frames.
        times: (T,) frame times in seconds as the folder gives them (frame 0 first).
        gravity: (3,) m/s^2, the world's.
        ground_height: y of the ground plane (normal +y), metres; ``None``: no ground.
        dx: the fit's grid spacing, metres (sets the contact band).
        max_frames: use at most the first ``max_frames`` frames (the training frames).
        tolerance: the ``abs(ratio - 1)`` accepted.
        contact_cells: contact band above the ground, in grid cells.

    Returns:
        A :class:`TimeScaleCheck`, or ``None`` with fewer than :data:`MIN_FRAMES` frames before
        contact (a body on the ground at frame 0 has none).

    Raises:
        ValueError: zero gravity, a negative tolerance, or fewer times than frames used.
    """
    g = np.asarray(gravity, dtype=np.float64).reshape(3)
    g_norm = float(np.linalg.norm(g))
    if not g_norm > 0:
        raise ValueError(f"gravity must be non-zero to check the time scale against it, got {list(g)}")
    if not tolerance >= 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance!r}")
    n = len(surfaces) if max_frames is None else min(len(surfaces), int(max_frames))
    t_all = np.asarray(times.detach().cpu().double().numpy() if torch.is_tensor(times) else times, dtype=np.float64)
    if len(t_all) < n:
        raise ValueError(f"times has {len(t_all)} entries but {n} surface frames are used; expected one time per frame")
    band = None if ground_height is None else float(ground_height) + contact_cells * float(dx)
    cents = []
    for f in range(n):
        s = surfaces[f]
        s = (s.detach().cpu().double().numpy() if torch.is_tensor(s) else np.asarray(s, dtype=np.float64)).reshape(-1, 3)
        if s.size == 0 or (band is not None and float(s[:, 1].min()) <= band):
            break
        cents.append(s.mean(0))
    k = len(cents)
    if k < MIN_FRAMES:
        return None
    t = t_all[:k] - t_all[0]
    x = np.stack(cents)
    coef, A = fit_free_parabola(x, t)
    accel = coef[2]
    g_hat = g / g_norm
    ratio = float(accel @ g_hat) / g_norm
    resid_along = (x - A @ coef) @ g_hat
    dof = k - 3
    s2 = float(resid_along @ resid_along) / dof
    se = math.sqrt(s2 * float(np.linalg.inv(A.T @ A)[2, 2])) / g_norm
    fps_claimed = 1.0 / float(np.median(np.diff(t)))
    fps_implied = fps_claimed / math.sqrt(ratio) if ratio > 0 else None
    agrees = abs(ratio - 1.0) <= (max(float(tolerance), 3.0 * se) if dof >= SE_MIN_DOF else float(tolerance))
    return TimeScaleCheck(list(range(k)), tuple(map(float, accel)), ratio, se, fps_claimed, fps_implied,
                          float(tolerance), bool(agrees))


def time_scale_from_input(inp, sim_config, **options) -> Optional[TimeScaleCheck]:
    """:func:`check_time_scale` on a :class:`~toolkit.physics.inputs.PhysicsInput`'s stage-0 surfaces
    over its training frames, with the gravity, ground and ``dx`` of ``sim_config`` (a
    :class:`~toolkit.mpm.SimConfig`)."""
    return check_time_scale(inp.surfaces, inp.times, gravity=tuple(float(c) for c in sim_config.gravity),
                            ground_height=getattr(sim_config, "ground_height", 0.0), dx=float(sim_config.dx),
                            max_frames=int(inp.n_train), **options)


def report_time_scale(inp, sim_config) -> Optional[dict]:
    """:func:`time_scale_from_input` as a record (:meth:`TimeScaleCheck.to_dict`, with its
    ``message``), logged: a warning when the clip does not fall at ``g``, a debug line when it does.
    ``None`` (logged at debug level) when the clip has too few free-flight frames to tell."""
    check = time_scale_from_input(inp, sim_config)
    if check is None:
        log.debug("time-scale check not made: fewer than %d stage-0 frames before ground contact", MIN_FRAMES)
        return None
    record = check.to_dict()
    if record["agrees"]:
        log.debug("time scale: %s", record["message"])
    else:
        log.warning("%s", record["message"])
    return record

"""Sanity checks of a physics input against its world, and reporting results in the dataset's frame.

Physics inputs live in the canonical world (y up, ground y = 0, gravity along -y; see
:mod:`toolkit.data.world`). A wrong world (a floor in the wrong place, gravity sideways) makes a fit
physically wrong without any error, so before the fit:

* the body must start above the ground: a particle more than ``tolerance_cells`` grid cells below
  ``y = 0`` is a :class:`WorldError` (the grid puts ground nodes there: the body would be pushed
  out or stuck);
* the first frames' centroid must accelerate along gravity: a least-squares parabola through the
  centroids of the first frames *before the body touches the ground* (its lowest point more than
  one grid cell above ``y = 0``; at least 3 such frames, else nothing is checked) gives the
  acceleration ``a``; ``a . g_hat < -0.25 |g|`` (pulled up)
  or a sideways part ``> 0.5 |g|`` that dominates the along-gravity part is a warning (contact and
  reconstruction noise can fool it, so it never stops a run).

How *fast* the body falls (frame times, length units) is checked by :mod:`toolkit.physics.time_scale`
when the physics module is built.

Both messages name the world settings in use. ``world_meta`` is the plain dict the pipeline keeps in
``PhysicsInput.meta["world"]`` and in ``RUN/world.json``.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = [
    "WorldError",
    "centroid_acceleration",
    "check_motion",
    "fit_free_parabola",
    "check_start_above_ground",
    "check_world",
    "read_world_meta",
    "to_dataset_frame",
    "world_meta",
    "write_world_meta",
]

log = logging.getLogger(__name__)

WORLD_META_FILE = "world.json"


class WorldError(ValueError):
    """A physics input contradicts its world (e.g. the body starts below the ground)."""


def world_meta(scene) -> dict:
    """The plain-data description of ``scene``'s world kept with a physics input.

    Keys: ``dataset`` (:meth:`World.to_dict`, the dataset's frame), ``to_canonical`` (``R``, ``t``),
    ``gravity`` (canonical frame, m/s^2), ``ground_height`` (0.0: the canonical ground),
    ``layout``.
    """
    world, T = scene.world, scene.to_canonical
    return {"dataset": world.to_dict(), "to_canonical": T.to_dict(),
            "gravity": [float(v) for v in T.apply_vectors(np.asarray(world.gravity))],
            "ground_height": 0.0, "layout": scene.layout}


def describe(meta: Optional[dict]) -> str:
    """One line naming the world settings in use (for messages)."""
    if not meta:
        return ("canonical world assumed (gravity (0, -9.8, 0) m/s^2, ground y = 0 with normal +y); the input "
                "carries no world description")
    d = meta.get("dataset") or {}
    return (f"dataset world: gravity {d.get('gravity')} m/s^2, ground through {d.get('ground_point')} with normal "
            f"{d.get('ground_normal')} (source: {d.get('source')}); simulated as gravity {meta.get('gravity')} m/s^2, "
            f"ground y = {meta.get('ground_height', 0.0)} m")


def write_world_meta(path: str | Path, meta: dict) -> Path:
    from toolkit.atomic import write_text

    return write_text(path, json.dumps(meta, indent=2) + "\n")


def read_world_meta(path: str | Path) -> Optional[dict]:
    path = Path(path)
    return json.loads(path.read_text()) if path.is_file() else None


def check_start_above_ground(particles: np.ndarray, dx: float, meta: Optional[dict] = None,
                             tolerance_cells: float = 3.0) -> float:
    """Raise :class:`WorldError` when the body starts more than ``tolerance_cells * dx`` below y = 0.

    Args:
        particles: (N, 3) frame-0 particles, canonical world, metres.
        dx: grid spacing of the fit, metres.
        meta: :func:`world_meta` of the scene (for the message).
        tolerance_cells: allowed depth below the ground in grid cells.

    Returns:
        The lowest particle's height above the ground (m).
    """
    pts = np.asarray(particles, dtype=np.float64)
    ground = float((meta or {}).get("ground_height", 0.0))
    lowest = float(pts[:, 1].min()) - ground
    tol = tolerance_cells * float(dx)
    if lowest < -tol:
        below = float(np.mean(pts[:, 1] - ground < 0.0))
        raise WorldError(
            f"the body starts below the ground: its lowest particle is at y = {lowest:+.4f} m and "
            f"{100 * below:.0f}% of its particles are below y = 0 (tolerance {tolerance_cells:g} cells = {tol:.4f} m "
            f"at dx = {dx:g} m). World in use: {describe(meta)}. Check the dataset's ground (world.json in the "
            "scene folder, or the reader's ground_height) and gravity direction"
        )
    return lowest


def fit_free_parabola(centroids: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of (K, 3) points on ``c0 + v t + a t^2 / 2`` at (K,) times (K >= 3; ``t`` from
    ``times[0]``). Returns the (3, 3) coefficients (rows ``c0``, ``v``, ``a``) and the (K, 3) design
    matrix ``[1, t, t^2 / 2]``."""
    t = np.asarray(times, dtype=np.float64) - float(times[0])
    A = np.stack([np.ones_like(t), t, 0.5 * t * t], 1)
    coef, *_ = np.linalg.lstsq(A, np.asarray(centroids, dtype=np.float64), rcond=None)
    return coef, A


def centroid_acceleration(centroids: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(3,) acceleration (m/s^2) of the least-squares parabola ``c0 + v t + a t^2 / 2`` through
    (K, 3) centroids at (K,) times (K >= 3)."""
    return fit_free_parabola(centroids, times)[0][2]


def check_motion(centroids: np.ndarray, times: np.ndarray, gravity: Sequence[float],
                 meta: Optional[dict] = None) -> Optional[str]:
    """Warn (and return the message) when the first frames do not accelerate along gravity.

    Args:
        centroids: (K, 3) body centroids of the first K >= 3 frames, canonical world, metres.
        times: (K,) seconds.
        gravity: (3,) m/s^2, canonical world (what the simulator will use).
        meta: :func:`world_meta` of the scene (for the message).
    """
    if len(centroids) < 3:
        return None
    g = np.asarray(gravity, dtype=np.float64)
    g_norm = float(np.linalg.norm(g))
    if g_norm == 0:
        return None
    a = centroid_acceleration(centroids, times)
    along = float(a @ g) / g_norm
    side = float(np.linalg.norm(a - along * g / g_norm))
    if along < -0.25 * g_norm:
        what = f"accelerate against gravity ({-along:.3g} m/s^2 upwards)"
    elif side > 0.5 * g_norm and side > 2.0 * abs(along):
        what = f"accelerate sideways ({side:.3g} m/s^2 across gravity, {along:.3g} m/s^2 along it)"
    else:
        return None
    msg = (f"the first {len(centroids)} frames {what}: acceleration {np.round(a, 3).tolist()} m/s^2 against "
           f"gravity {g.tolist()} m/s^2. Gravity may point the wrong way for this data. World in use: {describe(meta)}")
    warnings.warn(msg, stacklevel=2)
    log.warning(msg)
    return msg


def check_world(particles: np.ndarray, surfaces: Sequence, times: Sequence[float], dx: float,
                meta: Optional[dict] = None, gravity: Optional[Sequence[float]] = None,
                n_frames: int = 5) -> Optional[str]:
    """Both checks on a physics input's data (see the module docstring).

    Args:
        particles: (N, 3) frame-0 particles.
        surfaces: per-frame (M_t, 3) point sets (stage-0 surfaces or ground-truth clouds); empty
            ones are skipped.
        times: (T,) seconds.
        dx: grid spacing of the fit (m).
        meta: :func:`world_meta`, or None (canonical world assumed).
        gravity: canonical gravity the simulator uses; default ``meta["gravity"]`` or (0, -9.8, 0).
        n_frames: frames used by the motion check (fewer once the body is within one cell of
            the ground).

    Returns:
        The motion warning, if any.
    """
    check_start_above_ground(np.asarray(particles), dx, meta)
    g = gravity if gravity is not None else (meta or {}).get("gravity", (0.0, -9.8, 0.0))
    ground = float((meta or {}).get("ground_height", 0.0))
    cents, ts = [], []
    for t, pts in enumerate(list(surfaces)[:n_frames]):
        pts = np.asarray(pts.detach().cpu() if hasattr(pts, "detach") else pts, dtype=np.float64)
        if not len(pts):
            continue
        if float(pts[:, 1].min()) - ground <= float(dx):  # touching the ground: contact forces, not gravity
            break
        cents.append(pts.mean(0))
        ts.append(float(times[t]))
    return check_motion(np.asarray(cents), np.asarray(ts), g, meta) if len(cents) >= 3 else None


def to_dataset_frame(estimate: dict, meta: Optional[dict]) -> dict:
    """``v0`` and ``gravity`` of an estimate (canonical world) expressed in the dataset's frame.

    Returns ``{"v0": [...], "gravity": [...]}`` (m/s, m/s^2); the canonical values when ``meta`` is None.
    """
    from toolkit.data.world import RigidTransform

    back = RigidTransform.from_dict((meta or {}).get("to_canonical")).inverse()
    out = {}
    for key in ("v0", "gravity"):
        if estimate.get(key) is not None:
            out[key] = [float(v) for v in back.apply_vectors(np.asarray(estimate[key], dtype=np.float64))]
    return out

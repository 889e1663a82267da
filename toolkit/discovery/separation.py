"""What observation would separate two candidates the data cannot tell apart.

When two refits explain the clip equally well (:func:`toolkit.discovery.selection.decide`),
discovery names both and says which *new* observation would tell them apart. The answer is
derived from the two refits' predictions, not from a fixed text per pair:

A new observation must show the two apart by ``need = max(VISIBLE_PX, 2 x`` what the fitted
cameras already show over the clip) pixels: a difference the clip shows did not separate them.

* **a recorded camera**: first, the scene's cameras that were not fitted (the held-out ones) are
  asked: if one of them, with the body in view, sees the two predictions part by ``need`` pixels
  over the clip, the data to separate them already exist, and the report names that camera
  (``camera``; observation "another camera"). The benchmark's four-camera slides (2026-11-28)
  showed one well-placed added camera naming an effect three could not.
* **another camera**: over the observed frames the two predictions part in 3D, but the fitted
  cameras see the difference mostly along their viewing rays, while a camera looking across the
  difference would see ``need`` pixels (the difference's full size in pixels at the fitted cameras' depth and
  focal length). The direction to look across is reported.
* **a longer clip**: the predictions stay within a pixel over the observed frames but part
  after them; the report gives the first frame (and how many frames past the clip) where any
  fitted camera sees them :data:`VISIBLE_PX` pixels apart.
* **another throw**: they stay together over the clip and its continuation; the same two
  models are simulated from the initial velocity scaled by :data:`THROW_SCALES` and the throw
  that parts them most is reported (a speed-dependent force and a constant one, for instance,
  part at another speed).

Pixel distances use the centroid of the body (m) projected by each fitted camera; "the clip" is
the training frames (``input.n_train``), the frames the candidates were judged on.
"""

from __future__ import annotations

import logging
from typing import Optional

import numpy as np
import torch

__all__ = ["separating_observation", "recorded_camera_pixels", "VISIBLE_PX", "THROW_SCALES", "EXTRA_FRAMES"]

log = logging.getLogger(__name__)

#: a difference this many pixels wide in a fitted camera counts as visible
VISIBLE_PX = 1.0
#: initial-velocity scales tried for "another throw"
THROW_SCALES = (0.5, 2.0)
#: frames simulated past the observed clip for "a longer clip" (at most)
EXTRA_FRAMES = 12


def _centroids(refit, n_frames: int, v0_scale: float = 1.0) -> Optional[np.ndarray]:
    """(T, 3) body centroid (m) of a refit's prediction over ``n_frames`` frames, or ``None``
    when the simulation fails (e.g. the body leaves the grid)."""
    lib, q = refit.lib, np.array(refit.q, dtype=np.float64)
    if v0_scale != 1.0:
        for a in "xyz":
            q[lib.index_of[f"v0.{a}"]] *= v0_scale
    try:
        _, pos = lib.trajectory(q, list(range(n_frames)))
    except Exception as exc:  # a longer horizon may leave the grid: that observation is not available
        log.info("separation: %s over %d frames failed (%s)", refit.name, n_frames, exc)
        return None
    if not torch.isfinite(pos).all():
        return None
    return pos.mean(1).double().cpu().numpy()


def _pixels(cams, c: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For centroids ``c`` (T, 3) and differences ``d`` (T, 3): (C, T) image distance (px) of
    ``d`` in each camera, and (C, T) its full size (px) seen by a camera at the same depth and
    focal length looking across it."""
    K = cams.K.double().cpu().numpy()
    w2c = cams.w2c.double().cpu().numpy()
    out, full = [], []
    for k in range(len(K)):
        R, t = w2c[k, :3, :3], w2c[k, :3, 3]

        def proj(x):
            y = x @ R.T + t
            z = np.maximum(y[:, 2], 1e-6)
            return np.stack([K[k, 0, 0] * y[:, 0] / z + K[k, 0, 2], K[k, 1, 1] * y[:, 1] / z + K[k, 1, 2]], 1), z

        p0, z = proj(c)
        p1, _ = proj(c + d)
        out.append(np.linalg.norm(p1 - p0, axis=1))
        full.append(np.linalg.norm(d, axis=1) * K[k, 0, 0] / z)
    return np.array(out), np.array(full)


def _in_view(cams, c: np.ndarray) -> np.ndarray:
    """(C, T) whether each centroid ``c`` (T, 3) projects inside each camera's image, in front of it."""
    uv, z = cams.project(torch.as_tensor(c, dtype=torch.float64, device=cams.K.device))
    u, v = uv[..., 0], uv[..., 1]
    return ((z > 0) & (u >= 0) & (u < cams.width) & (v >= 0) & (v < cams.height)).cpu().numpy()


def recorded_camera_pixels(inp, ca: np.ndarray, cb: np.ndarray) -> dict[int, float]:
    """For every camera of ``inp`` that was not fitted: the largest image distance (px) between the
    centroids ``ca`` and ``cb`` (T, 3, m) over the frames where the body is in its view (0 when it
    never is). ``{}`` when every camera was fitted."""
    others = [c for c in range(len(inp.cameras)) if c not in set(inp.train_cameras)]
    if not others:
        return {}
    cams = inp.cameras[others]
    seen, _ = _pixels(cams, ca, cb - ca)
    view = _in_view(cams, ca) & _in_view(cams, cb)
    return {int(c): float(np.where(view[i], seen[i], 0.0).max()) for i, c in enumerate(others)}


def separating_observation(a, b, visible_px: float = VISIBLE_PX) -> dict:
    """Which observation separates the refits ``a`` and ``b`` (:class:`~toolkit.discovery.confirm.Refit`).

    Returns:
        ``{"candidates": [a, b], "observation": "another camera" | "a longer clip" | "another throw"
        | "none found", "sentence": ..., "clip_px": largest separation a fitted camera sees over the
        observed frames (px), "across_px": the same difference seen across (px), "direction": unit
        world direction to look across (another camera), "longer_clip_frame": first frame past the
        clip where a fitted camera sees >= visible_px (or None), "throw_px": {v0 scale: px},
        "recorded_px": {camera index: px} for the scene's cameras that were not fitted, "camera":
        the recorded camera that separates them (or None)}``.
    """
    inp = a.lib.input
    T = inp.n_train  # the clip the candidates were judged on (the training frames)
    cams = inp.cameras[list(inp.train_cameras)]
    out: dict = {"candidates": [a.name, b.name], "clip_px": None, "across_px": None, "direction": None,
                 "longer_clip_frame": None, "throw_px": {}, "recorded_px": {}, "camera": None}
    ca, cb = _centroids(a, T), _centroids(b, T)
    if ca is None or cb is None:
        out.update(observation="none found", sentence=f"{a.name} and {b.name} could not both be simulated over the clip.")
        return out
    seen, across = _pixels(cams, ca, cb - ca)
    out["clip_px"], out["across_px"] = float(seen.max()), float(across.max())
    # what a new observation must show: a visible difference, and at least twice what the clip
    # already shows (a difference the clip shows did not separate them: it is within noise)
    need = max(visible_px, 2.0 * out["clip_px"])
    out["needed_px"] = need
    out["recorded_px"] = recorded_camera_pixels(inp, ca, cb)
    if out["recorded_px"]:
        cam, px = max(out["recorded_px"].items(), key=lambda kv: kv[1])
        if px >= need:
            fitted = sorted(int(c) for c in inp.train_cameras)
            out.update(observation="another camera", camera=cam, sentence=(
                f"another camera: camera {cam}, recorded but not fitted, sees {a.name} and {b.name} part by {px:.1f} px "
                f"over the clip against {out['clip_px']:.1f} px in the fitted cameras {fitted}; fitting with cameras "
                f"{sorted(fitted + [cam])} would separate them."))
            return out
    if out["across_px"] >= need:
        t = int(across.max(0).argmax())
        d = (cb - ca)[t]
        out["direction"] = (d / max(np.linalg.norm(d), 1e-12)).tolist()
        dx, dy, dz = out["direction"]
        out.update(observation="another camera", sentence=(
            f"another camera: over the clip {a.name} and {b.name} part by {out['across_px']:.1f} px seen across "
            f"(frame {t}), but only {out['clip_px']:.1f} px in the fitted cameras, which look along the difference; "
            f"a camera viewing across the direction ({dx:+.2f}, {dy:+.2f}, {dz:+.2f}) would separate them."))
        return out
    for n in range(T + 2, T + EXTRA_FRAMES + 1, 2):
        la, lb = _centroids(a, n), _centroids(b, n)
        if la is None or lb is None:
            break
        seen_l, _ = _pixels(cams, la, lb - la)
        hits = np.nonzero(seen_l.max(0) >= need)[0]
        if len(hits):
            f = int(hits[0])
            if f >= T:
                out["longer_clip_frame"] = f
                out.update(observation="a longer clip", sentence=(
                    f"a longer clip: {a.name} and {b.name} agree within {out['clip_px']:.1f} px over the {T} fitted "
                    f"frames but part by {need:.1f} px at frame {f} ({f - T + 1} frame(s) past the clip)."))
                return out
            break
    for s in THROW_SCALES:
        ta, tb = _centroids(a, T, s), _centroids(b, T, s)
        if ta is not None and tb is not None:
            out["throw_px"][str(s)] = float(_pixels(cams, ta, tb - ta)[0].max())
    if out["throw_px"]:
        s, px = max(out["throw_px"].items(), key=lambda kv: kv[1])
        if px >= need:
            out.update(observation="another throw", sentence=(
                f"another throw: {a.name} and {b.name} predict this throw alike (within {out['clip_px']:.1f} px) but part by "
                f"{px:.1f} px when thrown at {s}x the initial velocity."))
            return out
    out.update(observation="none found", sentence=(
        f"no observation tried separates {a.name} and {b.name} by {need:.1f} px (clip {out['clip_px']:.1f} px, "
        f"a longer clip and throws at {', '.join(map(str, THROW_SCALES))}x the speed): the data cannot tell them apart."))
    return out

"""Model selection that refuses to over-name: held-out data, a penalty per parameter, ties within noise.

**Criterion: cross-validation on held-out frames and cameras, with a penalty per extra
parameter.** Every confirmation refit (the base alone, each candidate with the base) is fitted
on the refit frames of the fitted cameras and scored on data it did not use
(:func:`validation_components`): the held-out cameras on the refit frames, every camera on the
held-out training frames, and the stage-0 surfaces on those frames. A candidate's
*validation improvement* is the mean relative drop of those losses against the base refit, each
measured against the loss plus stage 0's floor (:func:`relative_improvements`, floors from
:func:`toolkit.discovery.from_images.geometry_floor`). Its *penalized* improvement subtracts
:attr:`~toolkit.discovery.calibration.Thresholds.per_parameter` for every strength parameter
beyond the first (the calibrated threshold already pays for the first one).

Why cross-validation and not AIC/BIC: the residuals are pixels and surface points, strongly
correlated within a frame and a camera, so the number of independent observations that an
information criterion needs is unknown (``n`` = pixels would make any penalty negligible);
held-out frames and cameras measure prediction directly, and a candidate that only bends to
the refit frames is not rewarded there. The per-parameter penalty then stops a many-parameter
candidate (extra acceleration, 3 components) from winning over a one-parameter one by the
small extra freedom every additional parameter buys on held-out data too.

**Null result.** No candidate's penalized improvement passes the null-calibrated threshold:
"no missing effect".

**Ties within noise** (:func:`criterion_noise`): the held-out losses are kept per frame and
camera; two candidates are tied when their validation improvements differ by less than twice
the standard error of the paired per-frame differences (frames are the independent units), or
less than the fixed tolerance of :func:`decide`. Tied candidates are all reported, with what
observation would separate them (:mod:`toolkit.discovery.separation`).
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

__all__ = ["PENALTY_PER_PARAMETER", "validation_components", "relative_improvements", "penalized", "criterion_noise",
           "decide", "passes", "camera_reported", "CARVED_THROUGH_CAMERAS", "camera_judged"]

#: default relative validation improvement each strength parameter beyond the first must buy
#: (see :attr:`toolkit.discovery.calibration.Thresholds.per_parameter`)
PENALTY_PER_PARAMETER = 0.01


def validation_components(lib, q: np.ndarray, val_frames: Sequence[int], cells: Optional[dict] = None) -> dict[str, float]:
    """The validation losses of a refit: ``held_out_cameras`` (image loss of the held-out
    cameras on the refit frames), ``held_out_frames`` (image loss of every camera on
    ``val_frames``) and ``held_out_surfaces`` (Chamfer to the stage-0 surfaces on ``val_frames``).

    When ``cells`` is a dict it receives the per-frame losses behind each component
    (``{component: [loss per frame]}``), for :func:`criterion_noise`.
    """
    from toolkit.metrics.geometry import chamfer_loss

    inp = lib.input
    out: dict[str, float] = {}
    per: dict[str, list[float]] = {}
    if inp.held_out_cameras:
        loss = lib.image_losses(q, lib.fit_frames, inp.held_out_cameras)  # (F, C)
        out["held_out_cameras"] = float(loss.mean())
        per["held_out_cameras"] = loss.mean(1).tolist()
    if val_frames:
        loss = lib.image_losses(q, val_frames, list(range(len(inp.cameras))))
        out["held_out_frames"] = float(loss.mean())
        per["held_out_frames"] = loss.mean(1).tolist()
        if lib.module.lambda_geometry > 0:
            x0, pos = lib.trajectory(q, val_frames)
            vals = [float(chamfer_loss(pos[k][lib.module.surface_index], inp.surfaces[f].to(pos.device)))
                    for k, f in enumerate(val_frames) if len(inp.surfaces[f])]
            if vals:
                out["held_out_surfaces"] = float(np.mean(vals))
                per["held_out_surfaces"] = vals
    if cells is not None:
        cells.update(per)
    return out


def relative_improvements(base: dict[str, float], cand: dict[str, float], floors: Optional[dict[str, float]] = None) -> dict[str, float]:
    """``(base_k - cand_k) / (base_k + floor_k)`` per component ``k`` present in both (0 where
    the denominator is 0). ``floors`` (default 0) is stage 0's geometric uncertainty in each
    component's units (:func:`toolkit.discovery.from_images.geometry_floor`)."""
    floors = floors or {}
    out = {}
    for k in base:
        if k in cand:
            den = base[k] + max(floors.get(k, 0.0), 0.0)
            out[k] = (base[k] - cand[k]) / den if den > 0 else 0.0
    return out


#: validation components made from stage 0's geometry, which was carved through the fitted cameras
CARVED_THROUGH_CAMERAS = ("held_out_surfaces",)


def camera_judged(relative: dict[str, float], stage0_geometry: bool) -> dict[str, float]:
    """The relative improvements (:func:`relative_improvements`) that judge the camera-pose control.

    With stage-0 geometry the held-out surfaces were reconstructed through the camera under
    suspicion: they carry its pose error, so a corrected pose that moves the physics away from
    them is not evidence against the correction. The control is then judged by the image
    components only (held-out cameras and frames). With geometry that does not come from the
    cameras (the true body) every component judges it."""
    if not stage0_geometry:
        return dict(relative)
    return {k: v for k, v in relative.items() if k not in CARVED_THROUGH_CAMERAS}


def penalized(validation: float, dof: int, per_parameter: float) -> float:
    """The validation improvement less ``per_parameter`` for every strength parameter beyond the first."""
    return float(validation) - per_parameter * max(int(dof) - 1, 0)


def criterion_noise(cells: dict[str, dict[str, list[float]]], a: str, b: str, base: str = "base",
                    floors: Optional[dict[str, float]] = None) -> float:
    """Standard error of the difference of two refits' validation improvements.

    ``cells[name][component]`` are per-frame losses (:func:`validation_components`). Per
    component, the paired per-frame differences ``(a_f - b_f) / (base_f + floor)`` are the
    samples (frames are the independent units: pixels of one frame are not); the standard error
    of their mean is combined over the components as the improvement is (a mean of the
    components). ``0.0`` when fewer than 2 frames are available in every component.
    """
    floors = floors or {}
    var, n = 0.0, 0
    for k in cells.get(base, {}):
        if k not in cells.get(a, {}) or k not in cells.get(b, {}):
            continue
        ba, aa, bb = (np.asarray(cells[x][k], dtype=float) for x in (base, a, b))
        if len(ba) < 2 or len(aa) != len(ba) or len(bb) != len(ba):
            n += 1
            continue
        den = ba + max(floors.get(k, 0.0), 0.0)
        d = np.where(den > 0, (bb - aa) / np.where(den > 0, den, 1.0), 0.0)
        var += float(np.var(d, ddof=1)) / len(d)
        n += 1
    return math.sqrt(var) / n if n else 0.0


def passes(name: str, v: dict, thr) -> bool:
    """A physics candidate passes: its penalized validation improvement beats the threshold, the
    training objective does not get worse, and no validation component worsens too much."""
    val = penalized(v["validation"], v.get("dof", 1), getattr(thr, "per_parameter", 0.0))
    return (name != "base" and not v["control"] and val > thr.validation and v["fit"] > thr.fit
            and v["worst"] > -thr.max_worsening)


def camera_reported(cam: Optional[dict], thr) -> bool:
    """Whether the camera-pose control's statistics point at an observation problem: its training
    improvement passes ``thr.camera``, no held-out component worsens beyond ``thr.max_worsening``,
    and the held-out data improve past ``thr.validation`` or the improvement is concentrated in one
    camera (``concentration`` >= :data:`toolkit.discovery.camera.CONCENTRATED`)."""
    from toolkit.discovery.camera import CONCENTRATED

    if cam is None or cam["fit"] <= thr.camera or cam["worst"] <= -thr.max_worsening:
        return False
    return cam["validation"] > thr.validation or cam.get("concentration", 0.0) >= CONCENTRATED


def decide(validation: dict, dofs: dict[str, int], thr, noise: Optional[dict[str, dict[str, float]]] = None,
           single_camera: Optional[int] = None, prefer: Sequence[str] = (),
           silhouette_suspect: Optional[int] = None) -> tuple[Optional[str], str, list[str]]:
    """``(decision, kind, tied)`` from the confirmation's validation statistics, the candidates'
    numbers of strength parameters and the thresholds.

    Among the candidates that pass (:func:`passes`), those whose penalized improvement is within
    ``max(threshold, 20 % of the best, 2 x criterion noise)`` of the best cannot be told apart
    (``noise[a][b]``: :func:`criterion_noise`, optional); of those the one with the fewest strength
    parameters is chosen (parsimony), then the best. ``prefer`` narrows that choice first: when
    some tied candidates are in it (the kind of force the observed flight shows,
    :func:`toolkit.discovery.kinematics.preferred_candidates`), the winner is one of them. Without a passing candidate, the camera-pose
    control is an observation problem when it improves the fit and the held-out data; otherwise
    ``(None, "none", [])`` (:func:`camera_reported`). When the base model's residual grows in one fitted camera alone
    (``single_camera``, :attr:`toolkit.discovery.residuals.Localization.single_camera`) and the
    camera-pose control explains the training data at least as well as the best physics
    candidate, the observation problem wins over physics: a force acts on every view alike.
    When the fitted cameras' silhouettes contradict one camera's pose (``silhouette_suspect``,
    :func:`toolkit.discovery.camera.silhouette_check`) and the camera-pose control was refitted,
    the decision is that observation problem whatever the candidates do: masks of one instant that
    disagree are not a matter of physics.
    """
    if silhouette_suspect is not None and "camera_pose" in validation:
        return "camera_pose", "observation", []
    per = getattr(thr, "per_parameter", 0.0)
    score = {n: penalized(v["validation"], dofs.get(n, v.get("dof", 1)), per) for n, v in validation.items()}
    passing = [n for n, v in validation.items() if passes(n, {**v, "dof": dofs.get(n, v.get("dof", 1))}, thr)]
    cam = validation.get("camera_pose")
    cam_ok = camera_reported(cam, thr)
    if cam_ok and single_camera is not None and passing and cam["fit"] >= max(validation[n]["fit"] for n in passing):
        return "camera_pose", "observation", []
    if passing:
        best_name = max(passing, key=lambda n: score[n])
        best = score[best_name]
        base_tol = max(thr.validation, 0.2 * best)

        def tol(n):
            se = (noise or {}).get(best_name, {}).get(n, 0.0)
            return max(base_tol, 2.0 * se)

        tied = [n for n in passing if best - score[n] < tol(n) or n == best_name]
        pool = [n for n in tied if n in prefer] or tied
        win = min(pool, key=lambda n: (dofs.get(n, 1), -score[n]))
        return win, "physics", sorted((n for n in tied if n != win), key=lambda n: -score[n])
    if cam_ok:
        return "camera_pose", "observation", []
    return None, "none", []

"""A camera-pose error as an observation problem: one fitted camera, a rigid shift, its own residual.

The ``camera_pose`` control first refits a translation of *every* fitted camera with the base
(3 x C parameters). With a stage-0 geometry those translations also absorb small geometry
mismatches in every camera, which makes the held-out data worse and hides a real pose error.
So the control is narrowed to the camera that carries the improvement
(:func:`single_camera_refit`):

1. per fitted camera, the drop of its training image loss (over the refit frames) from the base
   refit to the all-camera refit; the camera with the largest drop is the suspect;
2. the control is refitted with the base and that camera's translation only (3 strengths);
   the *concentration* is the share of the all-camera refit's training improvement that this
   one camera's rigid shift recovers (1: the error is that camera's pose; about ``1 / C`` when
   every camera absorbs a little, which is what a geometry mismatch or a force does).

The decision (:func:`toolkit.discovery.selection.decide`) reports an observation problem when
this refit improves the training objective by more than the calibrated
:attr:`~toolkit.discovery.calibration.Thresholds.camera`, no held-out component worsens beyond
the allowed amount, and either the held-out data improve (a corrected pose lets the physics fit
the other views) or the improvement is concentrated in the one camera (at least
:data:`CONCENTRATED`: a rigid image-space shift of one view that the physics never followed).

Before any refit, :func:`silhouette_check` asks the masks themselves: where one fitted camera's
silhouettes contradict the others' (:mod:`toolkit.scene.silhouette_agreement`), no force can be
the cause, so the control is confirmed on that camera and the decision is an observation problem
(:func:`toolkit.discovery.selection.decide`, ``silhouette_suspect``). A shift the geometry absorbs
(stage 0 fitted to the wrong camera) leaves the training loss unmoved, but not the masks.
"""

from __future__ import annotations

import logging
from typing import Optional

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["CONCENTRATED", "single_camera_refit", "camera_shift_text", "silhouette_check"]

#: share of the all-camera improvement one camera's shift must recover (twice what the other
#: cameras recover together with 3 fitted cameras). Chosen, not calibrated: on the tiny stage-0
#: scene with a 2.5 cm pose error the share was 0.85 (training gain 20 %); on a tiny stage-0
#: null scene it was 0.71 too, but with a training gain of 2.5 %, below the camera threshold,
#: which is what kept it from being reported. Null scenes of the benchmark
#: (``camera_concentration`` in the calibration statistics) are the check.
CONCENTRATED = 2.0 / 3.0


def silhouette_check(inp) -> Optional[dict]:
    """Whether the fitted cameras' silhouettes agree on the training frames
    (:func:`toolkit.scene.silhouette_agreement.silhouette_agreement` on the physics input's claimed
    cameras and masks): its ``to_dict()`` with ``message``, or ``None`` when it cannot run (it
    must not stop the discovery). A ``suspect`` is a camera whose pose the masks contradict,
    which no physics can cause."""
    from toolkit.scene.silhouette_agreement import silhouette_agreement

    try:
        cams = list(inp.train_cameras)
        check = silhouette_agreement(inp.cameras, {c: inp.masks[c] for c in cams}, cams, range(inp.n_train))
    except Exception as exc:  # no masks, an empty frame: the check is advice
        log.warning("silhouette check skipped: %s", exc)
        return None
    log.info("silhouettes: %s", check.message())
    return {**check.to_dict(), "message": check.message()}


def single_camera_refit(lib, base, full, iterations: int, camera: Optional[int] = None):
    """The camera-pose control narrowed to one camera (see the module docstring).

    Args:
        lib: the library model.
        base: the base-only :class:`~toolkit.discovery.confirm.Refit`.
        full: the all-camera ``camera_pose`` refit.
        iterations: Levenberg-Marquardt iterations.
        camera: the scene index of the camera to narrow to (the silhouette check's suspect);
            default (or a camera that is not fitted): the one whose loss the all-camera refit
            lowered most.

    Returns:
        A :class:`~toolkit.discovery.confirm.Refit` named ``camera_pose`` whose ``extra`` holds
        ``camera`` (scene camera index), ``fitted_index`` (its index among the fitted cameras),
        ``concentration``, ``per_camera_drop`` (relative drop per fitted camera) and ``shift`` (m).
    """
    from toolkit.discovery.confirm import lm_refit

    cams = list(lib.input.train_cameras)
    before = lib.image_losses(base.q, lib.fit_frames, cams).mean(0).numpy()
    after = lib.image_losses(full.q, lib.fit_frames, cams).mean(0).numpy()
    drop = before - after
    k = cams.index(camera) if camera in cams else int(np.argmax(drop))
    names = [f"camera_pose.c{k}.{a}" for a in "xyz"]
    q = base.q.copy()
    for n in names:
        q[lib.index_of[n]] = full.q[lib.index_of[n]]
    rf = lm_refit(lib, q, lib.base_names + names, "camera_pose", iterations=iterations)
    gain_full, gain_one = base.objective - full.objective, base.objective - rf.objective
    share = float(np.clip(gain_one / gain_full, 0.0, 1.0)) if gain_full > 0 else 0.0
    rf.extra = {"camera": cams[k], "fitted_index": k, "concentration": share,
                "per_camera_drop": [float(d / b) if b > 0 else 0.0 for d, b in zip(drop, before)],
                "shift": [float(rf.q[lib.index_of[n]]) for n in names]}
    return rf


def camera_shift_text(refit, loc) -> str:
    """The verdict's words for a camera-pose refit: which fitted camera (the one with the largest
    rigid shift) and its shift in cm, e.g. *of fitted camera 1 (its centre off by (+1.8, +0.9,
    -0.6) cm, a rigid image-space shift)*; ``loc`` is the
    :class:`~toolkit.discovery.residuals.Localization`."""
    if refit is None or not refit.strengths:
        return " of a fitted camera"
    per: dict[int, list[float]] = {}
    for n, v in refit.strengths.items():
        k = int(n.split(".")[1][1:])
        per.setdefault(k, []).append(v)
    k = max(per, key=lambda c: float(np.linalg.norm(per[c])))
    cam = loc.train_cameras[k] if k < len(loc.train_cameras) else k
    d = ", ".join(f"{100 * v:+.1f}" for v in per[k])
    alone = " (the residual grows in that camera alone)" if loc.single_camera == cam else ""
    return f" of fitted camera {cam} (its centre off by ({d}) cm, a rigid image-space shift){alone}"

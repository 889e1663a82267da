"""Decision thresholds of discovery, calibrated on scenes generated without any hidden effect.

A physics candidate is *discovered* when, against the base-only refit, it improves

* the validation data (held-out cameras on the refit's frames, every camera on the held-out
  training frames, the stage-0 surfaces of the held-out frames: the mean of the relative
  improvements, ``validation``) by more than :attr:`Thresholds.validation`, and
* the training objective (relative, ``fit``) by more than :attr:`Thresholds.fit` (fixed at 0,
  not calibrated: a real effect must not make the fit worse, but a flexible candidate improves
  the fit of null scenes too, and an effect that acts late, such as a wall reached near the end
  of the refit frames, improves mostly the held-out frames; the training improvement does not
  separate them),

with no validation component worse by more than :attr:`Thresholds.max_worsening`. The
camera-pose control is reported (an observation error) when no physics candidate passes, its
training improvement exceeds :attr:`Thresholds.camera`, no held-out component worsens too much,
and either it improves the validation data as a physics candidate must (a corrected pose lets
the physics fit the other views) or one camera's rigid shift recovers most of the improvement
(:mod:`toolkit.discovery.camera`: a pose error the physics never followed shows in its own
camera only; a misfit absorbed by every camera's free translation is not a pose error).
Otherwise the answer is "no missing effect".

How the shipped values were obtained (:data:`DEFAULT_THRESHOLDS`): ``benchmarks/discovery.py
--calibrate`` runs the whole workflow (base fit, ranking, confirmation) on null scenes
(:func:`toolkit.discovery.hidden.hidden_suite` with nothing hidden) and keeps, per scene, the
largest statistic any candidate reached; :func:`calibrate` sets the ``validation`` and
``camera`` thresholds to ``margin x max + floor`` over those scenes (the camera's over the
scenes where it would have been reported). Re-run it for another
scene size or fitting budget and load the written JSON with :meth:`Thresholds.load` (``projo4d discover --thresholds``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

__all__ = ["Thresholds", "DEFAULT_THRESHOLDS", "calibrate", "null_statistics"]


@dataclass(frozen=True)
class Thresholds:
    """Decision thresholds (relative improvements over the base-only refit; see the module docstring).

    Attributes:
        validation: minimum mean relative improvement of the validation components.
        fit: minimum relative improvement of the training objective.
        camera: minimum relative training improvement of the camera-pose control.
        max_worsening: largest relative worsening allowed in any validation component.
        per_parameter: validation improvement each strength parameter beyond the first must buy
            (the penalty of :mod:`toolkit.discovery.selection`; not calibrated: a choice, 0.01).
        source: how the values were obtained.
        n_null: number of null scenes behind them.
    """

    validation: float = 0.03
    fit: float = 0.0
    camera: float = 0.10
    max_worsening: float = 0.10
    per_parameter: float = 0.01
    source: str = "default"
    n_null: int = 0

    @classmethod
    def load(cls, path: str | Path) -> "Thresholds":
        """Thresholds from a JSON file written by :meth:`save` (or :func:`calibrate`)."""
        d = json.loads(Path(path).read_text())
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})

    def save(self, path: str | Path) -> Path:
        from toolkit.atomic import write_json

        return write_json(path, asdict(self))

    def to_dict(self) -> dict:
        return asdict(self)


#: thresholds calibrated with ``benchmarks/discovery.py --small --calibrate --null 12``: 12 null
#: scenes of size ``tiny`` (32 px, 10 cameras, 6 + 3 frames; base fit dx 0.04 m, 30 substeps,
#: curriculum ``XAS:20@3,XASM:80``; discovery with its defaults). The largest validation
#: improvement a candidate reached on them was 0.063 (air drag on a toss), hence 1.25 x 0.063 + 0.01;
#: the camera-pose control never passed the validation threshold there, hence its floor.
DEFAULT_THRESHOLDS = Thresholds(validation=0.088, fit=0.0, camera=0.05, max_worsening=0.10,
                                source="calibrated on 12 null scenes (tiny size, benchmarks/discovery.py --small)", n_null=12)


def null_statistics(result, per_parameter: float = 0.01) -> dict[str, float]:
    """The decision statistics of a :class:`~toolkit.discovery.workflow.DiscoveryResult` (or its
    ``to_dict()``, or ``{"validation": ...}``) computed on a null scene: ``validation`` and
    ``fit``, the largest over the confirmed physics candidates (the validation improvement
    penalized by ``per_parameter`` per strength parameter beyond the first, when the entry
    records its ``dof``); ``camera``, ``camera_validation``
    and ``camera_worst``, the camera-pose control's training improvement, validation
    improvement and worst validation component, and ``camera_concentration`` (its share in one
    camera, :mod:`toolkit.discovery.camera`) (0 when it was not confirmed)."""
    d = result if isinstance(result, dict) else result.to_dict()
    val, fit = [0.0], [0.0]
    cam = {"camera": 0.0, "camera_validation": 0.0, "camera_worst": 0.0, "camera_concentration": 0.0}
    for name, v in d["validation"].items():
        if name == "base":
            continue
        if v.get("control"):
            if name == "camera_pose":
                cam = {"camera": float(v["fit"]), "camera_validation": float(v["validation"]),
                       "camera_worst": float(v.get("worst", 0.0)), "camera_concentration": float(v.get("concentration", 0.0))}
            continue
        val.append(float(v["validation"]) - per_parameter * max(int(v.get("dof", 1)) - 1, 0))
        fit.append(float(v["fit"]))
    return {"validation": max(val), "fit": max(fit), **cam}


def calibrate(null_stats: Iterable[dict[str, float]], margin: float = 1.25, floors: Optional[dict[str, float]] = None,
              source: str = "", fit: float = 0.0, max_worsening: float = 0.10, per_parameter: float = 0.01) -> Thresholds:
    """Thresholds from the statistics of null scenes (:func:`null_statistics` of each).

    ``validation = margin x (largest null value) + floor`` (floor 0.01). ``camera`` likewise
    (floor 0.05), over the null scenes where the camera-pose control would otherwise have been
    reported (its validation improvement above the ``validation`` threshold or its improvement
    concentrated in one camera, and no component worse than ``max_worsening``). So no null scene of the calibration set is a false positive,
    with a margin for scenes outside it. ``fit`` and ``max_worsening`` are fixed (see the module
    docstring).
    """
    stats = list(null_stats)
    if not stats:
        raise ValueError("calibration needs at least one null scene")
    floors = {"validation": 0.01, "camera": 0.05, **(floors or {})}
    tau_val = margin * float(np.max([max(s["validation"], 0.0) for s in stats])) + floors["validation"]
    from toolkit.discovery.camera import CONCENTRATED

    cams = [s.get("camera", 0.0) for s in stats
            if (s.get("camera_validation", 0.0) > tau_val or s.get("camera_concentration", 0.0) >= CONCENTRATED)
            and s.get("camera_worst", 0.0) > -max_worsening]
    tau_cam = margin * float(max([0.0] + [max(c, 0.0) for c in cams])) + floors["camera"]
    return Thresholds(validation=tau_val, fit=fit, camera=tau_cam, max_worsening=max_worsening, per_parameter=per_parameter,
                      source=source or f"calibrated on {len(stats)} null scene(s), margin {margin}", n_null=len(stats))

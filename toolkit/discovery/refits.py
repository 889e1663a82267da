"""The confirmation refits of discovery: one candidate from the base refit, and the final refit.

:func:`refit_candidate` starts each candidate where the ranking pointed (the linear prediction,
scaled back to the best objective; the searched wall placement; the searched yield stress). The
extra acceleration is refitted a second time from the observed flight
(:func:`toolkit.discovery.kinematics.acceleration_start`) when the flight bends smoothly, and the
better of the two (training objective) is kept: a base fit that absorbed the force can make the
linear prediction point the wrong way. Air drag is likewise refitted a second time from the
drag rate of the observed track (:func:`toolkit.discovery.kinematics.drag_start`). The second
start replaces the first only when it lowers the training objective by more than
:data:`SECOND_START_MIN_GAIN`: two starts that end closer than that fit the data equally well,
and choosing by the smaller difference chose by noise (on the medium air-drag slide the drag
start ended 0.7 % lower and validated worse, 0.046 against 0.084, losing the name).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from toolkit.discovery.confirm import Refit, lm_refit
from toolkit.discovery.kinematics import acceleration_start, drag_start
from toolkit.discovery.library import LibraryModel

__all__ = ["refit_candidate", "final_refit", "start_point", "SECOND_START_MIN_GAIN"]

#: a second start must lower the training objective by more than this fraction to replace the
#: first (the coarse material search's ``MIN_GAIN``, the same reason: a flat valley)
SECOND_START_MIN_GAIN = 0.01


def start_point(lib: LibraryModel, base: Refit, score) -> np.ndarray:
    """The base refit with the candidate's strengths at the ranking's prediction, scaled back
    (1, 1/2, 1/4, 0) to the best objective: the linear prediction can overshoot."""
    best_q, best_L = base.q.copy(), base.objective
    for alpha in (1.0, 0.5, 0.25):
        q = base.q.copy()
        for n, v in score.predicted_strength.items():
            if n in lib.index_of:
                q[lib.index_of[n]] = alpha * v
        q = lib.clip(q)
        try:
            L = lib.objective(q)
        except Exception:  # a failing rollout: try a smaller step
            continue
        if L < best_L:
            best_q, best_L = q, L
    return best_q


def refit_candidate(lib: LibraryModel, plib: Optional[LibraryModel], state: dict, score, base: Refit, iterations: int,
                    motion=None) -> Refit:
    """Confirmation refit of one candidate, from the base refit's parameters.

    ``motion`` (:class:`~toolkit.discovery.kinematics.ObservedMotion`, optional): the clip's
    observed first phase; a smoothly bending flight gives the extra acceleration a second start."""
    name = score.name
    if name == "plastic_yield":
        q = plib.q0.copy()
        q[plib.idx(plib.base_names)] = base.q[lib.idx(lib.base_names)]
        q[plib.index_of["plastic_yield.log10_yield_stress"]] = state["yield"]
        rf = lm_refit(plib, q, plib.base_names + ["plastic_yield.log10_yield_stress"], name, iterations=iterations)
        rf.extra = {"yield_stress": float(10 ** rf.q[plib.index_of["plastic_yield.log10_yield_stress"]])}
        return rf
    if name == "wall":
        k, offset = state["wall"]
        lib.set_wall(k, offset)
        q = base.q.copy()
        q[lib.index_of["wall.strength"]] = (score.search or {}).get("strength", 1.0)
        if (score.search or {}).get("start") == "observed_v0":  # the placement scored from the observed v0
            for a, v in zip("xyz", score.search["v0"]):
                q[lib.index_of[f"v0.{a}"]] = v
        rf = lm_refit(lib, q, lib.base_names + ["wall.strength"], name, iterations=iterations)
        rf.extra = dict(score.search or {})
        return rf
    lib.assign(base.q)
    q = start_point(lib, base, score)
    free = lib.base_names + lib.params_of(name)
    rf = lm_refit(lib, q, free, name, iterations=iterations)
    second = {"extra_acceleration": (acceleration_start, "observed_flight"),
              "air_drag": (drag_start, "observed_drag_rate")}.get(name)
    if second is not None:
        start, label = second
        rf.extra = {"start": "prediction"}
        q2 = start(lib, base.q, motion)
        if q2 is not None:
            lib.assign(base.q)
            rf2 = lm_refit(lib, q2, free, name, iterations=iterations)
            rf2.extra = {"start": label, "other_start_objective": float(rf.objective)}
            if rf2.objective < (1.0 - SECOND_START_MIN_GAIN) * rf.objective:
                return rf2
            rf.extra["other_start_objective"] = float(rf2.objective)
    return rf


def final_refit(lib: LibraryModel, plib: Optional[LibraryModel], state: dict, name: str, seed: Refit, iterations: int) -> Refit:
    """The candidate refitted on every training frame from its confirmation refit."""
    target = seed.lib if seed.lib is not None else lib
    if name == "wall":
        k, offset = state["wall"]
        target.set_wall(k, offset)
    free = target.base_names + (target.params_of(name) if name != "plastic_yield" else ["plastic_yield.log10_yield_stress"])
    rf = lm_refit(target, seed.q, free, name, iterations=iterations)
    rf.extra = seed.extra
    if name == "plastic_yield":
        rf.extra = {"yield_stress": float(10 ** rf.q[target.index_of["plastic_yield.log10_yield_stress"]])}
    return rf

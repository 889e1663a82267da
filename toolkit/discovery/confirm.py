"""Confirmation: short refits of the top candidates with the base parameters refitted too.

Each refit is a bounded Levenberg-Marquardt minimization of the Gauss-Newton objective
``0.5 |r|^2`` (:meth:`~toolkit.discovery.library_objectives.LibraryObjectives.residuals`) over the base
parameters ``theta`` (initial velocity, optimized material parameters, a rigid shift of the
initial positions, optimized parameters of effects already in the model) and the candidate's
strengths, starting from the fitted base with the strengths at the ranking's prediction.
Jacobians are forward differences (one rollout per parameter, no backward pass), so a refit of
``k`` parameters costs about ``iterations x (k + 2)`` rollouts. The same refit with no
candidate (``"base"``) is the control every candidate is compared with: an improvement must
come from the candidate, not from refitting the base longer.

Each refit is then scored on data the fit did not use: the fit's own image loss
(``(1 - w) L1 + w (1 - SSIM)``) on the **held-out cameras** over the training frames.

Strength intervals: a profile interval from the curvature at the refit's optimum, the strengths
whose Gauss-Newton objective, with every other refitted parameter re-optimized, stays within
``PROFILE_TOLERANCE`` (relative) of the minimum: ``+- sqrt(2 tol L (H^-1)_jj)`` with
``H = J^T J`` over the refitted parameters (clipped to the strength's bounds).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from toolkit.discovery.library import LibraryModel

__all__ = ["Refit", "lm_refit", "held_out_loss", "PROFILE_TOLERANCE"]

log = logging.getLogger(__name__)

#: relative objective increase that defines the strength interval.
PROFILE_TOLERANCE = 0.01


@dataclass
class Refit:
    """One confirmation refit.

    Attributes:
        name: candidate name, or ``"base"`` for the control refit.
        q: the refitted library parameters.
        start_objective, objective: Gauss-Newton objective before and after (training data).
        held_out: the fit's image loss on the held-out cameras, training frames (mean over
            cameras and frames); ``nan`` without held-out cameras.
        strengths: ``{parameter: value}`` of the candidate at the optimum.
        intervals: ``{parameter: (low, high)}`` profile intervals of the strengths.
        iterations: Levenberg-Marquardt iterations done; ``rollouts`` rollouts used.
        seconds: wall-clock time.
        lib: the library model the refit belongs to (the plastic variant for ``plastic_yield``).
        extra: searched parameters (wall normal/offset, ...).
    """

    name: str
    q: np.ndarray
    start_objective: float
    objective: float
    held_out: float = float("nan")
    strengths: dict[str, float] = field(default_factory=dict)
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    iterations: int = 0
    rollouts: int = 0
    seconds: float = 0.0
    lib: Optional[LibraryModel] = field(default=None, repr=False)
    extra: Optional[dict] = None

    def to_dict(self) -> dict:
        return {"name": self.name, "start_objective": self.start_objective, "objective": self.objective,
                "held_out": self.held_out, "strengths": self.strengths,
                "intervals": {k: list(v) for k, v in self.intervals.items()}, "iterations": self.iterations,
                "rollouts": self.rollouts, "seconds": self.seconds, "extra": self.extra,
                "base": self.lib.describe(self.q, "base") if self.lib is not None else None}


def held_out_loss(lib: LibraryModel, q: np.ndarray, frames: Optional[Sequence[int]] = None) -> float:
    """Mean image loss of the held-out cameras over ``frames`` (default: the training frames)."""
    cams = lib.input.held_out_cameras
    if not cams:
        return float("nan")
    frames = lib.train_frames() if frames is None else list(frames)
    return float(lib.image_losses(q, frames, cams).mean())


def lm_refit(lib: LibraryModel, q_start: np.ndarray, free: Sequence[str], name: str, iterations: int = 6,
             lam: float = 1e-2, min_rel_improvement: float = 1e-4) -> Refit:
    """Bounded Levenberg-Marquardt on the Gauss-Newton objective over the parameters ``free``.

    Args:
        lib: the library model.
        q_start: starting library parameters (clipped to the bounds).
        free: names of the refitted parameters (base and the candidate's strengths).
        name: label of the refit.
        iterations: Jacobian evaluations at most.
        lam: initial Marquardt damping (relative to the diagonal of ``J^T J``).
        min_rel_improvement: stop when an accepted step improves the objective by less.

    Returns:
        The :class:`Refit` (``held_out`` filled in).
    """
    t0 = time.time()
    q = lib.clip(np.asarray(q_start, np.float64).copy())
    idx = np.array(lib.idx(free), dtype=int)
    steps = lib.steps[idx]
    lib.assign(q)
    r = lib.residuals(q).numpy()
    L = 0.5 * float(r @ r)
    L_start = L
    rollouts = 1
    J = None
    it = 0
    for it in range(1, iterations + 1):
        lib.assign(q)  # refresh the Chamfer assignment at the current point
        r = lib.residuals(q).numpy()
        L = 0.5 * float(r @ r)
        J = lib.jacobian(q, free, r0=_torch(r))
        rollouts += 1 + len(free)
        A = J.T @ J
        g = J.T @ r
        diag = np.maximum(np.diag(A), 1e-12 * max(np.diag(A).max(), 1e-30))
        accepted = False
        for _ in range(5):
            fixed = np.zeros(len(free), dtype=bool)
            for _pass in range(3):  # active set: parameters pushed against a bound stay there
                d = np.zeros(len(free))
                k = ~fixed
                if k.any():
                    M = A[np.ix_(k, k)] + lam * np.diag(diag[k])
                    d[k] = np.linalg.solve(M, -g[k])
                q_try = q.copy()
                q_try[idx] = q[idx] + d * steps
                clipped = lib.clip(q_try)
                hit = (np.abs(clipped[idx] - q_try[idx]) > 0) & ~fixed
                if not hit.any():
                    break
                fixed |= hit
            q_try = lib.clip(q_try)
            try:
                r_try = lib.residuals(q_try).numpy()
                L_try = 0.5 * float(r_try @ r_try)
            except Exception as exc:  # a step into a failing simulation: damp more
                log.info("refit %s: trial step failed (%s)", name, exc)
                L_try = math.inf
            rollouts += 1
            if L_try < L:
                improvement = (L - L_try) / max(L, 1e-30)
                q, L = q_try, L_try
                lam = max(lam / 3.0, 1e-6)
                accepted = True
                break
            lam *= 5.0
        if not accepted or improvement < min_rel_improvement:
            break
    refit = Refit(name=name, q=q, start_objective=L_start, objective=L, iterations=it, rollouts=rollouts, lib=lib)
    strength_names = [n for n in free if n not in lib.base_names]
    refit.strengths = {n: float(q[lib.index_of[n]]) for n in strength_names}
    if J is not None and strength_names:
        refit.intervals = _profile_intervals(lib, q, free, J, L)
    refit.held_out = held_out_loss(lib, q)
    refit.seconds = time.time() - t0
    return refit


def _profile_intervals(lib: LibraryModel, q: np.ndarray, free: Sequence[str], J: np.ndarray, L: float) -> dict:
    A = J.T @ J
    try:
        cov = np.linalg.pinv(A, rcond=1e-10)
    except np.linalg.LinAlgError:  # pragma: no cover
        return {}
    out = {}
    for k, n in enumerate(free):
        if n in lib.base_names:
            continue
        i = lib.index_of[n]
        half = math.sqrt(max(2.0 * PROFILE_TOLERANCE * L * cov[k, k], 0.0)) * lib.steps[i]
        out[n] = (float(max(q[i] - half, lib.low[i])), float(min(q[i] + half, lib.high[i])))
    return out


def _torch(r: np.ndarray):
    import torch

    return torch.as_tensor(r)

"""Probes of the uncertainty step (:mod:`toolkit.physics.uncertainty`): forward rollouts around the
estimate, the geometric loss as a residual vector with fixed matches, the one-sided interval test,
the MAP prior step and its guard on the fit's own loss."""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch


def _simulate(module, n: int) -> torch.Tensor:
    with torch.no_grad(), module.substeps_unlogged():  # probes, not the fit: no substep log lines
        _, pos = module.simulate(n, frozenset())
    return pos


def _nearest(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Index in ``b`` of each point of ``a``'s nearest neighbour."""
    return torch.cdist(a.double(), b.double()).argmin(dim=1)


class _Residuals:
    """The geometric loss as a residual vector with nearest neighbours fixed at the base state.

    ``sum(r**2)`` equals ``lambda_geometry * sum_f chamfer(surface_f, target_f) / F`` at the base.
    """

    def __init__(self, module, frames: list[int], positions: torch.Tensor):
        self.module, self.frames = module, frames
        self.targets = [module.input.surfaces[f].to(positions.device).double() for f in frames]
        self.scale = math.sqrt(module.lambda_geometry / len(frames))
        self.match = []
        for f, t in zip(frames, self.targets):
            s = positions[f][module.surface_index].double()
            self.match.append((_nearest(s, t), _nearest(t, s)))

    def __call__(self, positions: torch.Tensor) -> torch.Tensor:
        parts = []
        for f, t, (st, ts) in zip(self.frames, self.targets, self.match):
            s = positions[f][self.module.surface_index].double()
            parts.append((s - t[st]).reshape(-1) / math.sqrt(len(s)))
            parts.append((t - s[ts]).reshape(-1) / math.sqrt(len(t)))
        return torch.cat(parts) * self.scale


def _geometric_ssr(module, frames: list[int], positions: torch.Tensor) -> float:
    """The geometric loss with nearest neighbours re-matched (what the fit minimizes)."""
    r = _Residuals(module, frames, positions)(positions)
    return float((r ** 2).sum())


def _open_sides(module, params, frames, n, theta, sds, q, curvature, s2) -> tuple[dict[int, tuple[int, ...]], int]:
    """Sides of the interval of each nonlinear (log10, tanh) parameter the data do not bound.

    The linearization predicts that moving parameter k alone to an end of its interval raises the
    data term ``SSR / (2 s^2)`` by ``h^2 J_k.J_k / (2 s^2)``. A side where the simulated rise is
    below :data:`OPEN_SIDE_FRACTION` of that is open: e.g. a stiffness that a small sag bounds
    from below while any stiffer value looks the same. Parameters whose label is already
    ``not determined`` are skipped (their interval ends may be decades away). Returns
    ``({k: (-1 and/or +1)}, rollouts)``.
    """
    from toolkit.physics.uncertainty import LABELS, OPEN_SIDE_FRACTION, label_for

    found: dict[int, tuple[int, ...]] = {}
    rollouts = 0
    for p, v in zip(params, theta):
        p.set(float(v))
    base = _geometric_ssr(module, frames, _simulate(module, n))
    rollouts += 1
    for k, p in enumerate(params):
        h = q * sds[k]
        expected = h ** 2 * curvature[k] / (2 * s2)
        if p.space == "linear" or label_for(sds[k] / p.prior_std) == LABELS[2] or expected <= 0:
            continue
        sides = []
        for side in (-1, 1):
            p.set(float(theta[k] + side * h))
            try:
                rise = (_geometric_ssr(module, frames, _simulate(module, n)) - base) / (2 * s2)
            except Exception:  # the simulator rejects that state: the data do rule it out
                rise = math.inf
            rollouts += 1
            if rise < OPEN_SIDE_FRACTION * expected:
                sides.append(side)
        p.set(float(theta[k]))
        if sides:
            found[k] = tuple(sides)
    return found, rollouts


def _fit_loss_setup(module):
    """The stage, cameras and frames the fit's own loss is probed on: the last stage that optimizes
    the material (else the last stage), every training camera, every fitted frame after frame 0."""
    stages = list(module.stages)
    stage = next((s for s in reversed(stages) if "M" in s.groups), stages[-1])
    return stage, list(module.input.train_cameras), list(range(1, module.input.n_train))


def _relative_rise(losses: list[float]) -> float:
    rise = (losses[1] - losses[0]) / max(abs(losses[0]), 1e-30)
    return rise if math.isfinite(rise) else math.inf


def _fit_loss_rise(module, params, n: int, before: np.ndarray, after: np.ndarray) -> tuple[float, int]:
    """Relative change of the fit's own loss (:meth:`~toolkit.physics.InversePhysicsModule.losses`
    of the last stage that optimizes the material, else the last stage: image and geometric terms,
    every training camera, every fitted frame after frame 0) from ``before`` to ``after`` (raw
    parameters); the parameters are left at ``after``. Returns ``(rise, rollouts)``."""
    stage, cams, fit_frames = _fit_loss_setup(module)
    losses = []
    for th in (before, after):
        for p, v in zip(params, th):
            p.set(float(v))
        losses.append(module.probe_losses(_simulate(module, max([n, *fit_frames])), stage, cams, fit_frames)["total"])
    return _relative_rise(losses), 2


@torch.no_grad()
def _fine_fit_loss_rise(module, params, before: np.ndarray, after: np.ndarray) -> tuple[Optional[float], int]:
    """:func:`_fit_loss_rise` with both states simulated on a grid of half the fit's spacing
    (:func:`toolkit.physics.grid_check.shift_of_estimate`: each fit particle split into 8, its position the
    mean of its children, so the fit's Gaussians are rendered where the finer grid moves them).

    A rise the fit's grid shows but the finer one does not is the coarse grid's, not the data's.
    Returns ``(rise, rollouts)``; ``rise`` is None when the fine grid does not fit in memory or its
    rollout fails. The parameters are left at ``after``."""
    from toolkit.mpm.config import SimulationError
    from toolkit.physics.grid_check import shift_of_estimate

    stage, cams, fit_frames = _fit_loss_setup(module)
    losses, rollouts = [], 0
    for th in (before, after):
        for p, v in zip(params, th):
            p.set(float(v))
        try:
            shift = shift_of_estimate(module, max(fit_frames))
        except (SimulationError, RuntimeError):  # the fine grid does not fit, or its rollout fails
            for p, v in zip(params, after):
                p.set(float(v))
            return None, rollouts + 2
        rollouts += 2
        losses.append(module.probe_losses(shift["fine_positions"], stage, cams, fit_frames)["total"])
    return _relative_rise(losses), rollouts


def _map_step(module, params, frames, n, theta, grad_data, s2, H, prior_mean, prior_prec, free: list[int]):
    """One Gauss-Newton step on ``SSR / (2 s^2) + prior`` in the coordinates ``free`` (the others
    held), halved until the objective decreases."""

    def objective(th, positions=None):
        for p, v in zip(params, th):
            p.set(float(v))
        positions = positions if positions is not None else _simulate(module, n)
        return _geometric_ssr(module, frames, positions) / (2 * s2) + 0.5 * float(((th - prior_mean) ** 2 * prior_prec).sum())

    grad = grad_data / s2 + prior_prec * (theta - prior_mean)
    delta = np.zeros_like(theta)
    delta[free] = -np.linalg.solve(H[np.ix_(free, free)], grad[free])
    for p, v in zip(params, theta):
        p.set(float(v))
    f0 = objective(theta, _simulate(module, n))
    rollouts = 1
    for alpha in (1.0, 0.5, 0.25, 0.125):
        trial = theta + alpha * delta
        try:
            f = objective(trial)
        except Exception:  # a trial state the simulator rejects (e.g. too stiff): try a shorter step
            f = math.inf
        rollouts += 1
        if f < f0:
            moved = {p.name: float(d) for p, d in zip(params, alpha * delta)}
            return trial, {"taken": True, "scale": alpha, "objective": [f0, f], "moved_raw": moved}, rollouts
    for p, v in zip(params, theta):
        p.set(float(v))
    return theta, {"taken": False, "objective": [f0, f0]}, rollouts

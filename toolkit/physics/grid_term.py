"""The grid term of the intervals: where a grid of half the spacing would put the estimate.

The intervals of :mod:`toolkit.physics.uncertainty` measure the spread of the data around the
minimum of the fit's loss. A grid too coarse for the body moves that minimum: on the calibration
benchmark, stiff tosses fitted at twice the truth's dx ended 0.3-0.5 decades soft and sand 20
degrees low, with intervals that missed the truth (``docs/tutorials/uncertainty.md``). This module
turns the grid check (:mod:`toolkit.physics.grid_check`) into a parameter offset:

1. the estimate is simulated over the training frames on the fit's grid and on one of half the
   spacing (each particle split into 8); each fit particle's fine-grid position is the mean of its
   children, so the two trajectories have the same particles;
2. the geometric residuals of the uncertainty step (nearest neighbours fixed at the estimate) are
   evaluated on both: ``d = r(fine) - r(coarse)`` is what the finer grid changes in the data term;
3. the parameters that make the fit's grid absorb that change, to first order (one Gauss-Newton
   step with the uncertainty's prior, the fine grid's Jacobian taken equal to the fit's):

       delta = -(J^T J / s^2 + diag(1 / prior_std^2))^-1 J^T d / s^2.

``theta + delta`` estimates what the same fit would return on the finer grid. The uncertainty widens
each interval to cover both answers (the union of the interval around ``theta`` and the same one
around ``theta + delta``); the estimate itself stays the fit's. A grid that resolves the body gives
``delta`` within the statistical interval; one that does not moves it by more (the note says so).

What it does not do: the finer grid is itself not the continuum (for a truth simulated on a finer
grid still, or a real body, the offset of the remaining refinements is not included), and the step
is linear: a parameter whose effect saturates (a sand friction angle below the angle the spread
needs) can need more than one step. Cost: one rollout on the fit's grid and one on the fine grid
(8x the particles and nodes, about twice the substeps), shared with the grid check that the
pipeline runs after the fit.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

__all__ = ["grid_offsets", "GRID_SHIFT_SD"]

#: a grid of half the spacing that moves an estimate by more than this many posterior standard deviations
#: makes it grid-dependent: the parameter's note says so, and the finer-grid refit runs
#: (:func:`toolkit.grid_refinement.refinement_reason`)
GRID_SHIFT_SD = 1.0


@torch.no_grad()
def grid_offsets(module, residuals, jacobian: np.ndarray, s2: float, prior_precision: np.ndarray) -> tuple[Optional[np.ndarray], dict]:
    """The first-order parameter offset of a grid of half the spacing (see the module docstring).

    Args:
        module: the fitted :class:`~toolkit.physics.InversePhysicsModule`, at the estimate.
        residuals: the uncertainty step's residual function (positions ``(F, N, 3)`` -> ``(R,)``,
            nearest neighbours fixed at the estimate).
        jacobian: ``(R, K)`` derivatives of the residuals with respect to the K raw parameters,
            with fixed matches (not curvature-scaled).
        s2: residual variance of the uncertainty step.
        prior_precision: ``(K,)`` 1 / prior std^2 in the raw space.

    Returns:
        ``(delta, record)``: ``delta`` ``(K,)`` raw-space offsets, or None when the fine grid does
        not fit in memory or its rollout fails; ``record`` is the grid check's
        (:func:`toolkit.physics.grid_check.check_estimate`, or ``{"skipped": reason}``), which
        it keeps on the module for the pipeline's check to reuse.
    """
    from toolkit.physics.grid_check import check_estimate

    rec, shift = check_estimate(module)
    if shift is None:
        return None, rec
    d = (residuals(shift["fine_positions"]) - residuals(shift["positions"])).cpu().numpy()
    if not np.isfinite(d).all():
        return None, rec
    J = np.asarray(jacobian, dtype=np.float64)
    H = J.T @ J / s2 + np.diag(prior_precision)
    delta = -np.linalg.solve(H, J.T @ d / s2)
    return delta, rec

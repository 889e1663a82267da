"""Learning rates set by the parameters' transforms and the observed motion, not by a scene (issue #20).

The rule (also in ``docs/concepts.md``):

* material parameters: Adam steps in their raw (transformed) space,
  :func:`materials.base.default_lr`: 0.1 decade per iteration for ``log10`` parameters (E,
  viscosities, yield stress, bulk modulus), 1 % of the valid range for bounded ones (Poisson's
  ratio 0.0148, friction angle 0.89 degrees). A soft jelly and a stiff rubber take the same
  relative steps.
* the initial velocity v0 (m/s): :data:`VELOCITY_FRACTION` of the speed of the observed motion
  (:func:`observed_speed`: the fastest mean speed of the stage-0 surface's centroid from frame 0
  over the training frames), at least :data:`VELOCITY_FLOOR`. A body thrown at 3 m/s gets 10x the
  step of one drifting at 0.3 m/s, and a v0 that starts at zero (too few frames before contact
  for the ballistic estimate) can still reach the truth within the first stage.
* positions and appearance keep 3DGS's rates (:data:`toolkit.physics.module.DEFAULT_LEARNING_RATES`).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

__all__ = ["observed_speed", "velocity_rate", "VELOCITY_FRACTION", "VELOCITY_FLOOR"]

#: v0's Adam step as a fraction of the observed speed (per iteration, m/s per m/s)
VELOCITY_FRACTION = 0.05
#: smallest v0 step, m/s (the rate of a ~1 m scene; DESIGN: 1e-2 .. 5e-2)
VELOCITY_FLOOR = 0.02


def observed_speed(surfaces: Sequence[torch.Tensor], frame_dt: float, n_frames: int) -> float:
    """Fastest mean speed of the surface centroid from frame 0, m/s.

    Args:
        surfaces: per-frame (M_t, 3) surface points, metres (empty frames are skipped).
        frame_dt: seconds between frames.
        n_frames: frames to look at (the training frames).

    Returns:
        ``max_t |c_t - c_0| / (t frame_dt)`` over frames ``1 .. n_frames - 1``; 0 without two
        non-empty frames.
    """
    if not surfaces or len(surfaces[0]) == 0 or not frame_dt > 0:
        return 0.0
    c0 = surfaces[0].double().mean(0)
    best = 0.0
    for t in range(1, min(n_frames, len(surfaces))):
        if len(surfaces[t]):
            best = max(best, float((surfaces[t].double().mean(0) - c0).norm()) / (t * frame_dt))
    return best if math.isfinite(best) else 0.0


def velocity_rate(surfaces: Sequence[torch.Tensor], frame_dt: float, n_frames: int) -> float:
    """v0's default Adam learning rate, m/s: ``max(VELOCITY_FLOOR, VELOCITY_FRACTION * observed_speed)``."""
    return max(VELOCITY_FLOOR, VELOCITY_FRACTION * observed_speed(surfaces, frame_dt, n_frames))

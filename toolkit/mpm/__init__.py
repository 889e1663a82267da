"""Differentiable MLS-MPM in Warp (DESIGN section 4).

>>> from toolkit.mpm import MPMSimulator, SimConfig
"""

from toolkit.mpm.config import CFLError, GridTooLargeError, NaNError, OutOfDomainError, SimConfig, SimulationError
from toolkit.mpm.planning import SubstepPlan
from toolkit.mpm.simulator import GridSpec, MPMSimulator, RolloutResult, SimulationResult

__all__ = [
    "MPMSimulator",
    "SimConfig",
    "GridSpec",
    "SimulationResult",
    "RolloutResult",
    "SimulationError",
    "OutOfDomainError",
    "CFLError",
    "NaNError",
    "GridTooLargeError",
    "SubstepPlan",
]

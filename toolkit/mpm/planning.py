"""Host-side planning of a rollout: substeps from both stability limits, the grid memory bound,
and the integer ground layer.

* :func:`plan_substeps`: substeps per frame from the particle speed (``|v| dt <= cfl dx``) and the
  material's fastest wave at the *current* parameters (``c dt <= wave_cfl dx``, plus the explicit
  viscous limit for the Newtonian fluid), never fewer than ``SimConfig.substeps``.
* :func:`estimate_memory` / :func:`check_grid_memory`: bytes a rollout on a grid will take, and a
  one-line :class:`~toolkit.mpm.config.GridTooLargeError` before anything is allocated.
* :func:`ground_lattice_index`: which node layers are ground, decided in float64 on the dx lattice.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping, Optional

import numpy as np
import torch

from toolkit.mpm.config import GridTooLargeError, SimConfig

if TYPE_CHECKING:  # pragma: no cover
    from materials import Material
    from toolkit.mpm.simulator import GridSpec

__all__ = [
    "SubstepPlan",
    "plan_substeps",
    "quantize_substeps",
    "estimate_memory",
    "default_memory_limit",
    "check_grid_memory",
    "ground_lattice_index",
    "NODE_BYTES",
    "PARTICLE_BYTES",
]

#: bytes per grid node of one grid: mass (f32) + momentum (vec3) + velocity (vec3)
NODE_BYTES = 4 + 12 + 12
#: bytes per particle of one state: x, v (vec3), C, F (mat33), J (f32)
PARTICLE_BYTES = 12 + 12 + 36 + 36 + 4
#: the planned substeps take values ``substeps * 2^(k / STEPS_PER_OCTAVE)`` only
STEPS_PER_OCTAVE = 4


@dataclass(frozen=True)
class SubstepPlan:
    """Substeps per frame of one rollout and where they come from.

    Attributes:
        substeps: substeps per frame the rollout starts with.
        configured: ``SimConfig.substeps`` (the minimum).
        wave: substeps the material's fastest wave needs (``ceil(c frame_dt / (wave_cfl dx))``).
        viscous: substeps the explicit viscous limit needs (0 without one).
        speed: substeps the initial particle speed needs (``ceil(v frame_dt / (cfl dx))``).
        floor: substeps kept from earlier dt halvings (0 if none).
        wave_speed: the fastest wave speed over the particles, m/s.
        max_speed: the initial speed used for ``speed`` (largest ``|v0|`` plus one frame of
            gravity), m/s.
        needed: ``max(wave, viscous, speed)`` before rounding and the cap.
        capped: the plan hit ``SimConfig.max_substeps``.
    """

    substeps: int
    configured: int
    wave: int
    viscous: int
    speed: int
    floor: int
    wave_speed: float
    max_speed: float
    needed: int
    capped: bool = False

    @property
    def reason(self) -> str:
        """Which limit set the substeps: ``configured``, ``wave``, ``viscous``, ``speed`` or ``halving``."""
        if self.floor >= self.substeps and self.floor > self.configured:
            return "halving"
        if self.substeps <= self.configured:
            return "configured"
        limits = {"wave": self.wave, "viscous": self.viscous, "speed": self.speed}
        return max(limits, key=limits.get)


def quantize_substeps(needed: int, configured: int) -> int:
    """Smallest ``ceil(configured * 2^(k/4))`` (k >= 0 integer) that is >= ``needed``.

    Few distinct values keep the number of captured CUDA graphs small and make a fit's
    discretization change in a few steps rather than at every iteration.
    """
    if needed <= configured:
        return configured
    k = math.ceil(STEPS_PER_OCTAVE * math.log2(needed / configured) - 1e-9)
    while True:
        n = math.ceil(configured * 2.0 ** (k / STEPS_PER_OCTAVE) - 1e-9)
        if n >= needed:
            return n
        k += 1


def _columns(material: "Material", params: Any) -> dict[str, np.ndarray]:
    """Physical parameters as ``{name: (R,) float64 array}`` from a dict, a (P,) or an (R, P) tensor."""
    if isinstance(params, Mapping):
        full = material.complete(params)
        return {k: np.asarray([v], np.float64) for k, v in full.items()}
    rows = torch.as_tensor(params).detach().reshape(-1, len(material.params)).to("cpu", torch.float64).numpy()
    return {n: rows[:, i] for i, n in enumerate(material.param_names)}


def plan_substeps(material: "Material", config: SimConfig, params: Any, v0: Any = None, floor: int = 0,
                  wave_cfl: Optional[float] = None, gravity: Any = None) -> SubstepPlan:
    """Substeps per frame for a rollout of ``material`` at ``params`` from initial velocity ``v0``.

    Args:
        material: the simulated material (its ``wave_speed`` and ``viscous_dt`` hooks).
        config: ``dx``, ``frame_dt``, ``density``, ``gravity``, ``cfl``, ``wave_cfl``, ``substeps``,
            ``auto_substeps``, ``max_substeps``.
        params: physical parameters: a dict, a (P,) or an (N, P) tensor (the fastest row counts).
        v0: (3,) or (N, 3) initial velocity, m/s (``None``: at rest).
        floor: substeps kept from earlier dt halvings.
        wave_cfl: overrides ``config.wave_cfl``.
        gravity: (3,) m/s^2 of this rollout (e.g. a learnt one); default ``config.gravity``.

    Returns:
        a :class:`SubstepPlan`. Without ``config.auto_substeps`` its ``substeps`` is
        ``max(config.substeps, floor)``; otherwise the largest need, rounded up by
        :func:`quantize_substeps`, at least the floor, at most ``config.max_substeps``.
    """
    cfg = config
    courant = cfg.wave_cfl if wave_cfl is None else float(wave_cfl)
    cols = _columns(material, params)
    c = float(np.max(material.wave_speed(cols, cfg.density)))
    vdt = float(np.min(material.viscous_dt(cols, cfg.density, cfg.dx)))
    wave = math.ceil(c * cfg.frame_dt / (courant * cfg.dx) - 1e-9) if c > 0 else 0
    viscous = math.ceil(cfg.frame_dt / vdt - 1e-9) if math.isfinite(vdt) and vdt > 0 else 0
    speed_v = 0.0
    if v0 is not None:
        v = torch.as_tensor(v0).detach().reshape(-1, 3)
        speed_v = float(v.norm(dim=1).max()) if v.numel() else 0.0
    g = cfg.gravity if gravity is None else torch.as_tensor(gravity).detach().reshape(3).cpu().double().numpy()
    speed_v += float(np.linalg.norm(np.asarray(g, np.float64))) * cfg.frame_dt
    speed = math.ceil(speed_v * cfg.frame_dt / (cfg.cfl * cfg.dx) - 1e-9)
    needed = max(wave, viscous, speed)
    if not cfg.auto_substeps:
        return SubstepPlan(max(cfg.substeps, floor), cfg.substeps, wave, viscous, speed, floor, c, speed_v, needed)
    n = max(quantize_substeps(needed, cfg.substeps), floor)
    capped = n > cfg.max_substeps
    n = min(n, max(cfg.max_substeps, floor))
    return SubstepPlan(n, cfg.substeps, wave, viscous, speed, floor, c, speed_v, needed, capped)


# ---------------------------------------------------------------------- memory
def estimate_memory(dims, n_particles: int, n_frames: int, config: SimConfig, differentiable: bool) -> int:
    """Bytes a rollout on a grid of ``dims`` nodes will allocate (an upper estimate).

    Forward: one grid and two particle states (double buffering) plus the per-frame outputs.
    Differentiable: also ``checkpoint_every`` grids and ``checkpoint_every + 1`` states, all with
    gradient buffers (one per substep of a taped chunk), and the chunk-start checkpoints.
    """
    nodes = int(np.prod(np.asarray(dims, np.int64), dtype=np.int64))
    n = int(n_particles)
    total = nodes * NODE_BYTES + 2 * n * PARTICLE_BYTES + 2 * (n_frames + 1) * n * 12
    if differentiable:
        chunk = config.checkpoint_every
        total += chunk * nodes * NODE_BYTES * 2 + (chunk + 1) * n * PARTICLE_BYTES * 2
        n_chunks = n_frames * math.ceil(config.substeps / chunk)
        total += n_chunks * n * PARTICLE_BYTES
    return int(total)


def _available_ram() -> int:
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except Exception:  # pragma: no cover - psutil missing
        try:
            return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            return 8 << 30


def default_memory_limit(device: str, held: int = 0) -> tuple[int, str]:
    """``(bytes, description)``: half the free memory of a CUDA device, or half the available RAM,
    counting ``held`` bytes (buffers the caller will free) as free."""
    if str(device).startswith("cuda"):
        import warp as wp

        free = int(wp.get_device(device).free_memory)
        try:  # memory torch's caching allocator holds but does not use is free for our purpose
            dev = torch.device(str(device))
            free += int(torch.cuda.memory_reserved(dev) - torch.cuda.memory_allocated(dev))
        except Exception:  # pragma: no cover - torch without CUDA
            pass
        return (free + held) // 2, f"half the free memory of {device}"
    return (_available_ram() + held) // 2, "half the available RAM"


def _gb(b: float) -> str:
    return f"{b / 1e9:.3g} GB" if b >= 1e8 else f"{b / 1e6:.3g} MB"


def check_grid_memory(spec: "GridSpec", n_particles: int, n_frames: int, config: SimConfig, device: str,
                      differentiable: bool, growing: bool = False, held: int = 0) -> int:
    """Raise :class:`GridTooLargeError` (one line) if a rollout on ``spec`` would exceed the memory limit.

    Nothing is allocated. ``held``: bytes the caller already holds and will free (they count as free
    memory for the default limit). Returns the estimate in bytes.
    """
    need = estimate_memory(spec.dims, n_particles, n_frames, config, differentiable)
    if config.memory_limit is not None:
        limit, what = int(config.memory_limit), "SimConfig.memory_limit"
    else:
        limit, what = default_memory_limit(device, held)
        what = f"SimConfig.memory_limit = None: {what}"
    if need <= limit:
        return need
    lo = [round(o, 3) for o in spec.origin]
    hi = [round(u, 3) for u in spec.upper]
    dims = " x ".join(str(d) for d in spec.dims)
    kind = "a differentiable rollout" if differentiable else "a rollout"
    cause = ("the particles left the grid and growing it around them" if growing else
             "the domain (SimConfig.domain, or the particles' box swept along v0 and gravity plus SimConfig.margin)")
    raise GridTooLargeError(
        f"grid too large: dx = {spec.dx:g} m over the domain {lo} .. {hi} m is {dims} nodes; {kind} would need about "
        f"{_gb(need)}, over the limit {_gb(limit)} ({what}) on {device}; {cause} sets its size: use a larger "
        "SimConfig.dx, a smaller domain or initial velocity, or raise SimConfig.memory_limit",
        frame=0, substep=0,
    )


# ---------------------------------------------------------------------- ground
def ground_lattice_index(height: float, dx: float) -> int:
    """Global lattice index of the highest node layer with ``y <= height`` (nodes at ``n dx``).

    Float64 with a 1e-6-cell tolerance, so a ground on a node layer is that layer however the
    grid's origin rounds in float32.
    """
    return int(math.floor(float(height) / float(dx) + 1e-6))

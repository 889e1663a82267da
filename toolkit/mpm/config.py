"""Simulation settings and the errors the simulator reports."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal, Optional, Sequence

__all__ = [
    "SimConfig",
    "SimulationError",
    "OutOfDomainError",
    "CFLError",
    "NaNError",
    "GridTooLargeError",
    "BOUNDARY_MODES",
    "CPU_GRAPH_MAX_NODES",
    "captures_graphs",
]

BOUNDARY_MODES = ("sticky", "slip", "separate")


class SimulationError(RuntimeError):
    """A rollout could not continue. ``frame`` and ``substep`` (global, 0-based) say where;
    ``points`` holds the particle positions when the failure was detected (or None)."""

    def __init__(self, message: str, frame: int | None = None, substep: int | None = None, points=None):
        super().__init__(message)
        self.frame = frame
        self.substep = substep
        self.points = points


class OutOfDomainError(SimulationError):
    """A particle left the bounded grid."""


class CFLError(SimulationError):
    """A particle moved more than ``cfl * dx`` in one substep."""


class NaNError(SimulationError):
    """A particle position or velocity became NaN or infinite."""


class GridTooLargeError(SimulationError):
    """The grid (and the buffers a rollout needs) would not fit the memory limit; raised before any allocation."""


@dataclass
class SimConfig:
    """Settings of the MLS-MPM simulator (DESIGN section 4).

    Attributes:
        dx: grid spacing, metres.
        substeps: substeps per frame; ``dt = frame_dt / substeps``. With ``auto_substeps`` this is
            the minimum: a rollout uses more when the material's wave speed or the initial speed
            asks for it (see :meth:`MPMSimulator.plan_substeps`).
        frame_dt: time between output frames, seconds (1/24 for 24 fps).
        density: kg/m^3, fixed (under gravity only E/rho is identifiable).
        particle_volume: m^3 per particle; ``None`` means ``(dx/2)^3``.
        gravity: default gravity, m/s^2 (the simulator's inputs may override it).
        ground_height: y of the ground plane (normal +y), metres; ``None`` disables it. The ground
            nodes are the grid layers with ``y <= ground_height`` decided by an integer layer index
            computed in float64 (:meth:`GridSpec.ground_layer`), so the result does not depend on
            where the grid starts.
        boundary: ground contact mode: ``sticky`` (v = 0), ``slip`` (normal velocity removed) or
            ``separate`` (approaching normal velocity removed).
        domain: ``(lower, upper)`` corners of the grid in metres, or ``None`` to size it from the
            particles' initial positions, the ballistic trajectory and ``margin``. Corners are
            snapped to multiples of dx, so results do not depend on the domain size.
        margin: metres added around the auto-sized domain.
        out_of_domain: what happens when a particle leaves the grid: ``grow`` (default) enlarges
            an auto-sized grid around the particles and reruns the rollout (the lattice is snapped
            to dx, so the result is the one a larger grid would have given from the start; with an
            explicit ``domain`` it acts as ``error``); ``error`` raises :class:`OutOfDomainError`;
            ``clamp`` keeps particles inside (domain faces act as separating walls).
        cfl: a substep with ``|v| dt > cfl * dx`` for some particle is a CFL violation.
        graphs: capture chains of substeps as Warp graphs and replay them (removes the Python
            launch overhead that dominates small problems): ``"auto"`` (on CUDA unless
            ``deterministic``; on the CPU when the grid has at most :data:`CPU_GRAPH_MAX_NODES`
            nodes), True, False. A captured deterministic CUDA launch keeps its sort-reduce
            scratch (about 100 bytes per particle per substep) for the graph's lifetime, so a
            whole frame's graphs held 45 GB for a 49k-particle truth at 306 substeps per frame.
        auto_substeps: plan the substeps of every rollout from the material's wave speed at the
            rollout's parameters (``wave_cfl``) and from the initial particle speed (``cfl``); the
            plan is at least ``substeps`` and is rounded up to ``substeps * 2^(k/4)``, so it takes
            few distinct values. ``False`` uses ``substeps`` as given.
        wave_cfl: the fastest material wave (elastic P-wave; see ``Material.wave_speed``) may
            cross at most ``wave_cfl * dx`` per substep.
        max_substeps: the planned substeps per frame are capped here (with a warning).
        auto_dt_halving: on a CFL or NaN failure, double the substeps and rerun (up to
            ``max_dt_halvings`` times) instead of raising. The doubled count is kept for every
            later rollout of the same simulator (a fit does not retry the coarse step).
        max_dt_halvings: see above.
        memory_limit: bytes the grid and the rollout's buffers may take; a larger estimate raises
            :class:`GridTooLargeError` before anything is allocated. ``None`` (default): half the
            free memory of the CUDA device, or half the available RAM on CPU.
        checkpoint_every: substeps per checkpoint chunk for gradients (state kept at chunk starts,
            the chunk recomputed on the backward pass). Chunks never straddle frames.
        keep_tapes: keep every chunk's taped forward pass of a differentiable rollout, so the
            backward pass runs adjoints only instead of recomputing each chunk first (one forward
            pass less per gradient; memory grows with all substeps instead of one chunk; see
            :mod:`toolkit.mpm.tapes`): ``"auto"`` (default) when those buffers take at most half
            the memory limit, True, False. Results are bit-identical either way.
        deterministic: Warp's deterministic mode for float atomics on CUDA (reproducible, slower).
    """

    dx: float = 0.02
    substeps: int = 100
    frame_dt: float = 1.0 / 24.0
    density: float = 1000.0
    particle_volume: Optional[float] = None
    gravity: Sequence[float] = (0.0, -9.8, 0.0)
    ground_height: Optional[float] = 0.0
    boundary: Literal["sticky", "slip", "separate"] = "sticky"
    domain: Optional[tuple[Sequence[float], Sequence[float]]] = None
    margin: float = 0.2
    out_of_domain: Literal["grow", "error", "clamp"] = "grow"
    cfl: float = 0.4
    graphs: bool | str = "auto"
    auto_substeps: bool = True
    wave_cfl: float = 0.5
    max_substeps: int = 20000
    auto_dt_halving: bool = False
    max_dt_halvings: int = 3
    memory_limit: Optional[float] = None
    checkpoint_every: int = 25
    keep_tapes: bool | str = "auto"
    deterministic: bool = False

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field, value and what is expected."""

        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(f"SimConfig: {msg}")

        need(self.dx > 0 and math.isfinite(self.dx), f"dx must be a positive length in metres, got {self.dx!r}")
        need(isinstance(self.substeps, int) and self.substeps >= 1, f"substeps must be an integer >= 1, got {self.substeps!r}")
        need(self.frame_dt > 0, f"frame_dt must be > 0 seconds, got {self.frame_dt!r}")
        need(self.density > 0, f"density must be > 0 kg/m^3, got {self.density!r}")
        need(self.particle_volume is None or self.particle_volume > 0, f"particle_volume must be > 0 m^3, got {self.particle_volume!r}")
        need(len(tuple(self.gravity)) == 3, f"gravity must have 3 components, got {self.gravity!r}")
        need(self.boundary in BOUNDARY_MODES, f"boundary must be one of {BOUNDARY_MODES}, got {self.boundary!r}")
        need(self.out_of_domain in ("grow", "error", "clamp"), f"out_of_domain must be 'grow', 'error' or 'clamp', got {self.out_of_domain!r}")
        need(0 < self.cfl <= 1.0, f"cfl must be in (0, 1], got {self.cfl!r}")
        need(self.margin >= 0, f"margin must be >= 0 metres, got {self.margin!r}")
        need(isinstance(self.checkpoint_every, int) and self.checkpoint_every >= 1, f"checkpoint_every must be an integer >= 1, got {self.checkpoint_every!r}")
        need(self.graphs in (True, False, "auto"), f"graphs must be True, False or 'auto', got {self.graphs!r}")
        need(self.keep_tapes in (True, False, "auto"), f"keep_tapes must be True, False or 'auto', got {self.keep_tapes!r}")
        need(self.max_dt_halvings >= 0, f"max_dt_halvings must be >= 0, got {self.max_dt_halvings!r}")
        need(0 < self.wave_cfl <= 1.0, f"wave_cfl must be in (0, 1], got {self.wave_cfl!r}")
        need(isinstance(self.max_substeps, int) and self.max_substeps >= self.substeps,
             f"max_substeps must be an integer >= substeps ({self.substeps}), got {self.max_substeps!r}")
        need(self.memory_limit is None or self.memory_limit > 0,
             f"memory_limit must be a positive number of bytes or None (auto), got {self.memory_limit!r}")
        if self.domain is not None:
            lo, hi = self.domain
            need(len(lo) == 3 and len(hi) == 3, f"domain must be ((x0, y0, z0), (x1, y1, z1)), got {self.domain!r}")
            need(all(h - l >= 4 * self.dx for l, h in zip(lo, hi)), f"domain must be at least 4 dx wide on every axis, got {self.domain!r}")

    @property
    def dt(self) -> float:
        """Substep length, seconds."""
        return self.frame_dt / self.substeps

    @property
    def volume(self) -> float:
        """Volume per particle, m^3."""
        return self.particle_volume if self.particle_volume is not None else (0.5 * self.dx) ** 3

    @property
    def mass(self) -> float:
        """Mass per particle, kg."""
        return self.density * self.volume

    def to_dict(self) -> dict:
        d = asdict(self)
        d["gravity"] = list(self.gravity)
        if self.domain is not None:
            d["domain"] = [list(self.domain[0]), list(self.domain[1])]
        return d


#: ``graphs="auto"`` captures CPU rollouts on grids of at most this many nodes. Measured on one
#: core of a 2-core development machine (``benchmarks/cpu_graphs.py``: a 6-frame rollout and its
#: gradient; repeated runs differ by up to 30 %): captured is 1.1-1.7x faster on 4k nodes and
#: 1.4-1.7x on 8k, 0.8-1.1x near 13k, and 0.2-0.7x on 162k nodes, where the particles' box is a
#: small part of the grid. A discovery test scene (about 5.7k nodes): base fit 29.8 -> 25.8 s,
#: discovery 51.5 -> 26.4 s, with bit-identical results (a chain is captured on its second use;
#: see :mod:`toolkit.mpm.graph_cache`).
CPU_GRAPH_MAX_NODES = 8192


def captures_graphs(mode: bool | str, device: str, deterministic: bool, nodes: int | None = None) -> bool:
    """Whether a simulator captures its substep chains as Warp graphs (``SimConfig.graphs``).

    ``"auto"`` captures on CUDA unless ``deterministic``: a deterministic CUDA launch allocates
    scratch for its sort-reduce, and a captured graph keeps every launch's scratch alive as long as
    the graph, so the memory grows with the substeps per frame (45 GB for a 49k-particle truth at
    306 substeps per frame, against under 1 GB launched one by one). On the CPU, where a kernel runs
    on one thread and ``deterministic`` allocates nothing, it captures when the grid has at most
    :data:`CPU_GRAPH_MAX_NODES` nodes (``nodes``; ``None``: not known yet, no capture). A CPU
    replay skips the Python cost of packing each launch's arguments, but a captured grid update
    visits every node, where launched one by one it visits only the box the particles reach; on a
    small grid the first saving is larger. ``True``/``False`` are obeyed.
    """
    if mode != "auto":
        return bool(mode)
    if str(device).startswith("cuda"):
        return not deterministic
    return nodes is not None and nodes <= CPU_GRAPH_MAX_NODES

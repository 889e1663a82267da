"""The simulator's data: the bounded grid's geometry, the results of a rollout, and the per-substep
particle and grid buffers (Warp arrays)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import warp as wp

from toolkit.mpm.planning import ground_lattice_index

__all__ = ["GridSpec", "SimulationResult", "RolloutResult", "ParticleBuffers", "GridBuffers", "Arena"]


@dataclass(frozen=True)
class GridSpec:
    """A bounded grid: node (i, j, k) at ``origin + (i, j, k) * dx``, ``dims`` nodes per axis."""

    origin: tuple[float, float, float]
    dims: tuple[int, int, int]
    dx: float

    @property
    def upper(self) -> tuple[float, float, float]:
        return tuple(o + (n - 1) * self.dx for o, n in zip(self.origin, self.dims))

    @property
    def n_nodes(self) -> int:
        return int(np.prod(self.dims))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each point's whole stencil lies inside the grid."""
        X = (np.asarray(points, np.float64) - np.asarray(self.origin)) / self.dx
        return np.all((X >= 0.5) & (X < np.asarray(self.dims) - 1.5), axis=1)

    def ground_layer(self, height: float) -> int:
        """Index ``j`` of the highest node layer with ``y <= height`` (ground nodes are ``j' <= j``).

        Decided in float64 on the dx lattice (``floor((height - origin_y) / dx + 1e-6)``), never from
        a float32 node position, so the ground layers do not depend on where the grid starts. May be
        negative (the ground lies below the grid) or ``>= dims[1]``.
        """
        return ground_lattice_index(height, self.dx) - int(round(self.origin[1] / self.dx))

    def covers(self, other: "GridSpec") -> bool:
        return all(
            so <= oo + 1e-9 and so + (sn - 1) * self.dx >= oo + (on - 1) * self.dx - 1e-9
            for so, sn, oo, on in zip(self.origin, self.dims, other.origin, other.dims)
        )


@dataclass
class SimulationResult:
    """Differentiable simulation output.

    Attributes:
        positions: (T+1, N, 3) float32, world frame, metres; index t is time ``t * frame_dt``
            (index 0 is the initial state).
        velocities: (T+1, N, 3) float32, m/s.
        substeps: substeps per frame actually used (larger than configured after dt halving).
    """

    positions: torch.Tensor
    velocities: torch.Tensor
    substeps: int


@dataclass
class RolloutResult:
    """Forward-only output (torch, no gradients): like :class:`SimulationResult`, plus
    ``F`` (T+1, N, 3, 3) (elastic) deformation gradients and ``J`` (T+1, N) the tracked volume ratio
    when asked for (``J`` is tracked by fluids only and stays 1 for solids, whose volume ratio is
    ``det F``), and ``tracers`` (T+1, M, 3) positions of passive tracer points when given."""

    positions: torch.Tensor
    velocities: torch.Tensor
    substeps: int
    F: Optional[torch.Tensor] = None
    J: Optional[torch.Tensor] = None
    tracers: Optional[torch.Tensor] = None


class Arena:
    """Typed Warp arrays carved out of one zero-initialized device buffer.

    Clearing the arena (:meth:`zero_`) is one memset however many arrays it holds, which keeps a
    captured graph short: a taped chunk of 25 substeps has ~170 gradient and grid arrays to clear.

    Args:
        items: ``(shape, dtype)`` of each array, in order.
        device: Warp device.
    """

    _ALIGN = 256  # bytes; every view starts on a boundary this large

    def __init__(self, items: list[tuple[tuple[int, ...], type]], device: str):
        offsets, total = [], 0
        for shape, dtype in items:
            offsets.append(total)
            nbytes = int(np.prod(shape)) * wp.types.type_size_in_bytes(dtype)
            total += -(-nbytes // self._ALIGN) * self._ALIGN
        self.base = wp.zeros(max(total // 4, 1), dtype=wp.float32, device=device)
        self.views = [
            wp.array(ptr=self.base.ptr + off, dtype=dtype, shape=shape, device=device, capacity=total - off)
            for off, (shape, dtype) in zip(offsets, items)
        ]

    def zero_(self) -> None:
        self.base.zero_()


class ParticleBuffers:
    """Per-particle arrays of one substep: x, v (vec3), C, F (mat33), J (float)."""

    SPEC = (("x", wp.vec3), ("v", wp.vec3), ("C", wp.mat33), ("F", wp.mat33), ("J", wp.float32))

    def __init__(self, n: int, device: str, requires_grad: bool = False):
        self.x = wp.zeros(n, dtype=wp.vec3, device=device, requires_grad=requires_grad)
        self.v = wp.zeros(n, dtype=wp.vec3, device=device, requires_grad=requires_grad)
        self.C = wp.zeros(n, dtype=wp.mat33, device=device, requires_grad=requires_grad)
        self.F = wp.zeros(n, dtype=wp.mat33, device=device, requires_grad=requires_grad)
        self.J = wp.zeros(n, dtype=float, device=device, requires_grad=requires_grad)

    def arrays(self) -> tuple:
        return (self.x, self.v, self.C, self.F, self.J)

    def assign(self, other: "ParticleBuffers") -> None:
        for dst, src in zip(self.arrays(), other.arrays()):
            wp.copy(dst, src)

    def zero_grad(self) -> None:
        for a in self.arrays():
            if a.grad is not None:
                a.grad.zero_()


class GridBuffers:
    """Grid arrays of one substep: mass m (float), momentum mv and velocity v (vec3)."""

    SPEC = (("m", wp.float32), ("mv", wp.vec3), ("v", wp.vec3))

    def __init__(self, dims: tuple[int, int, int], device: str, requires_grad: bool = False):
        self.m = wp.zeros(dims, dtype=float, device=device, requires_grad=requires_grad)
        self.mv = wp.zeros(dims, dtype=wp.vec3, device=device, requires_grad=requires_grad)
        self.v = wp.zeros(dims, dtype=wp.vec3, device=device, requires_grad=requires_grad)

    def clear(self) -> None:
        self.m.zero_()
        self.mv.zero_()

    def zero_grad(self) -> None:
        for a in (self.m, self.mv, self.v):
            if a.grad is not None:
                a.grad.zero_()


class TapedChunk:
    """The buffers of one taped chunk of ``length`` substeps: ``length + 1`` particle states and
    ``length`` grids, with every gradient in one :class:`Arena` and every grid's mass and momentum
    in another, so a chunk's recompute and adjoint start from two memsets instead of ~13 per substep.
    """

    def __init__(self, n: int, dims: tuple[int, int, int], length: int, device: str):
        self.states = [ParticleBuffers(n, device) for _ in range(length + 1)]
        self.grids = [GridBuffers(dims, device) for _ in range(length)]
        self.grid_values = Arena([(dims, dt) for _ in self.grids for name, dt in GridBuffers.SPEC if name != "v"], device)
        it = iter(self.grid_values.views)
        for g in self.grids:
            g.m, g.mv = next(it), next(it)
        arrays = [a for st in self.states for a in st.arrays()] + [a for g in self.grids for a in (g.m, g.mv, g.v)]
        self.grads = Arena([(tuple(a.shape), a.dtype) for a in arrays], device)
        for a, view in zip(arrays, self.grads.views):
            a.grad = view

    def clear(self) -> None:
        """Zero every gradient and every grid's mass and momentum (two memsets)."""
        self.grads.zero_()
        self.grid_values.zero_()

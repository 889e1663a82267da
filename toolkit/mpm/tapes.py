"""Kept tapes: a differentiable rollout's forward pass recorded chunk by chunk, so that its backward
pass runs the adjoints only instead of recomputing every chunk first (issue #16).

Chunked checkpointing (:mod:`toolkit.mpm.autograd`) keeps one particle state per chunk of
``SimConfig.checkpoint_every`` substeps and recomputes each chunk on a ``wp.Tape`` before its
adjoint: memory ``O(chunk)``, one extra forward pass per gradient. When every chunk's buffers fit
(``SimConfig.keep_tapes``), the forward pass instead runs each chunk on its own
:class:`~toolkit.mpm.state.TapedChunk` under a tape and keeps it; the backward pass replays the
tapes' adjoints in reverse. The kernels and their order are the same, so states and gradients
are bit-identical to the recomputing path (tested); memory is ``O(all substeps)``.

A kept tape is valid until the simulator runs its next forward pass (any :meth:`simulate` or
:meth:`rollout`): its buffers and input arrays are reused then. A backward pass that finds its
tapes overwritten (two ``simulate`` calls before one ``backward``) falls back to recomputing from
the checkpoints, which every forward pass keeps.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np
import warp as wp

from toolkit.mpm.planning import NODE_BYTES, PARTICLE_BYTES, default_memory_limit
from toolkit.mpm.state import TapedChunk

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.mpm.graph_cache import GraphCache
    from toolkit.mpm.simulator import MPMSimulator

__all__ = ["KeptTapes", "tape_bytes"]


def tape_bytes(dims: Sequence[int], n_particles: int, lengths: Sequence[int]) -> int:
    """Bytes of one :class:`~toolkit.mpm.state.TapedChunk` per chunk of ``lengths`` substeps on a
    grid of ``dims`` nodes: ``length + 1`` particle states and ``length`` grids, all with gradients."""
    nodes = int(np.prod(np.asarray(dims, np.int64), dtype=np.int64))
    return int(sum((k + 1) * n_particles * PARTICLE_BYTES * 2 + k * nodes * NODE_BYTES * 2 for k in lengths))


class KeptTapes:
    """The taped chunks of a simulator's differentiable forward passes (one per chunk index, reused).

    Args:
        sim: the simulator whose ``_substep`` the chunks run.
        n: particles.
    """

    def __init__(self, sim: "MPMSimulator", n: int):
        self.sim = sim
        self.n = n
        self.pools: dict[int, TapedChunk] = {}
        self.tapes: dict[int, wp.Tape] = {}
        #: chunk indices whose tape was recorded by a captured graph (held by the graph cache)
        self.captured: set[int] = set()
        self.generation = -1
        self.inputs: Optional[tuple] = None

    @staticmethod
    def fit(sim: "MPMSimulator", n: int, chunks: Sequence[tuple[int, int, int]], held: int = 0) -> bool:
        """Whether the taped chunks of a rollout fit: ``SimConfig.keep_tapes`` True always,
        False never, ``"auto"`` when their bytes are at most half the memory limit
        (``SimConfig.memory_limit``, default half the free device memory or available RAM;
        ``held``: bytes of kept tapes already allocated, which count as free)."""
        mode = sim.config.keep_tapes  # validated: True, False or "auto"
        if mode != "auto":
            return bool(mode)
        need = tape_bytes(sim.grid.dims, n, [length for _, _, length in chunks])
        limit = sim.config.memory_limit
        if limit is None:
            limit = default_memory_limit(sim.device, held)[0]
        return need <= 0.5 * limit

    def held_bytes(self) -> int:
        return tape_bytes(self.sim.grid.dims, self.n, [len(p.grids) for p in self.pools.values()])

    def _pool(self, index: int, length: int) -> TapedChunk:
        pool = self.pools.get(index)
        if pool is None or len(pool.grids) != length:
            pool = self.pools[index] = TapedChunk(self.n, self.sim.grid.dims, length, self.sim.device)
        return pool

    def start(self, generation: int, inputs: tuple) -> None:
        """A new forward pass: ``inputs`` are its Warp parameter, gravity and effect arrays."""
        self.generation = generation
        self.inputs = inputs
        self.tapes = {}
        self.captured = set()

    def forward_chunk(self, index: int, state, args: tuple, first: int, length: int, status,
                      graphs: Optional["GraphCache"]) -> None:
        """Run chunk ``index`` (``length`` substeps from frame-local substep ``first``) from
        ``state`` on its own buffers under a tape, and write the end state back into ``state``."""
        sim = self.sim
        pool = self._pool(index, length)

        def body() -> wp.Tape:
            pool.clear()
            pool.states[0].assign(state)
            tape = wp.Tape()
            with tape:
                for k in range(length):
                    sim._substep(pool.states[k], pool.states[k + 1], pool.grids[k], *args, first + k, status,
                                 grid_mode="cleared")
            state.assign(pool.states[length])
            # the status flags and the CFL speed carry no gradient: every chunk writes them, and a
            # kept tape's read marks on them would flag the next chunk's writes as corrupting it
            # (wp.config.verify_autograd_array_access)
            for flags in (status, sim._violation_speed()):
                flags.mark_init()
            return tape

        key = None if graphs is None else ("taped", index, first, length, id(state.x), id(pool.states[0].x), id(args[0]),
                                           args[1], id(args[2]), id(args[3]), args[4])
        if key is None or not graphs.should_capture(key):
            self.tapes[index] = body()
            self.captured.discard(index)
            return
        if key not in graphs:
            with sim.capture() as capture:
                tape = body()
            graphs[key] = (capture.graph, tape)
        graph, tape = graphs[key]
        wp.capture_launch(graph)
        self.tapes[index] = tape
        self.captured.add(index)

    def backward_chunk(self, index: int, carry: Sequence, graphs: Optional["GraphCache"]) -> None:
        """The adjoint of chunk ``index``: ``carry`` holds the gradient of its end state on entry
        and of its start state on return."""
        pool, tape = self.pools[index], self.tapes[index]
        length = len(pool.grids)

        def body() -> None:
            tape.backward(grads={a: g for a, g in zip(pool.states[length].arrays(), carry)})
            for dst, src in zip(carry, pool.states[0].arrays()):
                wp.copy(dst, src.grad)

        # only a captured forward's tape is used again; a tape recorded launch by launch is new
        # on every pass, and its id may be a dead tape's
        key = None if graphs is None or index not in self.captured else ("tape_backward", index, id(tape), id(carry[0]))
        if key is None or not graphs.should_capture(key):
            body()
            return
        if key not in graphs:
            with self.sim.capture() as capture:
                body()
            graphs[key] = (capture.graph, tape)  # the entry keeps the tape, so its id stays its own
        wp.capture_launch(graphs[key][0])


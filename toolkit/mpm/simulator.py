"""The MLS-MPM simulator: bounded grid, substep loop, checks, and chunked checkpointing.

:class:`MPMSimulator` runs on ``cpu`` or ``cuda`` with the same code. Two entry points:

* :meth:`MPMSimulator.simulate` takes torch tensors and returns per-frame positions and
  velocities; it is differentiable (``torch.autograd``) with respect to the initial positions,
  the initial velocity, the material parameters, gravity and the effect parameters.
* :meth:`MPMSimulator.rollout` is the same forward pass without gradients, and can also return
  the deformation gradients (for energy diagnostics).

Gradients through time use chunked checkpointing: the forward pass keeps the particle state at
the start of every chunk of ``SimConfig.checkpoint_every`` substeps (chunks never straddle a
frame); the backward pass walks the chunks in reverse, restores the chunk's start state,
recomputes the chunk on a ``wp.Tape`` (each substep with its own particle and grid buffers, as
Warp's adjoints read the arrays' current contents) and runs its adjoint. Memory is
``O(chunk x (particles + grid))`` for the buffers plus ``O(n_chunks x particles)`` for the
checkpoints. When every chunk's buffers fit (``SimConfig.keep_tapes``), the forward pass records
each chunk on its own tape instead and the backward pass skips the recompute
(:mod:`toolkit.mpm.tapes`).
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np
import torch
import warp as wp

from materials import Material, get_material
from toolkit.mpm.config import CFLError, NaNError, OutOfDomainError, SimConfig, captures_graphs
from toolkit.mpm.graph_cache import GraphCache
from toolkit.mpm.planning import SubstepPlan, check_grid_memory, ground_lattice_index, plan_substeps
from toolkit.mpm.state import GridBuffers, GridSpec, ParticleBuffers, RolloutResult, SimulationResult, TapedChunk
from toolkit.mpm.effects import Effect, EffectContext, get_effect
if TYPE_CHECKING:  # pragma: no cover
    from toolkit.mpm.tapes import KeptTapes
from toolkit.mpm.kernels import (
    NO_FLAG,
    compose_effects,
    advect_tracers,
    init_state,
    make_g2p_kernel,
    make_grid_update_kernel,
    make_p2g_kernel,
    store_frame,
)

__all__ = ["MPMSimulator", "GridSpec", "SimulationResult", "RolloutResult", "SubstepPlan"]

log = logging.getLogger(__name__)

_KERNEL_CACHE: dict[tuple, object] = {}


class MPMSimulator:
    """Differentiable MLS-MPM with a registered material and optional physical effects.

    Args:
        material: a registered material name (``"neo_hookean"``, ...) or a :class:`Material`.
        config: simulation settings; defaults to :class:`SimConfig()`.
        effects: effects applied in the grid update, in order (names or instances).
        device: ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.

    Example:
        >>> sim = MPMSimulator("neo_hookean", SimConfig(substeps=50), device="cpu")
        >>> out = sim.simulate(x0, v0=torch.tensor([1.0, 0.0, 0.0]), params=sim.material.pack({"E": 1e5}), n_frames=10)
        >>> out.positions.shape  # (11, N, 3)
    """

    def __init__(
        self,
        material: str | Material = "neo_hookean",
        config: SimConfig | None = None,
        effects: Sequence[str | Effect] = (),
        device: str = "cpu",
    ):
        self.material = get_material(material)
        self.config = config if config is not None else SimConfig()
        self.config.validate()
        self.effects: list[Effect] = [get_effect(e) for e in effects]
        self.device = str(wp.get_device(device))
        self._grid: Optional[GridSpec] = None
        self._ground_j = -1  # the grid's highest ground layer (GridSpec.ground_layer), set with the grid
        self._buffers: dict = {}
        # captured substep chains; they reference the buffers above, so any reallocation clears them
        self._graphs: GraphCache = self._new_graphs()
        offsets = np.cumsum([0] + [len(e.params) for e in self.effects]).tolist()
        self._effect_offsets = offsets[:-1]
        self.n_effect_params = offsets[-1]
        #: substeps per frame below which no rollout goes once a dt halving was needed (kept for a fit)
        self.substeps_floor = 0
        #: number of dt halvings done so far (each one logged)
        self.halvings = 0
        #: the plan of the latest rollout
        self.last_plan: Optional[SubstepPlan] = None
        self._differentiable = False
        self._memory_checked: Optional[tuple] = None  # (grid, differentiable, bytes) last found to fit
        #: forward passes run so far; a kept tape belongs to one of them (toolkit.mpm.tapes)
        self.generation = 0
        ground = self.config.ground_height
        if ground is not None and any(e.registry_name == "ground_friction" for e in self.effects) and self.config.boundary == "sticky":
            log.warning("ground_friction has no effect with the 'sticky' boundary (infinite friction); use 'slip' or 'separate'")

    # ------------------------------------------------------------------ parameters
    @property
    def effect_param_names(self) -> list[str]:
        """Flat names ``<effect>.<param>`` in the order of the effect parameter vector."""
        return [f"{e.name}.{p.name}" for e in self.effects for p in e.params]

    def pack_effects(self, values: dict[str, dict[str, float]] | None = None) -> torch.Tensor:
        """Effect parameters as a flat (E,) float32 tensor, from ``{effect: {param: value}}``."""
        values = dict(values or {})
        unknown = set(values) - {e.name for e in self.effects}
        if unknown:
            raise ValueError(f"no effect(s) {sorted(unknown)} in this simulator; its effects are {[e.name for e in self.effects]}")
        flat: list[float] = []
        for e in self.effects:
            given = values.get(e.name, {})
            e.validate(given)
            flat.extend(float(given.get(p.name, p.default)) for p in e.params)
        return torch.tensor(flat, dtype=torch.float32, device=self._torch_device)

    def unpack_effects(self, flat: torch.Tensor) -> dict[str, dict[str, float]]:
        vals = flat.detach().cpu().reshape(-1).tolist()
        out: dict[str, dict[str, float]] = {}
        for e, off in zip(self.effects, self._effect_offsets):
            out[e.name] = {p.name: vals[off + i] for i, p in enumerate(e.params)}
        return out

    @contextlib.contextmanager
    def substep_plan_restored(self):
        """Rollouts inside leave :attr:`substeps_floor` and :attr:`halvings` as they were: a dt
        halving a probe needed (a coarse-search candidate, the grid check's rollout) is not kept
        for the fit's later rollouts."""
        floor, halvings = self.substeps_floor, self.halvings
        try:
            yield
        finally:
            self.substeps_floor, self.halvings = floor, halvings

    @contextlib.contextmanager
    def stream(self):
        """Context for the simulator's Warp work on CUDA (no-op on CPU).

        Work is ordered after everything already queued on torch's current stream, and torch's
        stream waits for it on exit. Torch's legacy default stream cannot be captured into a
        graph, so in that case Warp works on its own stream, synchronized with events.
        """
        if not self.device.startswith("cuda"):
            yield
            return
        torch_stream = torch.cuda.current_stream(self._torch_device)
        wp_torch_stream = wp.stream_from_torch(torch_stream)
        if torch_stream.cuda_stream != 0:
            with wp.ScopedStream(wp_torch_stream):
                yield
            return
        if getattr(self, "_work_stream", None) is None:
            self._work_stream = wp.Stream(self.device)
        work = self._work_stream
        work.wait_stream(wp_torch_stream)
        try:
            with wp.ScopedStream(work):
                yield
        finally:
            wp_torch_stream.wait_stream(work)

    @property
    def _torch_device(self) -> torch.device:
        return torch.device("cpu") if self.device == "cpu" else torch.device(self.device)

    def stable_substeps(self, params: dict[str, float] | torch.Tensor, courant: float | None = None) -> int:
        """Substeps per frame that the material alone needs at ``params`` (no rounding, no minimum).

        The fastest wave (:meth:`Material.wave_speed`: elastic P-wave ``sqrt((lambda + 2 mu) / rho)``,
        ``sqrt((kappa + 4 mu / 3) / rho)`` for the viscoplastic fluid, ``sqrt(7 kappa / rho)`` for the
        Newtonian one) crosses at most ``courant * dx`` per substep (default ``SimConfig.wave_cfl``), and
        the explicit viscous limit (:meth:`Material.viscous_dt`) holds. A guide, not a guarantee.
        """
        cfg = self.config
        plan = plan_substeps(self.material, cfg, params, wave_cfl=courant)
        return max(1, plan.wave, plan.viscous)

    def plan_substeps(self, params: dict[str, float] | torch.Tensor | None = None, v0=None, gravity=None) -> SubstepPlan:
        """The substeps a rollout with these parameters, initial velocity (m/s) and gravity (m/s^2,
        default ``config.gravity``) will use.

        See :func:`toolkit.mpm.planning.plan_substeps`; includes the halvings this simulator has kept.
        """
        if params is None:
            params = self.material.defaults()
        return plan_substeps(self.material, self.config, params, v0, floor=self.substeps_floor, gravity=gravity)

    # ------------------------------------------------------------------ grid
    def grid_for(self, x0: np.ndarray, v0: np.ndarray | None = None, n_frames: int = 0, gravity=None) -> GridSpec:
        """The grid used for a rollout from ``x0`` ((N, 3) positions, m; only their bounding box
        matters, so the box's two corners give the same grid).

        With ``SimConfig.domain`` set, that box. Otherwise the particles' bounding box, swept
        along the ballistic path ``v0 t + g t^2 / 2`` over the rollout (1.25x the speed, floored
        at the ground), plus ``margin``. Corners are snapped to multiples of dx, and a grid once
        made only grows, so a changing v0 during a fit does not change the discretization.
        """
        cfg = self.config
        dx = cfg.dx
        if cfg.domain is not None:
            lo = np.asarray(cfg.domain[0], np.float64)
            hi = np.asarray(cfg.domain[1], np.float64)
        else:
            x0 = np.asarray(x0, np.float64)
            lo, hi = x0.min(0), x0.max(0)
            if n_frames > 0:
                T = n_frames * cfg.frame_dt
                v = np.zeros(3) if v0 is None else np.asarray(v0, np.float64).reshape(-1, 3).mean(0)
                g = np.asarray(cfg.gravity if gravity is None else gravity, np.float64)
                ts = np.linspace(0.0, T, 33)
                path = 1.25 * v[None] * ts[:, None] + 0.5 * g[None] * ts[:, None] ** 2
                lo = lo + np.minimum(path.min(0), 0.0)
                hi = hi + np.maximum(path.max(0), 0.0)
            lo = lo - cfg.margin
            hi = hi + cfg.margin
            if cfg.ground_height is not None:
                lo[1] = max(lo[1], cfg.ground_height - 4 * dx)
                lo[1] = min(lo[1], x0[:, 1].min() - 4 * dx)
                hi[1] = max(hi[1], cfg.ground_height + 8 * dx)
        origin = np.floor(lo / dx) * dx
        dims = np.ceil((hi - origin) / dx).astype(int) + 1
        dims = np.maximum(dims, 4)
        spec = GridSpec(tuple(float(o) for o in origin), tuple(int(d) for d in dims), float(dx))
        if cfg.domain is None and self._grid is not None and self._grid.covers(spec):
            return self._grid
        if cfg.domain is None and self._grid is not None:
            # grow to the union, keeping the lattice
            lo_u = np.minimum(np.asarray(self._grid.origin), origin)
            hi_u = np.maximum(np.asarray(self._grid.upper), np.asarray(spec.upper))
            origin = np.round(lo_u / dx) * dx
            dims = np.round((hi_u - origin) / dx).astype(int) + 1
            spec = GridSpec(tuple(float(o) for o in origin), tuple(int(d) for d in dims), float(dx))
        return spec

    def set_grid(self, spec: GridSpec) -> None:
        """Fix the grid (e.g. restored from a checkpoint)."""
        if abs(spec.dx - self.config.dx) > 1e-12:
            raise ValueError(f"grid dx {spec.dx} differs from SimConfig.dx {self.config.dx}")
        off = [o / spec.dx - round(o / spec.dx) for o in spec.origin]
        if max(abs(o) for o in off) > 1e-4:
            raise ValueError(
                f"grid origin {list(spec.origin)} is not on the dx = {spec.dx} lattice (every corner must be a multiple "
                "of dx, as MPMSimulator.grid_for makes it): the ground layers and the result would depend on it"
            )
        if spec != self._grid:
            self._grid = spec
            self._buffers = {}
            self._graphs = self._new_graphs()
            ground = self.config.ground_height
            self._ground_j = spec.ground_layer(ground) if ground is not None else -1

    @property
    def grid(self) -> Optional[GridSpec]:
        return self._grid

    # ------------------------------------------------------------------ kernels
    def _kernels(self):
        cfg = self.config
        key = (
            self.material.cache_key(),
            tuple(e.cache_key() for e in self.effects),
            cfg.ground_height,
            cfg.dx,
            cfg.boundary,
            cfg.out_of_domain,
            cfg.deterministic,
        )
        if key not in _KERNEL_CACHE:
            ground_top = None
            if cfg.ground_height is not None:
                # half a cell above the highest ground layer: the same nodes as the kernel's integer test
                ground_top = (ground_lattice_index(cfg.ground_height, cfg.dx) + 0.5) * cfg.dx
            ctx = EffectContext(ground_height=cfg.ground_height, boundary=cfg.boundary, dx=cfg.dx, ground_top=ground_top)
            funcs = [e.build(off, ctx) for e, off in zip(self.effects, self._effect_offsets)]
            effects = compose_effects(funcs)
            grid_args = (effects, cfg.ground_height is not None, cfg.boundary, cfg.out_of_domain == "clamp", cfg.deterministic)
            _KERNEL_CACHE[key] = (
                make_p2g_kernel(self.material.warp_update(), cfg.deterministic),
                make_grid_update_kernel(*grid_args),
                make_g2p_kernel(cfg.deterministic),
                make_grid_update_kernel(*grid_args, clear_after=True),
            )
        return _KERNEL_CACHE[key]

    # ------------------------------------------------------------------ buffers
    def _pool(self, n: int, chunk: int) -> TapedChunk:
        """Per-substep states and grids for one taped chunk (allocated once, reused)."""
        key = ("pool", n, chunk)
        if key not in self._buffers:
            self._buffers = {k: v for k, v in self._buffers.items() if k[0] != "pool"}
            self._graphs = self._new_graphs()
            self._buffers[key] = TapedChunk(n, self._grid.dims, chunk, self.device)
        return self._buffers[key]

    def _pingpong(self, n: int):
        key = ("pingpong", n)
        if key not in self._buffers:
            self._graphs = self._new_graphs()
            self._buffers[key] = (
                ParticleBuffers(n, self.device),
                ParticleBuffers(n, self.device),
                GridBuffers(self._grid.dims, self.device),
            )
        return self._buffers[key]

    def _persistent(self, key: tuple, make):
        if key not in self._buffers:
            self._graphs = self._new_graphs()
            self._buffers[key] = make()
        return self._buffers[key]

    def _inputs(self, params: torch.Tensor, gravity: torch.Tensor, effect_params: torch.Tensor,
                grads: tuple[bool, bool, bool] = (False, False, False)):
        """Persistent Warp copies of one call's inputs: material parameters (R, P), gravity and the
        effect parameters.

        Captured graphs bake in array addresses, so the per-call torch tensors are copied into
        simulator-owned arrays that every graph references. ``grads`` says which of the three get a
        gradient buffer: an input without one costs its adjoint nothing, while one with a gradient
        receives an atomic add from every particle (parameters) or grid node (gravity, effects)
        that reads it, so callers pass per-particle parameters when they want their gradient.
        """
        shape = tuple(params.shape)
        n_eff = int(effect_params.shape[0])
        grads = tuple(bool(g) for g in grads)
        p, g, e = self._persistent(("inputs", shape, n_eff, grads), lambda: (
            wp.zeros(shape, dtype=float, device=self.device, requires_grad=grads[0]),
            wp.zeros(1, dtype=wp.vec3, device=self.device, requires_grad=grads[1]),
            wp.zeros(max(n_eff, 1), dtype=float, device=self.device, requires_grad=grads[2]),
        ))
        wp.copy(p, wp.from_torch(params.detach().contiguous(), dtype=wp.float32))
        wp.copy(g, wp.from_torch(gravity.detach().reshape(1, 3).contiguous(), dtype=wp.vec3))
        if n_eff:
            wp.copy(e, wp.from_torch(effect_params.detach().contiguous(), dtype=wp.float32))
        return p, g, e

    def _status(self):
        status = self._persistent(("status",), lambda: wp.zeros(4, dtype=wp.int32, device=self.device))
        status.fill_(NO_FLAG)
        self._violation_speed().zero_()
        return status

    def _violation_speed(self):
        """float[1]: the largest particle speed (m/s) in the first substep that violated the CFL limit."""
        return self._persistent(("violation_speed",), lambda: wp.zeros(1, dtype=float, device=self.device))

    # ------------------------------------------------------------------ substeps
    def _substep(self, s_in: ParticleBuffers, s_out: ParticleBuffers, grid: GridBuffers, params, per_particle: int,
                 gravity, effect_params, dt: float, step: int, status, tracers=None, grid_mode: str = "clear") -> None:
        """One substep s_in -> s_out; ``step`` is the frame-local substep index written to the flags.

        ``grid_mode`` says who clears the grid's mass and momentum before the P2G scatter:
        ``"clear"``: two memsets here; ``"cleared"``: the caller did (a taped chunk clears all its
        grids at once), and the grid stays filled for the adjoint; ``"reuse"`` (forward-only
        passes with one grid): it is clear on entry and the grid update clears it again as it
        reads it (except with tracers, whose advection reads the mass afterwards).
        """
        p2g, grid_update, g2p, grid_update_clearing = self._kernels()
        cfg = self.config
        spec = self._grid
        origin = wp.vec3(*spec.origin)
        n = s_in.x.shape[0]
        if grid_mode == "reuse" and tracers is None:
            grid_update = grid_update_clearing
        elif grid_mode != "cleared":
            grid.clear()
        wp.launch(
            p2g,
            dim=n,
            inputs=[s_in.x, s_in.v, s_in.C, s_in.F, s_in.J, params, per_particle, s_out.F, s_out.J, grid.m, grid.mv,
                    origin, spec.dx, dt, cfg.volume, cfg.mass, status, step],
            device=self.device,
        )
        offset, dims = self._update_box(s_in, tracers)
        wp.launch(
            grid_update,
            dim=dims,
            inputs=[grid.m, grid.mv, grid.v, gravity, effect_params, origin, spec.dx, dt, self._ground_j, offset],
            device=self.device,
        )
        if tracers is not None:
            wp.launch(advect_tracers, dim=tracers[0].shape[0], inputs=[tracers[0], grid.m, grid.v, tracers[1], origin, spec.dx, dt],
                      device=self.device)
        wp.launch(
            g2p,
            dim=n,
            inputs=[s_in.x, grid.v, s_out.x, s_out.v, s_out.C, origin, spec.dx, dt, cfg.cfl * spec.dx / dt,
                    int(cfg.out_of_domain == "clamp"), status, self._violation_speed(), step],
            device=self.device,
        )

    def _update_box(self, s_in: ParticleBuffers, tracers) -> tuple:
        """``(offset, dims)`` of the grid nodes this substep's grid update visits.

        On the CPU (one thread walks every node) only the box the particles' P2G stencils can
        reach, plus one node of slack against round-off: a falling body fills a few percent of
        its domain, so this is most of the grid update's cost. The particles' positions are read
        in place (host memory). On CUDA, with tracers (their advection reads the whole grid), under
        graph capture or with a non-finite position, the whole grid.
        """
        spec = self._grid
        full = (wp.vec3i(0, 0, 0), spec.dims)
        if self.device != "cpu" or tracers is not None or self.use_graphs():
            return full
        x = s_in.x.numpy()
        if x.shape[0] == 0:
            return full
        # per column: numpy's axis-0 reduction of an (N, 3) array is several times slower
        lo = np.array([x[:, k].min() for k in range(3)], dtype=np.float64)
        hi = np.array([x[:, k].max() for k in range(3)], dtype=np.float64)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            return full
        origin, dims = np.asarray(spec.origin, dtype=np.float64), np.asarray(spec.dims)
        # a particle's stencil is base .. base + 2 with base = floor((x - origin) / dx - 0.5)
        # (clipped as floats: a particle far outside the domain must not overflow the cast; the
        # kernels clamp a base into [0, dims - 3], and so does the box)
        first = np.clip(np.floor((lo - origin) / spec.dx - 0.5) - 1, 0, dims - 3).astype(np.int64)
        last = np.clip(np.floor((hi - origin) / spec.dx - 0.5) + 3, 2, dims - 1).astype(np.int64)
        return wp.vec3i(*(int(v) for v in first)), tuple(int(v) for v in last - first + 1)

    # ------------------------------------------------------------------ checks
    def _check_status(self, status, frame: int, substeps: int, state: ParticleBuffers) -> None:
        """Raise for the first failure flagged during ``frame`` (flags hold frame-local substeps)."""
        flags = status.numpy()
        oob = flags[0] if self.config.out_of_domain != "clamp" else NO_FLAG
        first = min(int(oob), int(flags[1]), int(flags[2]))
        if first == NO_FLAG:
            return
        # report the failure that happened first: a particle that left the grid or moved too fast
        # is what later turns into NaNs
        s = frame * substeps + min(first, substeps - 1)
        where = f"frame {s // substeps} (substep {s % substeps} of {substeps}, global substep {s})"
        if int(oob) == first:
            x = state.x.numpy()
            outside = ~self._grid.contains(x)
            idx = np.nonzero(outside & np.all(np.isfinite(x), axis=1))[0]
            lo, hi = self._grid.origin, self._grid.upper
            detail = f"{int(outside.sum())} particle(s), e.g. particle {idx[0]} at {np.round(x[idx[0]], 4).tolist()}," if len(idx) else "particles"
            raise OutOfDomainError(
                f"{detail} left the simulation domain [{np.round(lo, 3).tolist()}, {np.round(hi, 3).tolist()}] "
                f"at {where}; enlarge SimConfig.domain or SimConfig.margin, or set out_of_domain='clamp'",
                frame=s // substeps, substep=s, points=x,
            )
        cfg = self.config
        plan = self.last_plan
        wave = f"; the material's wave speed is {plan.wave_speed:.3g} m/s" if plan is not None and plan.wave_speed > 0 else ""
        if int(flags[1]) == first:
            vmax = float(self._violation_speed().numpy()[0])
            limit = cfg.cfl * cfg.dx * substeps / cfg.frame_dt
            stable = max(math.ceil(1.25 * vmax * cfg.frame_dt / (cfg.cfl * cfg.dx)), 2 * substeps,
                         plan.wave if plan is not None else 0)
            raise CFLError(
                f"CFL violation at {where}: particles moved at up to {vmax:.3g} m/s, more than {cfg.cfl} dx = "
                f"{cfg.cfl * cfg.dx:.3g} m per substep (limit {limit:.3g} m/s at {substeps} substeps per frame{wave}); "
                f"about {stable} substeps per frame would be stable: set SimConfig.substeps >= {stable} or enable auto_dt_halving",
                frame=s // substeps, substep=s,
            )
        stable = max(2 * substeps, plan.wave if plan is not None else 0)
        raise NaNError(
            f"NaN or inf in particle positions/velocities at {where}; the material may be too stiff for dt = "
            f"{cfg.frame_dt / substeps:.3g} s ({substeps} substeps per frame{wave}): try SimConfig.substeps >= {stable} "
            "or enable auto_dt_halving",
            frame=s // substeps, substep=s,
        )

    # ------------------------------------------------------------------ inputs
    def _prepare(self, x0, v0, params, gravity, effect_params, n_frames, differentiable: bool = False):
        dev = self._torch_device
        if not isinstance(x0, torch.Tensor):
            x0 = torch.as_tensor(np.asarray(x0), dtype=torch.float32)
        if x0.ndim != 2 or x0.shape[1] != 3 or x0.shape[0] == 0:
            raise ValueError(f"x0 must have shape (N, 3) with N >= 1, got {tuple(x0.shape)}")
        n = x0.shape[0]
        v0 = torch.zeros(3) if v0 is None else torch.as_tensor(v0, dtype=torch.float32)
        if v0.shape == (3,):
            v0 = v0.to(dev).expand(n, 3)
        elif tuple(v0.shape) != (n, 3):
            raise ValueError(f"v0 must have shape (3,) or (N, 3) = ({n}, 3), got {tuple(v0.shape)}")
        if params is None:
            params = self.material.pack(None)
        params = torch.as_tensor(params, dtype=torch.float32)
        if params.ndim == 1:
            params = params[None]
        if params.ndim != 2 or params.shape[1] != len(self.material.params) or params.shape[0] not in (1, n):
            raise ValueError(
                f"params for {self.material.name!r} must have shape (P,), (1, P) or (N, P) with P = "
                f"{len(self.material.params)} ({', '.join(self.material.param_names)}) and N = {n}, got {tuple(params.shape)}"
            )
        self.material.check_tensor(params)
        gravity = torch.as_tensor(self.config.gravity if gravity is None else gravity, dtype=torch.float32)
        if gravity.shape != (3,):
            raise ValueError(f"gravity must have shape (3,), got {tuple(gravity.shape)}")
        if effect_params is None:
            effect_params = self.pack_effects()
        effect_params = torch.as_tensor(effect_params, dtype=torch.float32).reshape(-1)
        if effect_params.shape[0] != self.n_effect_params:
            raise ValueError(
                f"effect_params must have {self.n_effect_params} values ({', '.join(self.effect_param_names) or 'no effects'}), "
                f"got {effect_params.shape[0]}"
            )
        if not isinstance(n_frames, int) or n_frames < 0:
            raise ValueError(f"n_frames must be an integer >= 0, got {n_frames!r}")
        # one small transfer instead of the particles: the bounding box (NaN/inf propagate into it),
        # the mean initial velocity, gravity and the effects
        with torch.no_grad():
            lo, hi = torch.aminmax(x0.detach(), dim=0)
            on = lambda t: t.detach().to(device=x0.device, dtype=torch.float32).reshape(-1)  # noqa: E731
            summary = torch.cat([lo, hi, on(v0.mean(0)), on(v0.abs().amax(0)), on(gravity), on(effect_params)])
            summary = summary.cpu().numpy().astype(np.float64)
        lo_np, hi_np, v_mean = summary[0:3], summary[3:6], summary[6:9]
        for name, part in (("x0", summary[0:6]), ("v0", summary[6:12]), ("gravity", summary[12:15]),
                           ("effect_params", summary[15:])):
            if not np.isfinite(part).all():
                raise ValueError(f"{name} contains NaN or inf values")
        spec = self.grid_for(np.stack([lo_np, hi_np]), v_mean, n_frames, summary[12:15])
        self._check_memory(spec, n, n_frames, differentiable)
        self.set_grid(spec)
        if not spec.contains(np.stack([lo_np, hi_np])).all():
            xs = x0.detach().cpu().numpy()  # only on failure: name a particle that lies outside
            outside = ~spec.contains(xs)
            i = int(np.nonzero(outside)[0][0])
            raise OutOfDomainError(
                f"{int(outside.sum())} initial particle(s) lie outside the simulation domain "
                f"[{np.round(spec.origin, 3).tolist()}, {np.round(spec.upper, 3).tolist()}], e.g. particle {i} at "
                f"{np.round(xs[i], 4).tolist()}; enlarge SimConfig.domain",
                frame=0, substep=0,
            )
        to = lambda t: t.to(device=dev, dtype=torch.float32).contiguous()  # noqa: E731
        return to(x0), to(v0), to(params), to(gravity), to(effect_params)

    # ------------------------------------------------------------------ public API
    def simulate(
        self,
        x0: torch.Tensor,
        v0: torch.Tensor | None = None,
        params: torch.Tensor | None = None,
        gravity: torch.Tensor | None = None,
        effect_params: torch.Tensor | None = None,
        n_frames: int = 1,
    ) -> SimulationResult:
        """Differentiable rollout.

        Args:
            x0: (N, 3) initial positions, metres.
            v0: (3,) one initial velocity for all particles, or (N, 3); m/s. Default zero.
            params: material parameters in physical units, (P,) or (N, P) in
                ``material.param_names`` order (see ``material.pack``); default the material's
                defaults.
            gravity: (3,) m/s^2; default ``config.gravity``.
            effect_params: (E,) flat effect parameters (``pack_effects``); default the effects'
                defaults.
            n_frames: number of frames to simulate after the initial one.

        Returns:
            :class:`SimulationResult` with positions and velocities of shape (n_frames + 1, N, 3).
        """
        from toolkit.mpm.autograd import SimulateFunction

        x0t, v0t, pt, gt, et = self._prepare(x0, v0, params, gravity, effect_params, n_frames, differentiable=True)
        holder: dict = {}
        pos, vel = SimulateFunction.apply(self, n_frames, holder, x0t, v0t, pt, gt, et)
        return SimulationResult(pos, vel, holder["substeps"])

    @torch.no_grad()
    def rollout(
        self,
        x0,
        v0=None,
        params=None,
        gravity=None,
        effect_params=None,
        n_frames: int = 1,
        return_deformation: bool = False,
        tracers=None,
    ) -> RolloutResult:
        """Forward-only rollout (no gradients); same arguments as :meth:`simulate`, plus:

        Args:
            return_deformation: also return F and J per frame.
            tracers: optional (M, 3) passive points (e.g. the surface mesh's vertices) moved with
                the grid velocity; they do not affect the simulation.
        """
        x0t, v0t, pt, gt, et = self._prepare(x0, v0, params, gravity, effect_params, n_frames)
        tr = None
        if tracers is not None:
            tr = torch.as_tensor(np.asarray(tracers) if not isinstance(tracers, torch.Tensor) else tracers, dtype=torch.float32)
            if tr.ndim != 2 or tr.shape[1] != 3 or not torch.isfinite(tr).all():
                raise ValueError(f"tracers must be a finite (M, 3) array, got shape {tuple(tr.shape)}")
            tr = tr.to(self._torch_device).contiguous()
        with self.stream():
            out = self.forward_with_retries(
                x0t, v0t, pt, gt, et, n_frames, keep_checkpoints=False, return_deformation=return_deformation, tracers=tr
            )
        return RolloutResult(
            out["positions"], out["velocities"], out["substeps"], out.get("F"), out.get("J"), out.get("tracers")
        )

    # ------------------------------------------------------------------ forward core
    def forward_with_retries(self, x0, v0, params, gravity, effect_params, n_frames, keep_checkpoints,
                             return_deformation=False, tracers=None, tape_grads=None):
        """Forward pass at the planned substeps (:meth:`plan_substeps`), with optional automatic dt
        halving on CFL/NaN failures (the doubled count is kept for later rollouts) and grid growth when
        a particle leaves an auto-sized grid (``out_of_domain="grow"``).

        ``tape_grads`` (with ``keep_checkpoints``): which of params, gravity and effect_params the
        backward pass will need gradients of; the chunks are then kept on tapes when they fit
        (``out["tapes"]``, see :mod:`toolkit.mpm.tapes`)."""
        plan = self.plan_substeps(params, v0, gravity)
        if plan.capped:
            log.warning("the material needs %d substeps per frame at these parameters (wave speed %.3g m/s); "
                        "capped at SimConfig.max_substeps = %d", plan.needed, plan.wave_speed, self.config.max_substeps)
        self.last_plan = plan
        substeps = plan.substeps
        halvings = grows = 0
        while True:
            try:
                return self._forward(x0, v0, params, gravity, effect_params, n_frames, substeps, keep_checkpoints,
                                     return_deformation, tracers, tape_grads)
            except OutOfDomainError as err:
                if not self._can_grow(err) or grows >= 4:
                    raise
                grows += 1
                self._grow_grid(err.points)
            except (CFLError, NaNError) as err:
                if not self.config.auto_dt_halving or halvings >= self.config.max_dt_halvings:
                    raise
                halvings += 1
                self.halvings += 1
                log.warning("%s; halving dt (substeps %d -> %d) and rerunning; later rollouts keep >= %d substeps",
                            type(err).__name__, substeps, 2 * substeps, 2 * substeps)
                substeps *= 2
                self.substeps_floor = max(self.substeps_floor, substeps)

    def _check_memory(self, spec: GridSpec, n: int, n_frames: int, differentiable: bool, growing: bool = False) -> None:
        """:func:`~toolkit.mpm.planning.check_grid_memory` before ``spec``'s buffers are allocated.

        A grid that already passed (for gradients too, if asked now) is not checked again: its buffers
        are allocated and no longer show as free memory. The bytes this simulator holds count as free.
        """
        done = self._memory_checked
        self._differentiable = differentiable
        if done is not None and done[0] == spec and (done[1] or not differentiable):
            return
        held = done[2] if done is not None else 0
        need = check_grid_memory(spec, n, n_frames, self.config, self.device, differentiable, growing=growing, held=held)
        self._memory_checked = (spec, differentiable, need)

    def _can_grow(self, err: OutOfDomainError) -> bool:
        return self.config.out_of_domain == "grow" and self.config.domain is None and err.points is not None

    def _grow_grid(self, state: np.ndarray) -> None:
        """Enlarge the grid around the particles of the frame in which they left it.

        Args:
            state: (N, 6) positions and velocities at the start of that frame; the grid is grown to
                hold where they can reach within two frames at twice their speed, plus the margin.
        """
        state = np.asarray(state, np.float64)
        state = state[np.all(np.isfinite(state), axis=1)]
        if not len(state):
            raise OutOfDomainError("particles left the domain and no finite state is left to grow the grid around")
        x, v = state[:, :3], state[:, 3:]
        reach = 4.0 * np.abs(v) * self.config.frame_dt
        dx = self.config.dx
        pad = max(2 * self.config.margin, 4 * dx)
        lo = np.minimum(np.asarray(self._grid.origin), (x - reach).min(0) - pad)
        hi = np.maximum(np.asarray(self._grid.upper), (x + reach).max(0) + pad)
        if self.config.ground_height is not None:
            lo[1] = max(lo[1], min(self._grid.origin[1], self.config.ground_height - 4 * dx))
        origin = np.floor(lo / dx) * dx
        dims = np.ceil((hi - origin) / dx).astype(int) + 1
        spec = GridSpec(tuple(float(o) for o in origin), tuple(int(d) for d in dims), float(dx))
        self._check_memory(spec, len(state), 0, self._differentiable, growing=True)
        log.info("particles left the grid; growing it from %s to %s and rerunning", self._grid.dims, spec.dims)
        self.set_grid(spec)

    def chunks(self, n_frames: int, substeps: int) -> list[tuple[int, int, int]]:
        """Checkpoint chunks as (frame, first global substep, length); none straddles a frame."""
        k = self.config.checkpoint_every
        out = []
        for f in range(n_frames):
            s = 0
            while s < substeps:
                length = min(k, substeps - s)
                out.append((f, f * substeps + s, length))
                s += length
        return out

    def _wp(self, t: torch.Tensor, dtype, requires_grad: bool = False):
        return wp.from_torch(t.contiguous(), dtype=dtype, requires_grad=requires_grad)

    def use_graphs(self) -> bool:
        """Whether substep chains are captured as graphs (see :func:`captures_graphs`)."""
        nodes = None if self._grid is None else int(np.prod(self._grid.dims))
        return captures_graphs(self.config.graphs, self.device, self.config.deterministic, nodes)

    def _new_graphs(self) -> GraphCache:
        """An empty graph cache: a key is captured on its first use on CUDA, its second on the CPU
        (see :mod:`toolkit.mpm.graph_cache`)."""
        return GraphCache(1 if str(self.device).startswith("cuda") else 2)

    def capture(self) -> wp.ScopedCapture:
        """A graph capture on this simulator's device. On CUDA every module is loaded first (a
        kernel loaded during a capture would not be in the graph on older drivers); on the CPU
        modules load when a captured launch first needs them, since loading them all compiles
        every Warp module of the process on a cold kernel cache."""
        return wp.ScopedCapture(device=self.device, force_module_load=str(self.device).startswith("cuda"))

    def _run_substeps(self, a, b, grid, args, first: int, length: int, status, tracers,
                      graphs: Optional[GraphCache]):
        """Run ``length`` substeps from state ``a`` (frame-local index ``first``); returns the new (a, b).

        With ``graphs`` (a dict owned by the caller) the chain is captured once per
        (first, length, buffer parity) and replayed afterwards.
        """
        def chain():
            s_in, s_out = a, b
            for k in range(length):
                self._substep(s_in, s_out, grid, *args, first + k, status, tracers, grid_mode="reuse")
                s_in, s_out = s_out, s_in
                if tracers is not None:
                    tracers.reverse()
            return s_in, s_out

        key = None if graphs is None else ("forward", first, length, id(a), id(grid), id(args[0]), args[1], args[4],
                                           None if tracers is None else id(tracers[0]))
        if key is None or not graphs.should_capture(key):
            return chain()
        if key not in graphs:
            tr_before = None if tracers is None else list(tracers)
            with self.capture() as capture:
                result = chain()
            graphs[key] = (capture.graph, result, None if tracers is None else list(tracers))
            if tracers is not None:
                tracers[:] = tr_before  # the capture did not run anything: restore the order
        graph, result, tr_after = graphs[key]
        wp.capture_launch(graph)
        if tracers is not None:
            tracers[:] = tr_after
        return result

    def gradient_inputs(self, params: torch.Tensor, gravity: torch.Tensor, effect_params: torch.Tensor, n: int,
                        need: Sequence[bool]) -> tuple:
        """``(wp_params, wp_gravity, wp_effects, per_particle, shared_row)`` for a pass whose adjoint
        needs the gradients ``need`` = (params, gravity, effect_params).

        A shared parameter row whose gradient is wanted is expanded to one row per particle: every
        particle's adjoint then adds into its own row instead of all of them contending for the
        same P floats (the caller sums the rows when ``shared_row``)."""
        shared_row = bool(need[0]) and params.shape[0] == 1 and n > 1
        if shared_row:
            params = params.expand(n, params.shape[1]).contiguous()
        per_particle = int(params.shape[0] == n and n > 1)
        grads = (bool(need[0]), bool(need[1]), bool(need[2]) and effect_params.shape[0] > 0)
        return (*self._inputs(params, gravity, effect_params, grads), per_particle, shared_row)

    def _kept_tapes(self, n: int, chunks) -> Optional["KeptTapes"]:
        """The simulator's :class:`~toolkit.mpm.tapes.KeptTapes` when a rollout's chunks fit, else None."""
        from toolkit.mpm.tapes import KeptTapes

        key = ("tapes", n)
        held = self._buffers[key].held_bytes() if key in self._buffers else 0
        if not KeptTapes.fit(self, n, chunks, held):
            return None
        return self._persistent(key, lambda: KeptTapes(self, n))

    def _forward(self, x0, v0, params, gravity, effect_params, n_frames, substeps, keep_checkpoints, return_deformation,
                 tracers=None, tape_grads=None):
        n = x0.shape[0]
        dt = self.config.frame_dt / substeps
        dev = self._torch_device
        ground = self.config.ground_height
        self._ground_j = self._grid.ground_layer(ground) if ground is not None else -1
        self.generation += 1
        units = self.chunks(n_frames, substeps) if keep_checkpoints else [(f, f * substeps, substeps) for f in range(n_frames)]
        tapes = None
        if keep_checkpoints and tape_grads is not None and tracers is None and not return_deformation:
            tapes = self._kept_tapes(n, units)
        a, b, grid = self._pingpong(n)
        grid.clear()  # the substeps keep it clear from here on (see _substep's grid_mode)
        status = self._status()
        if tapes is not None:
            wp_params, wp_gravity, wp_effects, per_particle, _ = self.gradient_inputs(params, gravity, effect_params, n, tape_grads)
            tapes.start(self.generation, (wp_params, wp_gravity, wp_effects, per_particle))
        else:
            per_particle = int(params.shape[0] == n and n > 1)
            wp_params, wp_gravity, wp_effects = self._inputs(params, gravity, effect_params)
        args = (wp_params, per_particle, wp_gravity, wp_effects, dt)
        wp.launch(init_state, dim=n, inputs=[self._wp(x0, wp.vec3), self._wp(v0, wp.vec3), a.x, a.v, a.C, a.F, a.J], device=self.device)

        positions = torch.empty((n_frames + 1, n, 3), dtype=torch.float32, device=dev)
        velocities = torch.empty_like(positions)
        wp_pos = wp.from_torch(positions, dtype=wp.vec3)
        wp_vel = wp.from_torch(velocities, dtype=wp.vec3)
        wp.launch(store_frame, dim=n, inputs=[a.x, a.v, 0, wp_pos, wp_vel], device=self.device)
        Fs = Js = None
        if return_deformation:
            Fs = torch.empty((n_frames + 1, n, 3, 3), dtype=torch.float32, device=dev)
            Js = torch.empty((n_frames + 1, n), dtype=torch.float32, device=dev)
            wp.copy(wp.from_torch(Fs[0], dtype=wp.mat33), a.F)
            wp.copy(wp.from_torch(Js[0]), a.J)
        tr_pair = tr_out = None
        if tracers is not None:
            m = tracers.shape[0]
            tr_pair = list(self._persistent(("tracers", m), lambda: (
                wp.zeros(m, dtype=wp.vec3, device=self.device), wp.zeros(m, dtype=wp.vec3, device=self.device))))
            wp.copy(tr_pair[0], wp.from_torch(tracers, dtype=wp.vec3))
            tr_out = torch.empty((n_frames + 1, m, 3), dtype=torch.float32, device=dev)
            wp.copy(wp.from_torch(tr_out[0], dtype=wp.vec3), tr_pair[0])
        graphs = self._graphs if self.use_graphs() else None
        checkpoints: list[ParticleBuffers] = []
        for index, (frame, first, length) in enumerate(units):
            if keep_checkpoints:
                ck = ParticleBuffers(n, self.device)
                ck.assign(a)
                checkpoints.append(ck)
            local = first - frame * substeps
            if tapes is not None:
                tapes.forward_chunk(index, a, args, local, length, status, graphs)
            else:
                a, b = self._run_substeps(a, b, grid, args, local, length, status, tr_pair, graphs)
            if local + length < substeps:
                continue
            wp.launch(store_frame, dim=n, inputs=[a.x, a.v, frame + 1, wp_pos, wp_vel], device=self.device)
            # copies stay on the simulator's stream (see stream())
            if tr_pair is not None:
                wp.copy(wp.from_torch(tr_out[frame + 1], dtype=wp.vec3), tr_pair[0])
            if return_deformation:
                wp.copy(wp.from_torch(Fs[frame + 1], dtype=wp.mat33), a.F)
                wp.copy(wp.from_torch(Js[frame + 1]), a.J)
            try:
                self._check_status(status, frame, substeps, a)
            except OutOfDomainError as err:
                # the end-of-frame state may be garbage already: keep the frame's (good) start state
                err.points = torch.cat([positions[frame], velocities[frame]], 1).cpu().numpy()
                raise
        out = {"positions": positions, "velocities": velocities, "substeps": substeps, "checkpoints": checkpoints, "dt": dt,
               "tapes": tapes}
        if return_deformation:
            out["F"], out["J"] = Fs, Js
        if tr_out is not None:
            out["tracers"] = tr_out
        return out

"""Warp kernels of one MLS-MPM substep (DESIGN section 4).

A substep is three launches: P2G (with the material update fused in), the grid update (gravity,
effects, boundary conditions) and G2P. P2G and the grid update are generated per material and
per set of effects from their ``@wp.func`` pieces and cached; G2P is shared.

Grid conventions: node ``(i, j, k)`` sits at ``origin + (i, j, k) dx``; a particle at grid
coordinate ``X = (x - origin) / dx`` touches the 3x3x3 nodes from ``base = floor(X - 0.5)``
with quadratic B-spline weights. A particle is inside the domain while
``0 <= base`` and ``base + 2 < dims`` on every axis.

Status flags (``status``, int32[4]): [0] first substep with a particle outside the domain,
[1] first substep with a CFL violation, [2] first substep with a NaN/inf, [3] unused; each is
``NO_FLAG`` when clean. They are written with atomics that the adjoint never needs. G2P also
keeps the largest particle speed of the first CFL-violating substep (``violation_speed``, float[1]),
so the error reports the real speed rather than that of a later, already broken state.

Ground nodes are the layers ``j <= ground_j``, an integer computed on the host in float64
(:meth:`GridSpec.ground_layer`): a float32 node position ``origin + j dx`` can round to either
side of the ground plane depending on where the grid starts.
"""

from __future__ import annotations

from typing import Callable, Sequence

import warp as wp

__all__ = [
    "NO_FLAG",
    "make_p2g_kernel",
    "make_grid_update_kernel",
    "make_g2p_kernel",
    "advect_tracers",
    "store_frame",
    "compose_effects",
]

NO_FLAG = 2**31 - 1


@wp.func
def bspline_weights(fx: wp.vec3):
    """Quadratic B-spline weights; row o is offset o, column a is axis a."""
    w0 = wp.cw_mul(wp.vec3(1.5) - fx, wp.vec3(1.5) - fx) * 0.5
    d1 = fx - wp.vec3(1.0)
    w1 = wp.vec3(0.75) - wp.cw_mul(d1, d1)
    d2 = fx - wp.vec3(0.5)
    w2 = wp.cw_mul(d2, d2) * 0.5
    return wp.matrix_from_rows(w0, w1, w2)


@wp.func
def stencil_base(X: wp.vec3, nx: int, ny: int, nz: int):
    """Lower stencil corner of grid coordinate X, clamped into the grid (memory safety)."""
    bx = int(wp.floor(X[0] - 0.5))
    by = int(wp.floor(X[1] - 0.5))
    bz = int(wp.floor(X[2] - 0.5))
    return wp.vec3i(wp.clamp(bx, 0, nx - 3), wp.clamp(by, 0, ny - 3), wp.clamp(bz, 0, nz - 3))


@wp.func
def inside(X: wp.vec3, nx: int, ny: int, nz: int):
    """True if a particle at grid coordinate X has its whole stencil inside the grid."""
    ok = X[0] >= 0.5 and X[1] >= 0.5 and X[2] >= 0.5
    return ok and X[0] < float(nx) - 1.5 and X[1] < float(ny) - 1.5 and X[2] < float(nz) - 1.5


def _options(deterministic: bool) -> dict | None:
    """Module options: Warp's deterministic float atomics (forward and adjoint) when asked for."""
    return {"deterministic": wp.DeterministicMode.RUN_TO_RUN} if deterministic else None


def make_p2g_kernel(update: Callable, deterministic: bool = False) -> "wp.Kernel":
    """P2G with the material update fused in.

    Args:
        update: the material's ``@wp.func`` ``(F_tmp, C, J, dt, p, row) -> (F_new, J_new, tau)``.
        deterministic: compile with Warp's deterministic atomics (reproducible on CUDA, slower).
    """

    @wp.kernel(module="unique", module_options=_options(deterministic))
    def p2g(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        C: wp.array(dtype=wp.mat33),
        F: wp.array(dtype=wp.mat33),
        J: wp.array(dtype=float),
        params: wp.array2d(dtype=float),
        per_particle: int,
        F_out: wp.array(dtype=wp.mat33),
        J_out: wp.array(dtype=float),
        grid_m: wp.array3d(dtype=float),
        grid_mv: wp.array3d(dtype=wp.vec3),
        origin: wp.vec3,
        dx: float,
        dt: float,
        volume: float,
        mass: float,
        status: wp.array(dtype=wp.int32),
        step: int,
    ):
        p = wp.tid()
        nx = grid_m.shape[0]
        ny = grid_m.shape[1]
        nz = grid_m.shape[2]
        inv_dx = 1.0 / dx
        X = (x[p] - origin) * inv_dx
        if not inside(X, nx, ny, nz):
            wp.atomic_min(status, 0, step)
        base = stencil_base(X, nx, ny, nz)
        fx = X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        w = bspline_weights(fx)

        Cp = C[p]
        F_tmp = (wp.identity(n=3, dtype=float) + dt * Cp) @ F[p]
        F_new, J_new, tau = update(F_tmp, Cp, J[p], dt, params, p * per_particle)
        F_out[p] = F_new
        J_out[p] = J_new

        affine = (-dt * volume * 4.0 * inv_dx * inv_dx) * tau + mass * Cp
        momentum = mass * v[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    wp.atomic_add(grid_mv, base[0] + i, base[1] + j, base[2] + k, weight * (momentum + affine @ dpos))
                    wp.atomic_add(grid_m, base[0] + i, base[1] + j, base[2] + k, weight * mass)

    return p2g


@wp.func
def _no_effect(v: wp.vec3, x: wp.vec3, dt: float, ep: wp.array(dtype=float)):
    return v


def compose_effects(funcs: Sequence[Callable]) -> Callable:
    """Chain effect functions ``apply(v, x, dt, ep) -> v`` in order into one ``@wp.func``."""
    chain = _no_effect
    for f in funcs:
        chain = _then(chain, f)
    return chain


def _then(first: Callable, second: Callable) -> Callable:
    @wp.func
    def chained(v: wp.vec3, x: wp.vec3, dt: float, ep: wp.array(dtype=float)):
        return second(first(v, x, dt, ep), x, dt, ep)

    return chained


def make_grid_update_kernel(
    effects: Callable, has_ground: bool, boundary: str, domain_walls: bool, deterministic: bool = False,
    clear_after: bool = False,
) -> "wp.Kernel":
    """Grid update: momentum -> velocity, gravity, effects, ground and domain boundaries.

    Args:
        effects: the composed effect function (see :func:`compose_effects`).
        has_ground: whether there is a ground plane; its node layers ``j <= ground_j`` (a kernel
            argument, see :meth:`GridSpec.ground_layer`) get the boundary condition.
        boundary: ``sticky``, ``slip`` or ``separate`` (ground contact at the ground layers).
        domain_walls: apply separating walls on the outer two node layers (``clamp`` mode).
        deterministic: deterministic atomics (the adjoint reduces into gravity and effect parameters).
        clear_after: also zero each node's mass and momentum once read, so the grid is clear for the
            next substep's P2G without two memsets per substep (forward-only: this variant has no
            adjoint, and nothing may read the mass after it, e.g. tracer advection).

    The kernel runs over a box of nodes: thread ``(i, j, k)`` updates node ``(i, j, k) + offset``
    (launch dims = the box's; the whole grid with a zero offset). Nodes outside the box keep their
    velocity; the caller guarantees that no particle's stencil reaches them.
    """
    has_ground = bool(has_ground)
    clear_after = bool(clear_after)
    mode = {"sticky": 0, "slip": 1, "separate": 2}[boundary]
    options = dict(_options(deterministic) or {})
    if clear_after:
        options["enable_backward"] = False

    @wp.kernel(module="unique", module_options=options or None)
    def grid_update(
        grid_m: wp.array3d(dtype=float),
        grid_mv: wp.array3d(dtype=wp.vec3),
        grid_v: wp.array3d(dtype=wp.vec3),
        gravity: wp.array(dtype=wp.vec3),
        effect_params: wp.array(dtype=float),
        origin: wp.vec3,
        dx: float,
        dt: float,
        ground_j: int,
        offset: wp.vec3i,
    ):
        ti, tj, tk = wp.tid()
        i = ti + offset[0]
        j = tj + offset[1]
        k = tk + offset[2]
        m = grid_m[i, j, k]
        mv = grid_mv[i, j, k]
        v = wp.vec3(0.0)
        if wp.static(clear_after):
            grid_m[i, j, k] = 0.0
            grid_mv[i, j, k] = wp.vec3(0.0)
        if m > 1.0e-15:
            xn = origin + wp.vec3(float(i), float(j), float(k)) * dx
            v = mv / m + dt * gravity[0]
            v = effects(v, xn, dt, effect_params)
            if wp.static(has_ground):
                if j <= ground_j:
                    if wp.static(mode == 0):
                        v = wp.vec3(0.0)
                    elif wp.static(mode == 1):
                        v = wp.vec3(v[0], 0.0, v[2])
                    else:
                        v = wp.vec3(v[0], wp.max(v[1], 0.0), v[2])
            if wp.static(domain_walls):
                nx = grid_m.shape[0]
                ny = grid_m.shape[1]
                nz = grid_m.shape[2]
                vx = v[0]
                vy = v[1]
                vz = v[2]
                if i < 2:
                    vx = wp.max(vx, 0.0)
                if i > nx - 3:
                    vx = wp.min(vx, 0.0)
                if j < 2:
                    vy = wp.max(vy, 0.0)
                if j > ny - 3:
                    vy = wp.min(vy, 0.0)
                if k < 2:
                    vz = wp.max(vz, 0.0)
                if k > nz - 3:
                    vz = wp.min(vz, 0.0)
                v = wp.vec3(vx, vy, vz)
        grid_v[i, j, k] = v

    return grid_update


def make_g2p_kernel(deterministic: bool = False) -> "wp.Kernel":
    """G2P (shared by all materials); a separate module per determinism setting."""
    return _G2P[bool(deterministic)]


def _make_g2p(deterministic: bool):
    @wp.kernel(module="unique", module_options=_options(deterministic))
    def g2p(
        x: wp.array(dtype=wp.vec3),
        grid_v: wp.array3d(dtype=wp.vec3),
        x_out: wp.array(dtype=wp.vec3),
        v_out: wp.array(dtype=wp.vec3),
        C_out: wp.array(dtype=wp.mat33),
        origin: wp.vec3,
        dx: float,
        dt: float,
        cfl_speed: float,
        clamp_particles: int,
        status: wp.array(dtype=wp.int32),
        violation_speed: wp.array(dtype=float),
        step: int,
    ):
        """Grid-to-particle transfer: velocity, APIC matrix C = 4/dx^2 sum w v (x_i - x_p)^T, x += dt v."""
        p = wp.tid()
        nx = grid_v.shape[0]
        ny = grid_v.shape[1]
        nz = grid_v.shape[2]
        inv_dx = 1.0 / dx
        X = (x[p] - origin) * inv_dx
        base = stencil_base(X, nx, ny, nz)
        fx = X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        w = bspline_weights(fx)
        new_v = wp.vec3(0.0)
        new_C = wp.mat33(0.0)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = wp.vec3(float(i), float(j), float(k)) - fx
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    gv = grid_v[base[0] + i, base[1] + j, base[2] + k]
                    new_v = new_v + weight * gv
                    new_C = new_C + (4.0 * inv_dx * weight) * wp.outer(gv, dpos)
        x_new = x[p] + dt * new_v
        speed2 = wp.dot(new_v, new_v)
        if not (speed2 <= cfl_speed * cfl_speed):
            # also true for NaN speeds, which the NaN flag below reports separately
            if wp.isfinite(speed2):
                wp.atomic_min(status, 1, step)
                if status[1] >= step:
                    # still the first violating substep: keep its largest speed for the message
                    wp.atomic_max(violation_speed, 0, wp.sqrt(speed2))
        if not (wp.isfinite(x_new) and wp.isfinite(new_v)):
            wp.atomic_min(status, 2, step)
        if clamp_particles != 0:
            lo = origin + wp.vec3(1.0 * dx)
            hi = origin + wp.vec3(float(nx) - 2.0, float(ny) - 2.0, float(nz) - 2.0) * dx
            x_new = wp.vec3(wp.clamp(x_new[0], lo[0], hi[0]), wp.clamp(x_new[1], lo[1], hi[1]), wp.clamp(x_new[2], lo[2], hi[2]))
        elif not inside((x_new - origin) * inv_dx, nx, ny, nz):
            wp.atomic_min(status, 0, step + 1)
        x_out[p] = x_new
        v_out[p] = new_v
        C_out[p] = new_C

    return g2p


_G2P = {False: _make_g2p(False), True: _make_g2p(True)}


@wp.kernel
def advect_tracers(
    y: wp.array(dtype=wp.vec3),
    grid_m: wp.array3d(dtype=float),
    grid_v: wp.array3d(dtype=wp.vec3),
    y_out: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    dx: float,
    dt: float,
):
    """Move passive tracer points (no mass) with the grid velocity.

    The velocity is the B-spline average over the stencil nodes that carry mass, renormalized by
    their weights, so a tracer on or slightly outside the body's surface moves with the body
    instead of being slowed by empty nodes. A tracer with no massive node nearby stays put.
    Tracers outside the grid are clamped to it; they never affect the simulation.
    """
    q = wp.tid()
    nx = grid_v.shape[0]
    ny = grid_v.shape[1]
    nz = grid_v.shape[2]
    X = (y[q] - origin) * (1.0 / dx)
    base = stencil_base(X, nx, ny, nz)
    fx = X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    w = bspline_weights(fx)
    vel = wp.vec3(0.0)
    wsum = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                if grid_m[base[0] + i, base[1] + j, base[2] + k] > 1.0e-15:
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    vel = vel + weight * grid_v[base[0] + i, base[1] + j, base[2] + k]
                    wsum = wsum + weight
    if wsum > 1.0e-6:
        vel = vel / wsum
    y_out[q] = y[q] + dt * vel


@wp.kernel
def store_frame(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), frame: int, xs: wp.array2d(dtype=wp.vec3), vs: wp.array2d(dtype=wp.vec3)):
    """Copy the current positions and velocities into row ``frame`` of the outputs."""
    p = wp.tid()
    xs[frame, p] = x[p]
    vs[frame, p] = v[p]


@wp.kernel
def accumulate_vec3(dst: wp.array(dtype=wp.vec3), src: wp.array(dtype=wp.vec3)):
    """dst += src (adjoint seeding on the simulator's stream)."""
    i = wp.tid()
    dst[i] = dst[i] + src[i]


@wp.kernel
def init_state(
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    J: wp.array(dtype=float),
):
    """Rest state: positions and velocities given, C = 0, F = I, J = 1."""
    p = wp.tid()
    x[p] = x0[p]
    v[p] = v0[p]
    C[p] = wp.mat33(0.0)
    F[p] = wp.identity(n=3, dtype=float)
    J[p] = 1.0

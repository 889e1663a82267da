"""The torch bridge of the simulator: a ``torch.autograd.Function`` with chunked checkpointing
(the chunks recomputed on the backward pass, or their forward tapes kept: :mod:`toolkit.mpm.tapes`)."""

from __future__ import annotations

import torch
import warp as wp

from toolkit.mpm.kernels import accumulate_vec3

__all__ = ["SimulateFunction"]


class SimulateFunction(torch.autograd.Function):
    """positions, velocities = SimulateFunction.apply(sim, n_frames, holder, x0, v0, params, gravity, effect_params)

    ``x0`` (N, 3), ``v0`` (N, 3), ``params`` (R, P), ``gravity`` (3,), ``effect_params`` (E,), all
    float32 contiguous on the simulator's device (see ``MPMSimulator._prepare``). Outputs are
    (T+1, N, 3). ``holder`` receives the substeps used (after any dt halving).
    """

    @staticmethod
    def forward(ctx, sim, n_frames, holder, x0, v0, params, gravity, effect_params):
        with sim.stream():
            out = sim.forward_with_retries(x0, v0, params, gravity, effect_params, n_frames, keep_checkpoints=True,
                                           tape_grads=tuple(ctx.needs_input_grad[5:8]))
        holder["substeps"] = out["substeps"]
        tapes = out.get("tapes")
        ctx.tapes = (tapes, tapes.generation) if tapes is not None else None
        ctx.sim = sim
        ctx.n_frames = n_frames
        ctx.substeps = out["substeps"]
        ctx.checkpoints = out["checkpoints"]
        ctx.save_for_backward(params, gravity, effect_params)
        return out["positions"], out["velocities"]

    @staticmethod
    def backward(ctx, g_pos, g_vel):
        sim = ctx.sim
        params, gravity, effect_params = ctx.saved_tensors
        substeps = ctx.substeps
        n = ctx.checkpoints[0].x.shape[0] if ctx.checkpoints else None
        if n is None:  # zero frames: the outputs are the inputs
            zeros = torch.zeros_like
            gp = g_pos if g_pos is not None else None
            gv = g_vel if g_vel is not None else None
            return (None, None, None, None if gp is None else gp[0], None if gv is None else gv[0],
                    zeros(params), zeros(gravity), zeros(effect_params))
        dev = params.device
        g_pos = torch.zeros((ctx.n_frames + 1, n, 3), device=dev) if g_pos is None else g_pos.contiguous()
        g_vel = torch.zeros((ctx.n_frames + 1, n, 3), device=dev) if g_vel is None else g_vel.contiguous()
        chunks = sim.chunks(ctx.n_frames, substeps)
        dt = sim.config.frame_dt / substeps
        need = ctx.needs_input_grad[5:8]
        kept = None
        if ctx.tapes is not None and ctx.tapes[1] == sim.generation:
            kept = ctx.tapes[0]  # no forward pass since ours: its tapes are intact
        ctx.tapes = None

        with sim.stream():
            if kept is not None:
                wp_params, wp_gravity, wp_effects, per_particle = kept.inputs
                shared_row = bool(need[0]) and params.shape[0] == 1 and n > 1
            else:
                sim.generation += 1  # the recompute reuses the input arrays that kept tapes read
                wp_params, wp_gravity, wp_effects, per_particle, shared_row = sim.gradient_inputs(
                    params, gravity, effect_params, n, need)
                pool = sim._pool(n, max(length for _, _, length in chunks))
                states, grids = pool.states, pool.grids
            for a in (wp_params, wp_gravity, wp_effects):
                if a.grad is not None:
                    a.grad.zero_()
            carry = sim._persistent(("carry", n), lambda: [wp.zeros_like(a) for a in ctx.checkpoints[0].arrays()])
            for a in carry:
                a.zero_()
            g_pos_wp = wp.from_torch(g_pos, dtype=wp.vec3)
            g_vel_wp = wp.from_torch(g_vel, dtype=wp.vec3)
            status = sim._status()

            args = (wp_params, per_particle, wp_gravity, wp_effects, dt)

            def chunk_backward(local: int, length: int) -> None:
                # recompute the chunk on a tape (one state and grid per substep), then its adjoint
                pool.clear()
                tape = wp.Tape()
                with tape:
                    for k in range(length):
                        sim._substep(states[k], states[k + 1], grids[k], *args, local + k, status, grid_mode="cleared")
                tape.backward(grads={a: g for a, g in zip(states[length].arrays(), carry)})
                for dst, src in zip(carry, states[0].arrays()):
                    wp.copy(dst, src.grad)

            graphs = sim._graphs if sim.use_graphs() else None
            for c in range(len(chunks) - 1, -1, -1):
                frame, first, length = chunks[c]
                local = first - frame * substeps
                if local + length == substeps:
                    wp.launch(accumulate_vec3, dim=n, inputs=[carry[0], g_pos_wp[frame + 1]], device=sim.device)
                    wp.launch(accumulate_vec3, dim=n, inputs=[carry[1], g_vel_wp[frame + 1]], device=sim.device)
                if kept is not None:
                    kept.backward_chunk(c, carry, graphs)
                    continue
                states[0].assign(ctx.checkpoints[c])
                key = None if graphs is None else ("backward", local, length, id(states[0].x), id(wp_params),
                                                   id(wp_gravity), id(wp_effects), per_particle, dt)
                if key is None or not graphs.should_capture(key):
                    chunk_backward(local, length)
                    continue
                if key not in graphs:
                    with sim.capture() as capture:
                        chunk_backward(local, length)
                    graphs[key] = capture.graph
                wp.capture_launch(graphs[key])

        # torch's stream has waited for the Warp work (sim.stream())
        g_x0 = wp.to_torch(carry[0]) + g_pos[0]
        g_v0 = wp.to_torch(carry[1]) + g_vel[0]
        g_params = g_gravity = g_effects = None
        need_params, need_gravity, need_effects = need
        if need_params:
            g_params = wp.to_torch(wp_params.grad).clone()
            if shared_row:
                g_params = g_params.sum(0, keepdim=True)
        if need_gravity:
            g_gravity = wp.to_torch(wp_gravity.grad).clone().reshape(3)
        if need_effects:
            g_effects = (wp.to_torch(wp_effects.grad)[: effect_params.shape[0]].clone() if effect_params.shape[0] > 0
                         else torch.zeros_like(effect_params))
        return None, None, None, g_x0, g_v0, g_params, g_gravity, g_effects

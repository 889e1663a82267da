"""Is the fit's grid fine enough? Re-simulate the estimate on a grid of half the spacing and
measure how far the trajectory moves (issue #20).

An MPM trajectory depends on the grid spacing until the grid resolves the body: a thin or stiff
body simulated two cells thick bends and bounces differently from the same body eight cells
thick. A fit on a grid that is too coarse then moves its material parameters to make the coarse
simulation look like the data; ``benchmarks/grid_bias.py`` measured 0.75 decades of E on a
generated letter T fitted at dx 0.02 m for a truth at 0.01 m (and the minimum at the truth on the
truth's grid). Nothing in the images says so, so after every fit the pipeline runs this check:

1. the fitted state (positions, v0, material, gravity, effects) is simulated over the training
   frames on the fit's grid and on one of half the spacing, each particle split into 8 at the
   corners of a cube of half its lattice pitch (same mass, same centre);
2. the **grid shift** is the mean distance between each particle and the mean of its 8 children,
   over particles and training frames (metres);
3. it is compared with the fit's own residual: the mean distance between the fitted surface
   particles and the observed (stage-0) surface of each training frame, both ways. A shift larger
   than that residual means a finer grid moves the prediction by more than the fit's misfit to
   the data: the estimates depend on the grid, and the summary says to fit again at the finer
   spacing.

It costs one coarse and one fine rollout of the training frames (the fine one 8x the particles
and nodes, about twice the substeps).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import TYPE_CHECKING, Optional

import torch

from toolkit.mpm.config import SimulationError

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.mpm import MPMSimulator
    from toolkit.physics.module import InversePhysicsModule

__all__ = ["subdivide", "grid_shift", "grid_convergence", "check_estimate", "shift_of_estimate", "state_key", "format_grid_check", "annotate_grid",
           "GRID_NOTE"]

#: added to the note of each material parameter when the grid check fails
GRID_NOTE = "grid-dependent: a grid of half the spacing moves the fit more than its misfit (see the grid check)"

log = logging.getLogger(__name__)

_CORNERS = torch.tensor([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=torch.float32)


def subdivide(x: torch.Tensor, pitch: float) -> torch.Tensor:
    """Split each of N particles on a lattice of ``pitch`` metres into 8 on the lattice of half
    the pitch: ``(N, 3) -> (8N, 3)``, children ``8i .. 8i + 7`` of particle ``i`` at its centre
    ``± pitch / 4`` per axis (their mean is the parent)."""
    return (x[:, None, :] + _CORNERS.to(x) * (pitch / 4.0)).reshape(-1, 3)


def grid_shift(sim: "MPMSimulator", x0: torch.Tensor, v0: torch.Tensor, params: torch.Tensor, gravity: torch.Tensor,
               effect_params: torch.Tensor, n_frames: int) -> dict:
    """Simulate a state on ``sim``'s grid and on one of half the spacing; how far it moves.

    Args:
        sim: the fit's simulator (its config gives dx and the particle volume).
        x0: (N, 3) particles on a lattice of pitch ``particle_volume ** (1/3)``; v0 (3,) or (N, 3);
            params (1, P) or (N, P) physical; gravity (3,); effect_params (E,).
        n_frames: frames simulated after the first.

    Returns:
        ``dx``, ``fine_dx`` (m), ``shift_m`` (mean distance over particles and frames 1..n_frames),
        ``shift_per_frame_m`` (frames 0..n_frames), ``substeps`` and ``fine_substeps`` (per frame).
    """
    from toolkit.mpm import MPMSimulator

    cfg = sim.config
    n = x0.shape[0]
    volume = cfg.volume
    pitch = volume ** (1.0 / 3.0)
    coarse = sim.rollout(x0, v0, params, gravity=gravity, effect_params=effect_params, n_frames=n_frames)
    fine_cfg = dataclasses.replace(cfg, dx=cfg.dx / 2.0, particle_volume=volume / 8.0, domain=None)
    fine = MPMSimulator(sim.material, fine_cfg, effects=sim.effects, device=sim.device)
    fine_params = params.repeat_interleave(8, dim=0) if params.shape[0] == n and n > 1 else params
    fine_v0 = v0.repeat_interleave(8, dim=0) if v0.ndim == 2 else v0
    out = fine.rollout(subdivide(x0, pitch), fine_v0, fine_params, gravity=gravity, effect_params=effect_params, n_frames=n_frames)
    parents = out.positions.reshape(n_frames + 1, n, 8, 3).mean(2)
    per_frame = (parents - coarse.positions).norm(dim=-1).mean(1).cpu().numpy()
    return {"dx": float(cfg.dx), "fine_dx": float(fine_cfg.dx), "shift_m": float(per_frame[1:].mean()) if n_frames else 0.0,
            "shift_per_frame_m": [float(s) for s in per_frame], "substeps": int(coarse.substeps),
            "fine_substeps": int(out.substeps), "positions": coarse.positions, "fine_positions": parents}


def surface_residual(module: "InversePhysicsModule", positions: torch.Tensor, frames) -> Optional[float]:
    """Mean distance (m) between the simulated surface particles and the observed surface of each
    of ``frames``, both ways (:func:`toolkit.metrics.mean_nearest_distance`), averaged over the
    frames that have an observed surface; None if none has."""
    from toolkit.metrics import mean_nearest_distance

    out = [mean_nearest_distance(positions[f][module.surface_index], module.input.surfaces[f])
           for f in frames if len(module.input.surfaces[f])]
    return float(sum(out) / len(out)) if out else None


def state_key(module: "InversePhysicsModule") -> bytes:
    """Bytes of everything that moves the particles (positions, v0, gravity, material, effects): two
    equal keys simulate the same trajectory."""
    with torch.no_grad():
        parts = [module.particle_offset.detach().flatten(), module.v0.detach().flatten(), module.gravity.detach().flatten(),
                 module.material_params().detach().flatten(), module.effect_params.detach().flatten()]
        return torch.cat([p.float().cpu() for p in parts]).numpy().tobytes()


@torch.no_grad()
def grid_convergence(module: "InversePhysicsModule", n_frames: Optional[int] = None) -> dict:
    """:func:`grid_shift` of a fitted module's estimate over its training frames, judged against
    the fit's own residual (:func:`check_estimate`).

    The uncertainty step (:mod:`toolkit.physics.uncertainty`) runs the same check at the end of a fit
    for its grid term; :func:`check_estimate` keeps the record on the module (``grid_check_result``,
    with the :func:`state_key` it was computed at), and while the estimate has not moved since, that
    record is returned instead of simulating again.

    Returns:
        the :func:`grid_shift` record (without positions) plus ``residual_m`` (None when no frame
        has an observed surface), ``first_frame_residual_m`` (the same distance at frame 0, where
        the particles were built from the observed surface: the floor a fit that follows the
        motion stays near; a residual many times it means the simulation misses the motion, and
        then a small ``ratio`` says little), ``ratio`` (shift / residual), ``converged`` (shift <= residual;
        None without a residual), ``frames`` and ``seconds``; or ``{"skipped": reason}`` when the
        fine grid does not fit in memory or its rollout fails.
    """
    n_frames = int(n_frames if n_frames is not None else module.input.n_train - 1)
    cached = getattr(module, "grid_check_result", None)
    if cached and cached.get("frames") == n_frames and getattr(module, "grid_check_key", None) == state_key(module):
        return dict(cached)
    return check_estimate(module, n_frames)[0]


@torch.no_grad()
def shift_of_estimate(module: "InversePhysicsModule", n_frames: int) -> dict:
    """:func:`grid_shift` of the module's current estimate (particles, v0, material, gravity,
    effects) over frames 0..``n_frames``, without substep log lines and with the simulator's
    substep plan restored afterwards. Raises what the rollouts raise (:class:`SimulationError`,
    or a RuntimeError such as a device out of memory)."""
    x0 = (module.particles0 + module.particle_offset).detach()
    args = (module.v0.detach(), module.material_params().detach(), module.gravity.detach(), module.effect_params.detach())
    sim = module.simulator
    with module.substeps_unlogged(), sim.substep_plan_restored():
        return grid_shift(sim, x0, *args, n_frames=n_frames)


@torch.no_grad()
def check_estimate(module: "InversePhysicsModule", n_frames: Optional[int] = None) -> tuple[dict, Optional[dict]]:
    """Simulate the module's current estimate on its grid and on one of half the spacing, and judge
    the shift against the fit's residual (training frames 1..``n_frames``, default all).

    Returns:
        ``(record, shift)``: the :func:`grid_convergence` record, also kept on the module for it to
        reuse, and the :func:`grid_shift` record with both trajectories (``positions``,
        ``fine_positions``); ``shift`` is None and ``record`` is ``{"skipped": reason}`` when the
        fine grid does not fit in memory or its rollout fails (nothing is kept then).
    """
    t = time.perf_counter()
    n_frames = int(n_frames if n_frames is not None else module.input.n_train - 1)
    try:
        shift = shift_of_estimate(module, n_frames)
    except (SimulationError, RuntimeError) as err:  # GridTooLargeError, or a device out of memory: the fine grid does not fit
        return {"skipped": f"{type(err).__name__}: {str(err)[:300]}", "seconds": time.perf_counter() - t}, None
    residual = surface_residual(module, shift["positions"], range(1, n_frames + 1))
    first = surface_residual(module, shift["positions"], [0])
    ok = residual is not None and math.isfinite(residual) and residual > 0
    rec = {k: v for k, v in shift.items() if k not in ("positions", "fine_positions")}
    rec.update({"frames": n_frames, "residual_m": residual if ok else None,
                "first_frame_residual_m": first if first is not None and math.isfinite(first) else None,
                "ratio": rec["shift_m"] / residual if ok else None,
                "converged": bool(rec["shift_m"] <= residual) if ok else None, "seconds": time.perf_counter() - t})
    if rec["converged"] is False:
        log.warning("%s", format_grid_check(rec))
    module.grid_check_result, module.grid_check_key = dict(rec), state_key(module)
    return rec, shift


def format_grid_check(rec: Optional[dict]) -> str:
    """One line for the CLI summary and the log."""
    if not rec:
        return "grid check: not run"
    if "skipped" in rec:
        return f"grid check: skipped ({rec['skipped']})"
    shift = f"halving dx ({rec['dx']:g} -> {rec['fine_dx']:g} m) moves the training frames by {1e3 * rec['shift_m']:.2f} mm on average"
    if rec.get("residual_m") is None:
        return f"grid check: {shift}"
    first = rec.get("first_frame_residual_m")
    floor = f"; {1e3 * first:.2f} mm at the first frame, where the particles were built" if first is not None else ""
    misfit = f"{rec['ratio']:.1f}x the fit's residual ({1e3 * rec['residual_m']:.2f} mm{floor})"
    if rec["converged"]:
        return f"grid check: {shift}, {misfit}: the grid moves the prediction less than the fit misses the data"
    return (f"grid check: {shift}, {misfit}: the estimates depend on the grid more than the fit's misfit; "
            f"fit again with --sim '{{\"dx\": {rec['fine_dx']:g}}}'")



def annotate_grid(rows: list[dict], rec: Optional[dict], material_params) -> list[dict]:
    """Append :data:`GRID_NOTE` to the note of the summary rows of ``material_params`` when the
    grid check ``rec`` found the estimate grid-dependent (``converged`` False). In place; returned."""
    if not rec or rec.get("converged") is not False:
        return rows
    names = set(material_params)
    for row in rows:
        if row["parameter"] in names:
            row["note"] = "; ".join(n for n in (row.get("note") or "", GRID_NOTE) if n)
    return rows

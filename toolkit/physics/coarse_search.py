"""Coarse global search of the material parameters before gradient descent (issue #20).

Gradient descent on a rollout loss only finds the minimum of the basin it starts in, and a
material's default guess can be decades away from a scene's truth. Before the first iteration
that optimizes ``M``, :func:`coarse_search` sweeps each optimized material parameter over its
search range (:attr:`materials.base.MaterialParam.search`) in the parameter's own coordinate
(log10 for ``log10`` parameters, the physical value for bounded ones), scoring every candidate by
**the fit's own loss** (:meth:`toolkit.physics.module.InversePhysicsModule.losses`: image + geometric terms of that
stage) on a few training frames of the stage's window, with the current positions, appearance
and v0, forward-only (no gradients). The module then starts from the best candidate.

Method (coordinate-wise, coarse to fine):

1. evaluate the current start (the given or default guess): the search never returns a point
   the loss ranks worse than where the fit would have started;
2. for each optimized parameter that has a search range, in the material's order (one without,
   such as an added effect's, keeps its guess): evaluate a grid over its search range
   (one point per decade for ``log10`` parameters, :data:`BOUNDED_POINTS` points for bounded
   ones) with the others held at their best values so far, then halve the grid step
   ``refinements`` times around the best point (within the range; gradient descent may leave it);
   the parameter moves there only if that lowers the loss by more than :data:`MIN_GAIN` (1 %),
   so a direction the clip does not determine (a flat loss) keeps its guess;
3. materials with a yield surface (a ``yield_stress`` or ``friction_angle`` parameter) have
   branches (a body that yields or not) that a single coordinate path can miss: the
   :data:`YIELD_STARTS` best local minima of the first parameter's grid each start a path
   (multi-start). With ``joint_yield`` the first parameter is also swept together with the yield
   parameter on their product grid, and paths start from that grid's best local minima as well
   (the first parameter's line at the yield parameter's guess can fall all the way to a stiff
   edge when the guess is off: ``docs/results/paper_size.md``, round 36);
4. the pick: the lower of the start and the default's best path end on the search's frames (a
   tie keeps the start). With ``joint_yield`` that pick and each product-grid path's end are
   scored again on **every frame of the window**, and a grid path's end replaces the pick only if
   it is lower there by more than :data:`MIN_GAIN`: the few search frames can rank a branch lower
   that the window as a whole ranks higher (at 64 px the product grid's soft, early-yielding
   branch won on 4 frames and its fits predicted 8x worse: ``docs/results/search_check_small/``).

A rollout that fails (CFL or NaN after the allowed dt halvings, out of the domain) scores
``inf``; the simulator's kept dt-halving floor is restored afterwards, so the search leaves the
fit's substeps as they were. The cost is a few tens of forward rollouts of the window's first
frames (see ``seconds`` and ``rollouts`` in the result); :class:`~toolkit.physics.InversePhysicsModule`
logs a line and writes ``material_search.json`` to the run folder.
"""

from __future__ import annotations

import logging
import math
import time
from typing import TYPE_CHECKING, Any, Optional

import numpy as np
import torch

from materials.base import MaterialError, MaterialParam
from toolkit.mpm.config import SimulationError

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.physics.module import InversePhysicsModule

__all__ = ["coarse_search", "candidate_loss", "search_and_apply", "search_axis", "score_frames", "YIELD_PARAMS", "YIELD_STARTS", "BOUNDED_POINTS",
           "DEFAULT_FRAMES", "DEFAULT_REFINEMENTS", "MIN_GAIN"]

log = logging.getLogger(__name__)

#: parameters whose presence marks a yield surface (multi-start)
YIELD_PARAMS = frozenset({"yield_stress", "friction_angle"})
#: coordinate paths of a material with a yield surface
YIELD_STARTS = 2
#: grid points of a bounded (tanh / linear) parameter's search range
BOUNDED_POINTS = 5
#: grid step of a log10 parameter, decades
LOG10_STEP = 1.0
#: frames of the stage's window scored per candidate (evenly spaced, the window's last included)
DEFAULT_FRAMES = 4
#: halvings of the grid step around the best point
DEFAULT_REFINEMENTS = 2
#: a parameter moves from where it was only if that lowers the loss by more than this fraction
MIN_GAIN = 0.01


def search_axis(p: MaterialParam, fit_bounds: Optional[tuple[float, float]] = None) -> tuple[bool, float, float, int]:
    """The sweep of one parameter: ``(log, low, high, points)`` in its search coordinate.

    ``log`` True means the coordinate is log10 of the physical value; the physical range is
    ``p.search``, narrowed to ``fit_bounds`` (the fit's range, physical) where they overlap.

    Raises:
        ValueError: ``p`` has no search range.
    """
    if p.search is None:
        raise ValueError(f"parameter {p.name!r} has no search range (MaterialParam.search): it is not searched")
    log_axis = p.transform == "log10"
    lo, hi = p.search
    if fit_bounds is not None and max(lo, fit_bounds[0]) < min(hi, fit_bounds[1]):
        lo, hi = max(lo, fit_bounds[0]), min(hi, fit_bounds[1])
    if log_axis:
        lo, hi = math.log10(lo), math.log10(hi)
        n = max(2, int(round((hi - lo) / LOG10_STEP)) + 1)
    else:
        n = BOUNDED_POINTS
    return log_axis, float(lo), float(hi), n


def score_frames(window: int, count: int = DEFAULT_FRAMES) -> list[int]:
    """``count`` training frames of a window of ``window`` frames: evenly spaced from frame 1
    (frame 0 is the start, identical for every candidate), the window's last included."""
    if window <= 1:
        return [0]
    picks = np.linspace(1, window - 1, num=min(count, window - 1))
    return sorted({int(round(f)) for f in picks})


def _physical(p: MaterialParam, coord: float, log_axis: bool) -> float:
    v = 10.0**coord if log_axis else coord
    lo = p.low if p.transform != "log10" else 0.0
    if p.transform == "log10":
        return float(min(max(v, math.nextafter(p.low, math.inf)), p.high))
    return float(min(max(v, lo), p.high))


def _finite(x: float) -> Optional[float]:
    """JSON has no inf: a failed candidate's loss is recorded as None."""
    return x if math.isfinite(x) else None


def candidate_loss(module: "InversePhysicsModule", stage: Any, params: torch.Tensor, frames: list[int],
                   v0: Optional[torch.Tensor] = None) -> float:
    """The fit's own loss of ``stage`` (image + geometric terms, every training camera) on
    ``frames`` for one candidate: ``params`` the physical material parameters (in the material's
    order), ``v0`` the initial velocity (m/s; default the module's), everything else as the module
    holds it. Forward only; the simulator's kept dt-halving floor is restored afterwards.

    Raises:
        SimulationError, MaterialError: the rollout failed (CFL or NaN after the allowed halvings,
            out of the domain).
    """
    sim = module.simulator
    with torch.no_grad(), sim.substep_plan_restored():
        x0 = (module.particles0 + module.particle_offset).detach()
        v = module.v0.detach() if v0 is None else v0
        out = sim.rollout(x0, v, params, gravity=module.gravity.detach(), effect_params=module.effect_params.detach(),
                          n_frames=max(frames))
        return float(module.probe_losses(out.positions, stage, list(module.input.train_cameras), frames)["total"])


def coarse_search(module: "InversePhysicsModule", stage: Any, frames: int = DEFAULT_FRAMES,
                  refinements: int = DEFAULT_REFINEMENTS, starts: Optional[int] = None,
                  joint_yield: bool = False) -> dict:
    """Sweep the module's optimized material parameters and return the search record.

    Args:
        module: the fit, with positions, appearance and v0 as they are now (read, not changed).
        stage: the stage about to optimize ``M`` (its frame window and loss terms are used).
        frames: frames of the window scored per candidate (see :func:`score_frames`).
        refinements: halvings of the grid step around the best point of each parameter.
        starts: coordinate paths (multi-start); default :data:`YIELD_STARTS` for a material with a
            yield surface (:data:`YIELD_PARAMS`), else 1.
        joint_yield: for a material whose yield parameter is not its first, sweep the first
            parameter and the yield parameter together on their product grid (the yield
            parameter's grid plus its guess: 4 x 5 points for plasticine's E and tau_Y); paths
            start from the grid's best local minima (4-neighbour) as well as from the default's
            (the first parameter's line at the guess, a row of that grid) and go on
            coordinate-wise as before.

    Returns:
        a JSON-ready dict: ``parameters`` (names searched), ``frames`` (the search's frames),
        ``cameras``, ``joint_yield`` (whether the first sweep was the product grid),
        ``window_frames`` (where the product grid's paths were weighed against the default's pick;
        ``frames`` without them or when the window has no other frames), ``best_window_loss``,
        ``start`` and
        ``best`` (physical values), ``start_loss``, ``best_loss``, ``points`` (every candidate:
        ``params``, ``loss``, ``path`` and ``note`` for a failed rollout), ``paths`` (the end of
        each path with its ``origin``, ``"line"`` for the default's or ``"grid"`` for the product
        grid's, its ``loss`` and, where it was scored on the window, ``window_loss``),
        ``rollouts`` (the window's included) and
        ``seconds``. The module is not changed.
    """
    t0 = time.perf_counter()
    mat = module.material
    names = [n for n in module.optimized_material if mat.param(n).search is not None]
    window = stage.window(module.input.n_train)
    picked = score_frames(window, frames)
    cams = list(module.input.train_cameras)
    fit_bounds = getattr(module, "fit_bounds", {})
    axes = {n: search_axis(mat.param(n), fit_bounds.get(n)) for n in names}
    base_phys = module.material_params().detach().clone()
    index = {n: mat.param_names.index(n) for n in names}
    start = {n: float(base_phys[index[n]]) for n in names}
    to_coord = {n: (lambda v, a=axes[n]: math.log10(v) if a[0] else v) for n in names}
    cache: dict[tuple, float] = {}
    points: list[dict] = []

    def rollout_loss(phys: dict[str, float], frames: list[int]) -> tuple[float, Optional[str]]:
        params = base_phys.clone()
        for n in names:
            params[index[n]] = phys[n]
        try:
            loss = candidate_loss(module, stage, params, frames)
        except (SimulationError, MaterialError) as err:  # CFL/NaN after the halvings, out of the domain
            return math.inf, f"{type(err).__name__}: {str(err)[:160]}"
        return (loss, None) if math.isfinite(loss) else (math.inf, "non-finite loss")

    def physical(coords: dict[str, float]) -> dict[str, float]:
        return {n: _physical(mat.param(n), coords[n], axes[n][0]) for n in names}

    def evaluate(coords: dict[str, float], path: int) -> float:
        phys = physical(coords)
        key = tuple(round(to_coord[n](phys[n]), 5) for n in names)  # float32 starts meet grid points
        if key in cache:
            return cache[key]
        loss, note = rollout_loss(phys, picked)
        cache[key] = loss
        rec = {"params": phys, "loss": _finite(loss), "path": path}
        if note:
            rec["note"] = note
        points.append(rec)
        return loss

    def line(coords: dict, name: str, grid, path: int) -> list[tuple[float, float]]:
        return [(c, evaluate({**coords, name: float(c)}, path)) for c in grid]

    def refine(coords: dict, name: str, step: float, path: int) -> dict:
        best_c, best_l = coords[name], evaluate(coords, path)
        lo_r, hi_r = axes[name][1], axes[name][2]
        for _ in range(refinements):
            step /= 2
            for c in (best_c - step, best_c + step):
                if not lo_r - 1e-9 <= c <= hi_r + 1e-9:
                    continue
                loss = evaluate({**coords, name: c}, path)
                if loss < best_l:
                    best_c, best_l = c, loss
        return {**coords, name: best_c}

    current = {n: to_coord[n](start[n]) for n in names}
    start_loss = evaluate(current, 0)
    paths: list[dict] = []
    if names:
        first = names[0]
        log_axis, lo, hi, n_pts = axes[first]
        grid = np.linspace(lo, hi, n_pts)
        n_starts = starts if starts is not None else (YIELD_STARTS if set(names) & YIELD_PARAMS else 1)
        partner = next((n for n in names[1:] if n in YIELD_PARAMS), None) if joint_yield else None
        # the default's paths start at the best local minima of the first parameter's line at the
        # others' guesses; with joint_yield the product grid's minima start further paths
        origins = [(o, "line") for o in _line_minima(line(current, first, grid, 0), current, first, max(1, n_starts))]
        if partner is not None:
            # the yield parameter's guess is a row of the grid too: the default's line is part of it
            rows = np.unique(np.append(np.linspace(axes[partner][1], axes[partner][2], axes[partner][3]),
                                       current[partner]))
            for o in _grid_minima(evaluate, current, first, grid, partner, rows, max(1, n_starts)):
                if all(o != seen for seen, _ in origins):
                    origins.append((o, "grid"))
        step0 = float(grid[1] - grid[0]) if len(grid) > 1 else 1.0
        def settle(before: dict, after: dict, path: int) -> dict:
            """Keep a coordinate's move only if it lowers the loss by more than MIN_GAIN (a flat,
            undetermined direction leaves the parameter where it was)."""
            return after if evaluate(after, path) < (1 - MIN_GAIN) * evaluate(before, path) else before

        for k, (origin, kind) in enumerate(origins):
            coords = settle(current, refine(origin, first, step0, k), k)
            for name in names[1:]:
                _, lo_n, hi_n, n_n = axes[name]
                g = np.linspace(lo_n, hi_n, n_n)
                best = min(line(coords, name, g, k), key=lambda cl: cl[1])
                coords = settle(coords, refine({**coords, name: float(best[0])}, name, float(g[1] - g[0]), k), k)
            paths.append({"path": k, "origin": kind, "coords": coords, "loss": evaluate(coords, k)})
    # the default's pick: the start or its best path end, by the search's frames (a tie keeps the
    # start); a product-grid path's end replaces it only if it is lower by more than MIN_GAIN on
    # every frame of the window (the few search frames can rank a branch lower that the window as a
    # whole ranks higher)
    whole = score_frames(window, window)
    final = [{"path": None, "origin": "start", "coords": current, "loss": start_loss}] + paths
    chosen = min((c for c in final if c["origin"] != "grid"), key=lambda c: c["loss"])
    extra = [c for c in final if c["origin"] == "grid"]
    on_window = bool(extra) and whole != picked
    for cand in ([chosen] + extra) if extra else []:
        cand["window_loss"] = rollout_loss(physical(cand["coords"]), whole)[0] if on_window else cand["loss"]
    if extra:
        best_extra = min(extra, key=lambda c: c["window_loss"])
        if best_extra["window_loss"] < (1 - MIN_GAIN) * chosen["window_loss"]:
            chosen = best_extra
    best = physical(chosen["coords"])
    best_loss = chosen["loss"]
    return {
        "material": mat.name, "parameters": names, "frames": picked, "cameras": cams, "stage": stage.name,
        "joint_yield": bool(names) and partner is not None,
        "start": start, "start_loss": _finite(start_loss), "best": best, "best_loss": _finite(best_loss),
        "window_frames": whole if extra else picked,
        "best_window_loss": _finite(chosen.get("window_loss", best_loss)),
        "paths": [{"path": p["path"], "origin": p["origin"], "loss": _finite(p["loss"]),
                   **({"window_loss": _finite(p["window_loss"])} if "window_loss" in p else {}),
                   "params": physical(p["coords"])} for p in paths],
        "points": points, "rollouts": len(points) + (1 + len(extra) if on_window else 0),
        "seconds": time.perf_counter() - t0,
        "iteration": int(module.curriculum_step),
    }


def _grid_minima(evaluate, current: dict, first: str, grid_a, second: str, grid_b, count: int) -> list[dict]:
    """Score the product grid of ``first`` x ``second`` (path 0) and return the coordinates of its
    ``count`` lowest 4-neighbour local minima (a point no higher than the grid points beside it)."""
    table = np.array([[evaluate({**current, first: float(a), second: float(b)}, 0) for b in grid_b] for a in grid_a])
    minima = []
    for i in range(table.shape[0]):
        for j in range(table.shape[1]):
            beside = [table[i + di, j + dj] for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1))
                      if 0 <= i + di < table.shape[0] and 0 <= j + dj < table.shape[1]]
            if all(table[i, j] <= b for b in beside):
                minima.append((table[i, j], i, j))
    minima.sort()
    return [{**current, first: float(grid_a[i]), second: float(grid_b[j])} for _, i, j in minima[:count]] or [current]


def _line_minima(scored: list[tuple[float, float]], current: dict, first: str, count: int) -> list[dict]:
    """The ``count`` lowest local minima of a line sweep ``[(coordinate, loss)]`` of ``first`` (an
    end counts when it is lower than its one neighbour), as starts ``{**current, first: coordinate}``;
    the line's first point when none is finite."""
    minima = [i for i in range(len(scored)) if (i == 0 or scored[i][1] <= scored[i - 1][1])
              and (i == len(scored) - 1 or scored[i][1] <= scored[i + 1][1])]
    return [{**current, first: float(scored[i][0])} for i in sorted(minima, key=lambda i: scored[i][1])[:count] or [0]]


def _loss_text(x: Optional[float]) -> str:
    return "failed" if x is None else f"{x:.4g}"


def search_and_apply(module: "InversePhysicsModule", stage: Any, folder: Optional[str] = None, **options) -> dict:
    """Run :func:`coarse_search`, start the module's material there, log a line and write the record.

    The optimized raw parameters and ``material_raw_fixed`` (where the uncertainty's prior is
    centred: where the parameters start) are set to the best point. The record goes to
    ``folder/material_search.json`` (atomically) when ``folder`` is given.

    Returns:
        the record of :func:`coarse_search`.
    """
    result = coarse_search(module, stage, **options)
    mat = module.material
    with torch.no_grad():
        for n, v in result["best"].items():
            raw = mat.param(n).to_raw(v).to(module.material_raw[n].device)
            module.material_raw[n].data.copy_(raw)
            module.material_raw_fixed[mat.param_names.index(n)] = raw
    fmt = ", ".join(f"{n} {v:.4g}" for n, v in result["best"].items())
    was = ", ".join(f"{n} {v:.4g}" for n, v in result["start"].items())
    log.info("material starts at the coarse-search best %s (loss %s; the guess %s: %s): %d rollouts on frames %s, %.1f s",
             fmt or "-", _loss_text(result["best_loss"]), was or "-", _loss_text(result["start_loss"]), result["rollouts"],
             result["frames"], result["seconds"])
    if folder is not None:
        from pathlib import Path

        from toolkit.atomic import write_json

        Path(folder).mkdir(parents=True, exist_ok=True)
        write_json(Path(folder) / "material_search.json", result)
    return result

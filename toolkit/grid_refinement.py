"""Fit again on a grid of half the spacing when the grid check says the estimate depends on the grid.

``RunSettings.refine_grid`` (``projo4d run --refine-grid / --no-refine-grid``; default ``"auto"``:
on CUDA only) adds one step after the run: when the
grid check (:mod:`toolkit.physics.grid_check`) finds that halving dx moves the training frames by
more than the fit's misfit, or when the uncertainty's grid term (:mod:`toolkit.physics.grid_term`)
finds that it moves a fitted material parameter by more than the parameter's posterior standard
deviation (:func:`refinement_reason`), the physics is fitted again at ``dx / 2`` in the sub-folder
``OUT/refined/``, a run folder of its own (its own ``run.json``, ``summary.json`` and report):

* it shares the parent's stage 0 (``refined/stage0`` links to ``../stage0``; nothing is trained
  again) and builds its continuum at the finer spacing (particles at ``dx / 4``);
* the material parameters and v0 start at the parent's estimate (``material_init="given"``: no
  coarse search on the finer grid), with the parent's curriculum, each stage's iterations times
  ``RunSettings.refine_iterations`` (``--refine-iterations``; :func:`refined_curriculum`);
* it is not refined again, whatever its own grid check says.

The refinement has about 8x the particles and nodes and twice the substeps of the parent's
physics stage. On a GPU that is not full at dx 0.02 m this costs far less than 8x (one full-size
elastic scene on an H100: 176 s at dx 0.02 m, 247 s at 0.01 m with two runs sharing the card;
1.8-3.4x with five sharing an H200, which the refined fits filled), so
``"auto"`` refines on CUDA devices; on a CPU it costs the full 8x, so ``"auto"`` only says that the
check failed and how to refine (``--refine-grid``). Why it is worth it where the grid check fails:
the full-size letter T of the whole-scene benchmark came out 0.60 decades soft in E at dx 0.02 m
and 0.16 at 0.01 m (``docs/limits.md``); from the true body, the five full-size elastic scenes'
mean log E error fell from 0.52 to 0.24 (``docs/results/paper_size.md``, round 15).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Optional

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.pipeline import RunSettings

__all__ = ["REFINED_FOLDER", "grid_moved_parameters", "refined_curriculum", "refinement_reason", "needs_refinement", "refines_on",
           "refined_settings", "refine_grid", "refine_after_fit"]

#: the refined run's sub-folder of the run folder
REFINED_FOLDER = "refined"

log = logging.getLogger(__name__)


def grid_moved_parameters(summary: dict) -> list[str]:
    """The fitted material parameters (not v0, gravity or effects; not fixed) whose estimate the
    uncertainty's grid term (:mod:`toolkit.physics.grid_term`) moves by more than
    :data:`~toolkit.physics.grid_term.GRID_SHIFT_SD` posterior standard deviations on a grid of half
    the spacing (the rows' ``grid_shift_sd``; the same rule as the parameter's note), each as
    ``"name (x.x sd)"``."""
    from toolkit.physics.grid_term import GRID_SHIFT_SD

    out = []
    for row in summary.get("parameters") or []:
        name, shift = str(row.get("parameter", "")), row.get("grid_shift_sd")
        if shift is None or "fixed" in str(row.get("label", "")) or name.startswith(("v0_", "gravity_")) or "." in name:
            continue
        if float(shift) > GRID_SHIFT_SD:
            out.append(f"{name} ({float(shift):.1f} sd)")
    return out


def refinement_reason(summary: dict, setting: bool | str = True) -> Optional[str]:
    """Why the run is fitted again at the grid check's ``fine_dx``, or None when it is not. The
    grid check must have run (a skipped check means the finer grid does not fit in memory); then:

    * ``setting="always"``: whatever the check found;
    * the check failed: halving dx moves the training frames by more than the fit's misfit;
    * the grid term moved a fitted material parameter by more than its standard deviation
      (:func:`grid_moved_parameters`): the check compares the finer grid's shift with the misfit,
      not with a parameter's bias, and fits of sand at the paper's size that passed it kept a
      friction angle about 7 degrees low that the finer grid moves toward the truth."""
    grid = summary.get("grid_check") or {}
    if not grid.get("fine_dx") or "skipped" in grid:
        return None
    if setting == "always":
        return "refine_grid='always'"
    if grid.get("converged") is False:
        return "the grid check failed"
    moved = grid_moved_parameters(summary)
    if moved:
        return "a grid of half the spacing moves " + ", ".join(moved)
    return None


def needs_refinement(summary: dict, setting: bool | str = True) -> bool:
    """Whether the run is fitted again at the grid check's ``fine_dx`` (:func:`refinement_reason`)."""
    return refinement_reason(summary, setting) is not None


def refines_on(setting: bool | str, device: str) -> bool:
    """Whether ``RunSettings.refine_grid`` refines a run on ``device`` (``"cpu"``, ``"cuda"``,
    ``"cuda:N"``) once it needs it (:func:`needs_refinement`): ``"auto"`` on CUDA only; ``True`` and
    ``"always"`` on any device."""
    if setting == "always":
        return True
    if setting == "auto":
        return str(device).startswith("cuda")
    return bool(setting)


def refined_curriculum(s: "RunSettings", fraction: float) -> tuple[str, dict]:
    """The refined run's curriculum ``(curriculum, curriculum_options)``: the parent's, or, when
    ``fraction < 1``, its stages as a schedule string (:mod:`strategies.schedule`) with each stage's
    iterations times ``fraction`` (rounded, at least 1); windows, batches, losses and the ``[S]``
    rule are kept. A curriculum with a stage learning-rate multiplier (which the schedule string
    cannot hold) is kept whole, with a warning."""
    if fraction >= 1:
        return s.curriculum, dict(s.curriculum_options)
    from materials import get_material
    from strategies.schedule import format_stage
    from toolkit.pipeline import resolve_curriculum

    key = get_material(s.material, **(s.material_options or {})).registry_name or None
    stages = resolve_curriculum(s.curriculum, s.curriculum_options).stages(key)
    if any(st.lr_scale for st in stages):
        log.warning("refine_iterations=%g: curriculum %r has a stage learning-rate multiplier; the refined fit runs it "
                    "whole", fraction, s.curriculum)
        return s.curriculum, dict(s.curriculum_options)
    scaled = [dataclasses.replace(st, iterations=max(1, round(st.iterations * fraction))) for st in stages]
    return ",".join(format_stage(st) for st in scaled), {}


def refined_settings(s: "RunSettings", estimate: dict, fine_dx: float) -> "RunSettings":
    """The settings of the refined run: ``s`` at ``sim.dx = fine_dx`` in ``s.out/refined``, starting
    at ``estimate`` (:meth:`~toolkit.physics.InversePhysicsModule.estimate`: material parameters, v0,
    effect strengths, and gravity when it is fitted), without a coarse search and without a further
    refinement. A continuum spacing the parent
    set explicitly is halved too; the curriculum is :func:`refined_curriculum` of
    ``s.refine_iterations``."""
    params = {k: float(v) for k, v in estimate["params"].items()}
    options = {**(s.model_options or {}), "material_init": "given", "v0_init": [float(v) for v in estimate["v0"]]}
    if estimate.get("effects"):
        options["effects"] = estimate["effects"]
    sim = {**s.sim, "dx": float(fine_dx)}
    if s.optimize_gravity:
        sim["gravity"] = [float(g) for g in estimate["gravity"]]
    continuum = dict(s.continuum)
    if "grid_size" in continuum:
        continuum["grid_size"] = float(continuum["grid_size"]) / 2
    curriculum, curriculum_options = refined_curriculum(s, float(s.refine_iterations))
    return dataclasses.replace(s, out=str(Path(s.out) / REFINED_FOLDER), sim=sim, curriculum=curriculum,
                               curriculum_options=curriculum_options,
                               initial_params={**(s.initial_params or {}), **params}, model_options=options,
                               continuum=continuum, refine_grid=False)


def refine_grid(s: "RunSettings", summary: dict, estimate: dict, device: str = "cuda",
                stage0: Optional[Path] = None) -> Optional[dict]:
    """Run the refined fit when :func:`needs_refinement` and :func:`refines_on` ``device`` (else
    None); returns its summary (also in ``s.out/refined/summary.json``). The parent's stage 0
    (``stage0``, default ``s.out/stage0``; a benchmark fit's is its prepare job's) is shared by a
    link, so it is not trained again."""
    from toolkit.pipeline import run_pipeline
    from toolkit.run_folder import claim_run_folder

    reason = refinement_reason(summary, s.refine_grid)
    if reason is None:
        return None
    if not refines_on(s.refine_grid, device):
        # a failed check is a warning; the grid term's shift is already in the parameter's note
        level = logging.WARNING if summary["grid_check"].get("converged") is False else logging.INFO
        log.log(level, "%s: `--refine-grid` would fit again at dx %g m from this estimate (not by default on %s: about 8x "
                "this physics stage)", reason, summary["grid_check"]["fine_dx"], device)
        return None
    child = refined_settings(s, estimate, summary["grid_check"]["fine_dx"])
    out = Path(child.out)
    claim_run_folder(child, "auto")  # before the link: a folder holding only stage0/ is not a run
    stage0 = Path(s.out) / "stage0" if stage0 is None else Path(stage0)
    if stage0.is_dir() and not (out / "stage0").exists():
        os.symlink(os.path.relpath(stage0, out), out / "stage0", target_is_directory=True)
    log.warning("%s: fitting again at dx %g m in %s (refine_grid=%s)", reason, child.sim["dx"], out, s.refine_grid)
    return run_pipeline(child, mode="auto")


def refine_after_fit(s: "RunSettings", summary: dict, estimate: dict, device: str, run: Path,
                     stage0: Optional[Path] = None) -> Optional[dict]:
    """:func:`refine_grid` for a finished fit in ``run`` (``projo4d run`` and a benchmark fit alike):
    when a refined fit ran, ``summary`` gains ``refined`` (its folder, :func:`refinement_reason` and
    its summary) and
    ``timings_s.refine_s``, and is written again to ``run/summary.json`` (atomically). Returns the
    refined summary, or None.

    A refined fit that fails (a :class:`~toolkit.mpm.config.SimulationError` such as a grid grown
    past the memory limit, CUDA out of memory, an input error at the finer spacing) does not lose
    the first fit: ``summary["refined"]`` records ``{"out", "failed": "<error type>: <message>"}``,
    the first fit's result stands, and None is returned. A stop request
    (:class:`~toolkit.checkpointing.RunInterrupted`) still propagates."""
    import time

    from toolkit.atomic import write_json

    t = time.perf_counter()
    refined, record = None, None
    reason = refinement_reason(summary, s.refine_grid)
    try:
        refined = refine_grid(s, summary, estimate, device, stage0=stage0)
        if refined is not None:
            record = {"out": str(run / REFINED_FOLDER), "reason": reason, "summary": refined}
    except (RuntimeError, ValueError) as err:  # a simulation, memory or input error; a stop request is not one
        record = {"out": str(run / REFINED_FOLDER), "reason": reason, "failed": f"{type(err).__name__}: {err}"}
        log.error("the refined fit failed; the first fit's result stands (%s): %s", run / "summary.json", record["failed"])
    summary["refined"] = record
    if record is not None:
        summary["timings_s"] = {**(summary.get("timings_s") or {}), "refine_s": time.perf_counter() - t}
    write_json(run / "summary.json", summary)
    return refined

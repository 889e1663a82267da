"""The whole job for one scene: stage 0, particle continuum, a strategy, prediction, metrics, report.

Run folder layout (every step resumes or is skipped when its output exists)::

    RUN/
      run.json              the run's identity (scene fingerprint, result-changing settings; toolkit.run_folder)
      settings.json         the resolved settings of this run
      stage0/               4D Gaussians checkpoints (last.ckpt), gaussians.ply (canonical, 3DGS layout)
      continuum/            particles.ply, surface_XXX.ply, stats.json
      physics_input.pt      the physics stages' input (Gaussians, particles, surfaces, images)
      physics/              checkpoints/, logs/, estimate.json, history.json
      evaluation/           evaluation.json, prediction.npz, renders.npz
      report/               trajectories.png, per_frame.png, prediction_vs_truth.mp4 (+ _future.png)
      summary.json          estimated parameters next to the truth, headline metrics, timings
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Optional

import torch

from toolkit.atomic import CorruptArtifactError, set_aside, write_json
from toolkit.checkpointing import newest_intact_checkpoint
from toolkit.errors import UserError
from toolkit.run_settings import RunSettings  # noqa: F401 (re-exported: defined without torch)
from toolkit.run_summary import format_summary, run_summary  # noqa: F401 (format_summary re-exported)

__all__ = ["RunSettings", "run_pipeline", "load_fitted_module"]

log = logging.getLogger(__name__)


def _device(name: str) -> str:
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def _accelerator(device: str) -> str:
    return "gpu" if device.startswith("cuda") else "cpu"


def _stage0_module(spec, renderer: str, seed: int):
    """The stage-0 module of a preset name (consistent schedule and network) or a schedule dict."""
    from toolkit.scene.stage0 import Gaussians4DModule

    kw = {"seed": seed}
    if renderer != "auto":
        kw["renderer"] = renderer
    if spec in ("full", "tiny"):
        return Gaussians4DModule.from_preset(spec, **kw)
    from toolkit.scene.stage0 import Stage0Schedule

    spec = dict(spec)
    preset = spec.pop("preset", "full")
    base = (Stage0Schedule.tiny() if preset == "tiny" else Stage0Schedule.full()).to_dict()
    return Gaussians4DModule.from_preset(preset, schedule={**base, **spec}, **kw)


def fit_stage0_step(s: RunSettings, scene, run: Path, timings: dict):
    """Stage 0 of ``s`` in ``run/stage0``: resumes from its newest intact checkpoint (a finished
    ``last.ckpt`` is loaded, not trained again), then writes ``gaussians.ply`` (canonical Gaussians
    at the first training time, 3DGS layout). ``timings["stage0_s"]`` gets the seconds it took.

    Returns:
        ``(module, views)``: the trained :class:`~toolkit.scene.stage0.Gaussians4DModule` on the
        run's device in eval mode, and its training views.
    """
    from toolkit.scene.export import save_ply
    from toolkit.scene.stage0 import Stage0DataModule, fit_stage0

    device = _device(s.device)
    data = Stage0DataModule(scene, cameras=s.cameras, n_train=training_frames(scene, s.n_train), downscale=s.downscale)
    views = data.training_views()
    stage0_dir = run / "stage0"
    t = time.perf_counter()
    module = _stage0_module(s.stage0, s.renderer, s.seed)
    every = max(500, module.schedule.iterations // 20)
    module = fit_stage0(data, module, out_dir=stage0_dir, ckpt_path=newest_intact_checkpoint(stage0_dir), checkpoint_every=every,
                        accelerator=_accelerator(device), progress_bar=True)
    for old in stage0_dir.glob("step_*.ckpt"):  # finished: last.ckpt is enough
        old.unlink()
    timings["stage0_s"] = time.perf_counter() - t
    module = module.to(device).eval()
    save_ply(stage0_dir / "gaussians.ply", module, time=float(views.times[0]))
    check_stage0_coverage(module, views, stage0_dir)
    return module, views


def check_stage0_coverage(module, views, stage0_dir: Path) -> Optional[dict]:
    """Writes ``stage0_dir/coverage.json`` (:func:`toolkit.scene.coverage.coverage_record`: how
    much of each training frame's masks the Gaussians cover) and warns, naming the frames, when
    stage 0 lost the object in some of them. Returns the record (None without masks)."""
    from toolkit.scene.coverage import coverage_record, lost_object_message, mask_coverage

    if views.masks is None:
        return None
    dev = module.gaussians.means.device
    record = coverage_record(mask_coverage(module, views.to(dev)))
    write_json(stage0_dir / COVERAGE_FILE, record)
    if record["lost_frames"]:
        log.warning(lost_object_message(record, stage0_dir / COVERAGE_FILE))
    return record


#: stage 0's mask coverage record, in the run's ``stage0`` folder
COVERAGE_FILE = "coverage.json"


class EmptyContinuumError(UserError):
    """Stage 0's Gaussians gave the continuum no particles (no interior voxel in the first frame)."""


def empty_continuum_message(run: Path, n_views: int, reason: str = "") -> str:
    """What went wrong when the continuum is empty: the step that emptied it (``reason``, from
    :meth:`~toolkit.scene.continuum.Continuum.empty_reason`), stage 0's last logged quality and the fix."""
    from toolkit.stage0_only import last_logged_metrics

    logged = last_logged_metrics(run / "stage0" / "logs")
    psnr, count = logged.get("train/psnr"), logged.get("train/n_gaussians")
    quality = (f"stage 0 ended at PSNR {psnr:.1f} dB" if psnr is not None else "stage 0 logged no PSNR") + (
        f" with {int(count)} Gaussians" if count is not None else "")
    why = f"; {reason} (counts per step: {run / 'continuum' / 'stats.json'})" if reason else ""
    return (f"the continuum found no particles: no voxel of the first frame is inside the object (the Gaussians' "
            f"density, carved by the masks of the {n_views} training views){why}; {quality} ({run / 'stage0' / 'logs'}). "
            "Usually stage 0 has not converged: train it longer (run.stage0 'full' or more iterations, then --overwrite) "
            "or with another --seed; else check the training cameras' masks and run.continuum (density_min)")


def build_physics_input(s: RunSettings, run: Path, timings: dict) -> Path:
    """Stage 0 + continuum (or the oracle), written as ``run/physics_input.pt``."""
    from toolkit.physics.inputs import PhysicsInput, load_all_images
    from toolkit.physics.world_checks import WORLD_META_FILE, check_world, world_meta, write_world_meta
    from toolkit.data.exclusion import exclusion_meta

    path = run / "physics_input.pt"
    if path.is_file():
        try:
            PhysicsInput.load(path)
            return path
        except CorruptArtifactError as err:
            set_aside(path, str(err))
    device = _device(s.device)
    from toolkit.data import load_scene
    from toolkit.scene.silhouette_agreement import check_scene

    scene = load_scene(s.scene)  # the fitting cameras' masks must agree (advice, before any training)
    check_scene(scene, s.cameras, range(training_frames(scene, s.n_train)), run / "silhouettes.json")
    if s.geometry == "oracle":
        from toolkit.physics.oracle import oracle_input

        t = time.perf_counter()
        inp = oracle_input(s.scene, cameras=s.cameras, n_train=s.n_train, particle_spacing=s.sim.get("dx", 0.02) / 2,
                           downscale=s.downscale, dx=float(s.sim.get("dx", 0.02)))
        timings["oracle_s"] = time.perf_counter() - t
        write_world_meta(run / WORLD_META_FILE, inp.meta["world"])
        inp.save(path)
        return path

    from toolkit.scene.continuum import ContinuumConfig, build_continuum

    module, views = fit_stage0_step(s, scene, run, timings)
    t0 = float(views.times[0])
    coverage_file = run / "stage0" / COVERAGE_FILE
    coverage = json.loads(coverage_file.read_text()) if coverage_file.is_file() else None

    t = time.perf_counter()
    dx = float(s.sim.get("dx", 0.02))
    cfg = {"grid_size": 8 * dx / 2, "candidate_level": 3, "final_level": 3, **s.continuum}
    with torch.no_grad():
        cont = build_continuum(module, views.to(device), config=ContinuumConfig.from_dict(cfg), device=device,
                               ground=(scene.world.ground_point, scene.world.ground_normal),
                               lost_frames=(coverage or {}).get("lost_frames", []))
    cont.save(run / "continuum")
    timings["continuum_s"] = time.perf_counter() - t
    log.info(cont.summary())
    if cont.particles.shape[0] == 0:
        raise EmptyContinuumError(empty_continuum_message(run, len(views.camera_indices), cont.empty_reason()))
    with torch.no_grad():
        g0 = module.gaussians_at(t0).detach()
    g0 = g0.to("cpu")
    images, masks = load_all_images(scene, s.downscale)
    T = scene.n_frames
    surfaces = list(cont.surfaces) + [torch.zeros((0, 3))] * (T - len(cont.surfaces))
    lost = [f for f in (coverage or {}).get("lost_frames", []) if f > 0]  # frame 0 built the particles: kept
    if lost:  # a model that lost the object there gives no measurement of the surface: no geometric loss
        from toolkit.scene.coverage import format_frames

        log.warning("the stage-0 surfaces of training frames %s are left out of the geometric loss (stage 0 lost the "
                    "object there; %s)", format_frames(lost), run / "stage0" / COVERAGE_FILE)
        surfaces = [torch.zeros((0, 3)) if i in lost else sf for i, sf in enumerate(surfaces)]
    gt = None
    if scene.ground_truth is not None:
        g = scene.ground_truth
        gt = {"material": g.material, "params": dict(g.params), "v0": g.v0, "gravity": g.gravity, "effects": g.effects,
              "point_clouds": [str(p) for p in g.point_clouds], "to_canonical": scene.to_canonical.to_dict()}
    cams = scene.cameras.scaled(1.0 / s.downscale) if s.downscale > 1 else scene.cameras
    inp = PhysicsInput(gaussians=g0, particles=cont.particles.float(), particle_volume=cont.particle_volume, surfaces=surfaces,
                       cameras=cams, train_cameras=list(views.camera_indices), images=images, masks=masks,
                       times=torch.as_tensor(scene.times, dtype=torch.float32), n_train=len(views.frames), ground_truth=gt,
                       meta={"scene_root": str(s.scene), "source": "stage0", "continuum": cont.stats, "stage0_coverage": coverage,
                             "world": world_meta(scene), **exclusion_meta(scene, s.downscale)})
    check_world(inp.particles.numpy(), surfaces, scene.times, dx, inp.meta["world"])  # scene in the wrong world: stop here
    write_world_meta(run / WORLD_META_FILE, inp.meta["world"])
    inp.save(path)
    return path


def resolve_curriculum(spec: str, options: Optional[dict] = None):
    """A strategy from a name, a schedule string or ``package.module.Class`` (+ options)."""
    from strategies import get_strategy

    options = dict(options or {})
    if ":" in spec:
        return get_strategy(spec)
    if "." in spec:
        import importlib

        module_name, _, cls_name = spec.rpartition(".")
        try:
            cls = getattr(importlib.import_module(module_name), cls_name)
        except (ImportError, AttributeError) as err:
            raise ValueError(f"cannot import strategy class {spec!r}: {err}") from None
        return get_strategy(cls, **options)
    return get_strategy(spec, **options)


def training_frames(scene, n_train: Optional[int]) -> int:
    """Frames ``[0, n_train)`` are fitted: the given number, else the split the scene records
    (the generator's ``ground_truth.json``), else ``min(14, T - 1)`` (PAC-NeRF's 14 + future)."""
    T = scene.n_frames
    if n_train is not None:
        if not 1 <= n_train <= T:
            raise ValueError(f"n_train must be in [1, {T}] for {scene.root}, got {n_train}")
        return n_train
    gt = scene.ground_truth
    recorded = (gt.extra.get("frames", {}) or {}).get("n_train_frames") if gt is not None else None
    if recorded:
        return int(recorded)
    return max(1, min(14, T - 1))


def load_fitted_module(run: str | Path, device: str = "cpu", checkpoint: str = "last.ckpt"):
    """The fitted :class:`~toolkit.physics.InversePhysicsModule` of a run folder.

    ``checkpoint`` names the file in ``physics/checkpoints`` (default the last; a kept stage end
    such as ``stage_01_end.ckpt`` gives the fit as it stood then)."""
    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule

    run = Path(run)
    ckpt_path = run / "physics" / "checkpoints" / checkpoint
    if not ckpt_path.is_file():
        raise FileNotFoundError(f"{ckpt_path} does not exist: fit the run first (projo4d run)")
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    hp = dict(ckpt["hyper_parameters"])
    sim = SimConfig(**{k: v for k, v in hp.pop("sim").items() if k != "frame_dt"})
    for k in ("input_path", "curriculum_name"):
        hp.pop(k, None)
    hp.setdefault("gaussian_shape", "rigid")  # runs saved before the option existed kept their Gaussians' shapes
    hp.setdefault("fit_ranges", "valid")  # runs saved before fit ranges existed had none
    module = InversePhysicsModule(str(run / "physics_input.pt"), sim=sim, **hp)
    module.load_state_dict(ckpt["state_dict"], strict=False)
    module.on_load_checkpoint(ckpt)
    return module.to(device)


def _restore_finished_fit(module, physics_dir: Path, ckpt_path: Optional[Path]) -> bool:
    """Load ``ckpt_path`` into ``module`` if that fit already ran its whole curriculum."""
    est_path = physics_dir / "estimate.json"
    if ckpt_path is None or not est_path.is_file():
        return False
    try:
        finished = json.loads(est_path.read_text()).get("iterations") == module.total_iterations
    except json.JSONDecodeError:
        finished = False
    if not finished:
        return False
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    if ckpt.get("projo4d", {}).get("curriculum_step") != module.total_iterations:
        return False
    module.load_state_dict(ckpt["state_dict"], strict=False)
    module.on_load_checkpoint(ckpt)
    log.info("physics fit in %s is complete: loaded its last checkpoint", physics_dir)
    return True


def run_pipeline(settings: RunSettings, mode: str = "auto") -> dict:
    """Run every step for one scene; returns (and writes) ``summary.json``.

    Every setting is checked first and the run folder's identity after that (see
    :mod:`toolkit.run_folder`; ``mode`` is ``"auto"``, ``"resume"`` or ``"overwrite"``), so a mistake
    costs seconds and writes nothing. The first Ctrl-C or SIGTERM saves a checkpoint at the end of
    the current iteration and raises :class:`~toolkit.checkpointing.RunInterrupted`; rerunning the
    same command resumes from it.
    """
    from toolkit.checkpointing import graceful_interrupts
    from toolkit.run_folder import claim_run_folder

    s = settings
    s.validate()
    claim_run_folder(s, mode)
    with graceful_interrupts():
        return _run_steps(s)


def _stop_if_interrupted(where: str) -> None:
    """Honour a Ctrl-C / SIGTERM that arrived after the last point where a step checks for one
    (e.g. during a fit's last iteration or its uncertainty): stop with exit status 130 instead of
    going on to the next step."""
    from toolkit.checkpointing import RunInterrupted, interrupt_requested

    if interrupt_requested() is not None:
        raise RunInterrupted(f"{interrupt_requested()} received: stopped {where}")


def _run_steps(s: RunSettings) -> dict:
    from toolkit.physics.fit import fit_physics
    from toolkit.threads import configure_threads

    # several runs on one machine must not each take every core (issue #25), on CPU and CUDA alike
    threads = configure_threads(s.threads, device=_device(s.device), name="RunSettings.threads (--threads)")
    run = Path(s.out)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    device = _device(s.device)

    input_path = build_physics_input(s, run, timings)
    _stop_if_interrupted("after stage 0 (physics_input.pt is saved)")
    module = make_physics_module(s, input_path)
    t = time.perf_counter()
    ckpt = newest_intact_checkpoint(run / "physics" / "checkpoints")
    if not _restore_finished_fit(module, run / "physics", ckpt):
        fit_physics(module, run / "physics", resume=ckpt, checkpoint_every=s.checkpoint_every, accelerator=_accelerator(device))
    _stop_if_interrupted("after the physics fit (its result is saved); the evaluation is next")
    timings["physics_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t_all
    summary = evaluate_and_report(module, run, s, timings)
    summary["threads"] = threads.to_dict()
    write_json(run / "summary.json", summary)
    if s.refine_grid is not False:
        from toolkit.grid_refinement import refine_after_fit

        _stop_if_interrupted("after the run (its summary is saved); the refined fit is next")
        refine_after_fit(s, summary, module.estimate(), device, run)
    return summary


def make_physics_module(s: RunSettings, input_path: str | Path):
    """The :class:`~toolkit.physics.InversePhysicsModule` of a run's settings and physics input."""
    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule

    from toolkit.physics.world_checks import WORLD_META_FILE, read_world_meta

    world = read_world_meta(Path(input_path).parent / WORLD_META_FILE) or {}
    defaults = {"auto_dt_halving": True, **({"gravity": world["gravity"]} if world.get("gravity") else {})}
    sim = SimConfig(**{**defaults, **s.sim})  # sim.gravity (canonical frame) overrides the scene's world
    return InversePhysicsModule(str(input_path), material=s.material, material_options=s.material_options,
                                initial_params=s.initial_params, optimize_params=s.optimize_params,
                                curriculum=resolve_curriculum(s.curriculum, s.curriculum_options), renderer=s.renderer,
                                sim=sim, lambda_geometry=s.lambda_geometry, learning_rates=s.learning_rates, seed=s.seed,
                                optimize_gravity=s.optimize_gravity, **(s.model_options or {}))


def evaluate_and_report(module, run: Path, s: RunSettings, timings: dict) -> dict:
    """Future prediction and metrics (``run/evaluation``), figures and video (``run/report``), and
    the summary (written to ``run/summary.json`` and returned)."""
    import numpy as np

    from toolkit.evaluation import evaluate_module
    from toolkit.report import write_report

    t = time.perf_counter()
    module = module.to(_device(s.device))
    evaluation = evaluate_module(module, run / "evaluation")
    timings["evaluation_s"] = time.perf_counter() - t
    from toolkit.physics.grid_check import annotate_grid, grid_convergence

    t = time.perf_counter()
    grid = grid_convergence(module)  # does the estimate depend on the grid? (issue #20)
    timings["grid_check_s"] = time.perf_counter() - t
    renders = np.load(run / "evaluation" / "renders.npz")["renders"].transpose(1, 0, 2, 3, 4)
    inp = module.input
    cams = s.report_cameras or (inp.train_cameras[:2] + inp.held_out_cameras[:2])
    files = write_report(run, module.history, module.curriculum.describe(module.material.registry_name or None),
                         evaluation, inp.ground_truth, inp.images.numpy(), renders, cams,
                         uncertainty=module.uncertainty_result, grid_check=grid)
    from toolkit.physics.forecast_spread import forecast_spread

    # how far the prediction moves across the parameters' intervals (the future may turn on one the clip leaves open);
    # the estimate's own prediction is the evaluation's
    t = time.perf_counter()
    summary_spread = forecast_spread(module, base=np.load(run / "evaluation" / "prediction.npz")["positions"])
    timings["forecast_spread_s"] = time.perf_counter() - t
    timings["total_s"] = (timings.get("total_s", 0.0) + timings["evaluation_s"] + timings["grid_check_s"]
                          + timings["forecast_spread_s"])
    summary = run_summary(module, evaluation, timings, files)
    summary["grid_check"] = grid
    summary["forecast_spread"] = summary_spread
    if (run / "silhouettes.json").is_file():  # the cameras' agreement, checked before stage 0
        summary["silhouettes"] = json.loads((run / "silhouettes.json").read_text())
    annotate_grid(summary["parameters"], grid, module.estimate()["params"])
    write_json(run / "summary.json", summary)
    return summary

"""Running a benchmark: plan, estimate, run the jobs in parallel (resumable), tabulate, export.

Parallelism is one independent job per worker: a scene's stage 0, or one strategy's fit of one
scene. Nothing is data-parallel: no gradient is ever averaged across scenes. The parts:

* :mod:`toolkit.benchmark.executors`: the executor interface, :class:`LocalExecutor` (a fresh
  ``spawn`` process per job, the least busy GPU through ``CUDA_VISIBLE_DEVICES``; ``jobs_per_gpu``
  jobs may share one, at 10^4 particles a fit does not fill an H100; or N CPU workers) and
  :class:`InlineExecutor` (one job at a time in this process: debugging, tutorials);
* :mod:`toolkit.benchmark.ray_executor`: :class:`RayExecutor`, the same jobs as Ray tasks on one
  machine or a Ray cluster of several (retries when a worker or machine dies);
* :mod:`toolkit.benchmark.slurm`: :class:`~toolkit.benchmark.slurm.SubmititExecutor`, the same
  jobs as SLURM jobs through submitit (requeued when preempted or out of time, resubmitted when
  they die);
* :mod:`toolkit.benchmark.scheduler`: :func:`run_jobs`, dependencies, priorities and the time limit;
* this module: :func:`run_benchmark`, the whole command.

Each job's CPU thread pools are sized for its share of the machine (issue #25): the local
executor gives every job process ``PROJO4D_THREADS`` (the affinity-mask cores divided by the jobs
running at once, at most 8, 1 for CPU workers, or ``threads``), ``OMP_NUM_THREADS`` & co. and
``PROJO4D_CONCURRENT_RUNS`` from its start; a Ray task or SLURM job gets its CPUs as its thread
count. The job applies it with :func:`toolkit.threads.configure_threads` (a ``threads`` setting of
the job wins).

With a time limit the running jobs get SIGTERM ``grace`` seconds before the limit (each saves its
state and returns ``interrupted``), then SIGKILL whatever has not returned when the limit comes.
Each finished job leaves a ``job.json`` marker, so a rerun skips it and resumes the others from
their checkpoints; results of an interrupted benchmark are kept and tabulated.

Progress is one JSON object per line on stdout (and in ``BENCH/progress.jsonl``): ``plan``,
``estimate`` (one per job still to run), ``start``, ``done`` / ``failed`` / ``interrupted``,
``heartbeat``, ``stopping``, ``finished``.
"""

from __future__ import annotations

import json
import math
import shutil
import signal
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

from toolkit.benchmark.executors import JOB_FUNCTION, InlineExecutor, LocalExecutor, make_executor
from toolkit.benchmark.executors import _visible_gpus  # noqa: F401 - used by toolkit.benchmark.commands
from toolkit.benchmark.executors import job_call as _ray_call  # noqa: F401 - the name tests and older code import
from toolkit.benchmark.scheduler import Events as _Events
from toolkit.benchmark.scheduler import run_jobs

__all__ = ["LocalExecutor", "InlineExecutor", "RayExecutor", "make_executor", "run_jobs", "run_benchmark", "JOB_FUNCTION"]


def __getattr__(name: str):
    """``RayExecutor`` and ``SubmititExecutor``, imported when asked for (their modules import
    nothing optional at import time, but keep ``projo4d benchmark`` light)."""
    if name == "RayExecutor":
        from toolkit.benchmark.ray_executor import RayExecutor

        return RayExecutor
    if name == "SubmititExecutor":
        from toolkit.benchmark.slurm import SubmititExecutor

        return SubmititExecutor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ------------------------------------------------------------------------------------ the benchmark
def _raise_interrupt(signum, frame):  # noqa: ARG001
    raise KeyboardInterrupt(f"signal {signum}")


def _stop_on_sigterm():
    """While jobs run, SIGTERM to this process stops them as Ctrl-C does (save, stop, leave)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_interrupt)


def _restore_sigterm(previous) -> None:
    if previous is not None:
        signal.signal(signal.SIGTERM, previous)


def _scene_from_other_spec(job: dict) -> bool:
    """A ``generate`` job whose folder holds a scene made from another spec or generator version
    (another ``--suite-seed``, ``--suite-overrides`` or ``--shape-set`` in the same ``--out``)."""
    from toolkit.synthetic.scene import GENERATOR_VERSION

    gt = Path(job["folder"]) / "ground_truth.json"
    if not gt.is_file():
        return False
    try:
        made = json.loads(gt.read_text()).get("generator") or {}
    except (ValueError, OSError):
        return False
    wanted = json.loads(json.dumps(job["settings"]["spec"]))
    return made.get("spec") != wanted or made.get("version") != GENERATOR_VERSION


def _check_changed(jobs: Sequence[dict], redo_changed: bool, emit) -> None:
    """Jobs whose folder holds results of other settings: an error, or removed with ``redo_changed``."""
    from toolkit.benchmark.jobs import read_marker
    from toolkit.benchmark.plan import BenchmarkError

    changed = []
    regenerated = {j["id"] for j in jobs if j["kind"] == "generate" and _scene_from_other_spec(j)}
    stale = set(regenerated)  # a scene generated again makes its stage 0s and fits stale, whatever their markers say
    grew = True
    while grew:
        grew = False
        for j in jobs:
            if j["id"] not in stale and any(d in stale for d in j.get("depends", [])):
                stale.add(j["id"])
                grew = True
    for j in jobs:
        if j["kind"] == "generate":
            if j["id"] in regenerated:
                changed.append(j)
            continue
        m = read_marker(j["folder"])
        if m and (m.get("fingerprint") != j["fingerprint"] or j["id"] in stale):
            changed.append(j)
    if not changed:
        return
    if not redo_changed:
        names = ", ".join(j["id"] for j in changed[:5]) + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")
        scenes = sorted(j["scene"] for j in jobs if j["id"] in regenerated)
        why = (f"; scene(s) {', '.join(scenes)} hold a scene generated from another spec (--suite-seed, "
               "--suite-overrides or --shape-set), so their stage 0s and fits are stale too" if scenes else "")
        raise BenchmarkError(f"{len(changed)} job folder(s) hold results made with other settings ({names}){why}; rerun "
                             "with the same settings, choose another --out, or pass --redo-changed to delete and redo them")
    for j in changed:
        emit("redo", job=j["id"], folder=j["folder"])
        shutil.rmtree(j["folder"], ignore_errors=True)


def _write_suite_index(spec) -> None:
    """After generate jobs: the suite's ``suite.json``. The benchmark's scenes are complete, so
    nothing is regenerated; scenes that ``--only`` left out are indexed as missing, not generated."""
    suites, names = {}, {}
    for sc in spec.scenes:
        if sc.generate is not None:
            info = sc.generate["suite"]
            suites[info["root"]] = info
            names.setdefault(info["root"], set()).add(sc.name)
    for root, info in suites.items():
        from toolkit.synthetic.suite import generate_suite

        generate_suite(info["root"], families=info["families"], scenes_per_family=info["per_family"], seed=info["seed"],
                       size=info["size"], device=info["device"], spec_overrides=info["spec_overrides"] or None,
                       shape_set=info.get("shape_set", "pac_nerf"), progress=False, only=names[root])


def _export(bench: Path, export: Path, emit, budget: int = 15 * 2**20) -> list[Path]:
    """Copy what the write-up needs into ``export`` as 4 files: tables.md, tables.json,
    progress.jsonl and results.tar.gz (the plan, the run summaries, evaluations, histories, the
    coarse searches' records and markers, then figures while they fit in ``budget`` bytes: a
    lent GPU machine brings back files of at most 16 MiB)."""
    import tarfile

    export.mkdir(parents=True, exist_ok=True)
    files = []
    for name in ("tables/tables.md", "tables/tables.json", "progress.jsonl"):
        src = bench / name
        if src.is_file():
            shutil.copy2(src, export / Path(name).name)
            files.append(export / Path(name).name)
    groups = [["benchmark.json", "runs/**/summary.json", "runs/**/job.json", "scenes/**/job.json", "scenes/**/settings.json",
               "runs/**/evaluation/evaluation.json", "runs/**/physics/estimate.json", "runs/**/physics/history.json",
               "runs/**/material_search.json"],
              ["tables/*.png"], ["tables/*.mp4"], ["runs/**/report/*.png"], ["tables/*.gif"]]
    members, skipped, used = [], 0, 0
    for i, patterns in enumerate(groups):
        for pat in patterns:
            for p in sorted(q for q in bench.glob(pat) if q.is_file()):
                size = p.stat().st_size
                factor = 0.25 if p.suffix == ".json" else 1.0  # JSON compresses well; images do not
                if i > 0 and used + size * factor > budget:
                    skipped += 1
                    continue
                members.append(p)
                used += size * factor
    tar_path = export / "results.tar.gz"
    with tarfile.open(tar_path, "w:gz") as tar:
        for p in members:
            tar.add(p, arcname=str(p.relative_to(bench)))
    files.append(tar_path)
    emit("exported", files=[str(f) for f in files], bytes=sum(f.stat().st_size for f in files), figures_left_out=skipped)
    return files


def run_benchmark(spec, out: str | Path, *, executor: str = "local", workers: Optional[int] = None,
                  gpus: Optional[Sequence[str]] = None, jobs_per_gpu: int = 1, threads: Optional[int] = None,
                  ray_address: Optional[str] = None, time_limit: Optional[float] = None, grace: float = 45.0,
                  retry_failed: bool = False, redo_changed: bool = False, dry_run: bool = False, export: Optional[str] = None,
                  figures: bool = True, echo: Optional[Callable[[dict], None]] = None, heartbeat: float = 60.0,
                  interrupt_at_step: Optional[int] = None, job_function: str = JOB_FUNCTION,
                  estimate_for: Optional[str] = None, slurm: Optional[dict] = None,
                  start_limit: Optional[float] = None) -> dict:
    """Plan, run (in parallel, resumable) and tabulate a benchmark.

    Args:
        spec: a :class:`~toolkit.benchmark.plan.BenchmarkSpec`.
        out: the benchmark folder (see :mod:`toolkit.benchmark.plan` for its layout).
        executor: ``local``, ``ray``, ``slurm`` or ``inline``.
        workers: worker processes (default: one per GPU x ``jobs_per_gpu``; 1 on a CPU).
        gpus: GPU ids to use (default: every visible GPU unless the settings say ``device: cpu``).
        jobs_per_gpu: workers sharing one GPU.
        threads: CPU threads per job (default: this process's affinity-mask cores divided by the
            jobs running at once; with Ray, the cluster's CPUs divided among its tasks).
        ray_address: Ray cluster address (``executor="ray"``).
        time_limit: seconds from now by which this call returns (jobs get SIGTERM ``grace`` seconds
            before); a rerun continues.
        grace: see ``time_limit``.
        start_limit: seconds from now after which no job starts; the running ones go on until
            they finish or ``time_limit`` (e.g. a lent machine: ``time_limit`` its time left,
            ``start_limit`` that less the length of a fit).
        retry_failed: run failed jobs again.
        redo_changed: delete and redo job folders made with other settings (else an error).
        dry_run: plan and print the estimates only.
        export: also copy the tables and a ``results.tar.gz`` of the light results there.
        figures: draw the comparison figures.
        echo: receives each event dict instead of printing it.
        heartbeat: seconds between heartbeat events.
        interrupt_at_step: testing aid: fits stop themselves (SIGTERM) after this iteration.
        job_function: ``"module:function"`` the workers run (testing aid).
        estimate_for: ``"cuda"`` or ``"cpu"``: price the estimates for that device (default: the
            one the jobs run on), e.g. to plan a GPU run with ``dry_run`` on a laptop.
        slurm: :class:`~toolkit.benchmark.slurm.SubmititExecutor` arguments for ``executor="slurm"``
            (``partition``, ``time_min``, ``gpus_per_job``, ``max_retries``, ``options``, ...);
            its job files go to ``BENCH/slurm``.

    Returns:
        ``{"complete": bool, "counts": {...}, "tables": path or None, "out": path}``.
    """
    from toolkit.benchmark.estimate import (
        PROFILES,
        Calibration,
        estimate_job,
        format_seconds,
        refinement_estimate,
        scene_info,
        sharing_slowdown,
        simulate_schedule,
    )
    from toolkit.benchmark.jobs import job_is_done, read_marker
    from toolkit.benchmark.plan import BenchmarkError, plan_benchmark

    t_start = time.time()
    deadline = t_start + time_limit if time_limit else None
    if start_limit is not None and start_limit < 0:
        raise BenchmarkError(f"--start-limit must be at least 0 seconds, got {start_limit:g}")
    start_deadline = t_start + start_limit if start_limit is not None else None
    bench = Path(out).resolve()
    if not dry_run:
        bench.mkdir(parents=True, exist_ok=True)
    emit = _Events(bench / "progress.jsonl", echo)
    jobs = [j.to_dict() for j in plan_benchmark(spec, bench)]
    if interrupt_at_step:
        for j in jobs:
            if j["kind"] == "fit":
                j["extra"]["interrupt_at_step"] = int(interrupt_at_step)
    if dry_run:
        emit.path = None  # a dry run writes nothing
    _check_changed(jobs, redo_changed and not dry_run, emit)
    if not dry_run:
        meta = {"spec": spec.to_dict(), "updated": time.strftime("%Y-%m-%dT%H:%M:%S")}
        (bench / "benchmark.json").write_text(json.dumps(meta, indent=2))

    device = (spec.overrides or {}).get("device", "auto")
    if gpus is None and device != "cpu" and executor == "local":
        gpus = _visible_gpus() or None
    if device == "cpu":
        gpus = None
    cluster = executor in ("ray", "slurm")
    if executor == "slurm" and device != "cpu" and int((slurm or {}).get("gpus_per_job", 1)) == 0:
        device = "cpu"  # CPU jobs: price them for a CPU
    profile = PROFILES[estimate_for or ("cuda" if (gpus or (cluster and device != "cpu")) else "cpu")]

    # estimates: the model (slowed down when jobs share a GPU), rescaled by what finished jobs
    # measured (also in earlier runs: the markers keep both numbers)
    from toolkit.benchmark.variant_jobs import base_scene, variant_scenes

    scene_by_name = {s.name: s for s in list(spec.scenes) + variant_scenes(spec.scenes, spec.variants, bench)}
    # a fit shares its GPU with at most the fits left to run per GPU
    fits_left = sum(1 for j in jobs if j["kind"] == "fit" and not job_is_done(j))
    fits_a_gpu = min(jobs_per_gpu, max(1, math.ceil(fits_left / max(1, len(gpus or [])))))

    def slow_of(kind: str) -> float:
        return sharing_slowdown(fits_a_gpu if kind == "fit" else jobs_per_gpu, kind) if gpus else 1.0
    calib = Calibration()
    particles: dict[str, int] = {}
    for j in jobs:
        if j["kind"] == "prepare":
            m = read_marker(j["folder"]) or {}
            if (m.get("result") or {}).get("n_particles"):
                particles[j["id"]] = int(m["result"]["n_particles"])
    model: dict[str, float] = {}
    refine_model: dict[str, float] = {}  # a fit's extra seconds if it refines (refinement_reason)

    def price(j: dict, n_part: Optional[int]) -> None:
        sc = base_scene(scene_by_name[j["scene"]])  # a variant: priced as its source scene
        info = scene_info(sc.path, None if Path(sc.path, "all_data.json").is_file() else (sc.generate or {}).get("spec"))
        slow = slow_of(j["kind"])
        model[j["id"]] = estimate_job(j, info, profile, n_part) * slow
        refine_model[j["id"]] = refinement_estimate(j, info, profile, n_part) * slow
        j["extra"]["estimate_s"] = round(model[j["id"]], 1)

    for j in jobs:
        price(j, particles.get(j["depends"][0]) if j["kind"] == "fit" and j["depends"] else None)
        m = read_marker(j["folder"]) if j["kind"] != "generate" else None
        if m and m.get("status") == "done" and m.get("fingerprint") == j["fingerprint"]:
            calib.add(j, m.get("wall_s_total"), m.get("estimate_s"))

    def estimate(j: dict) -> tuple[float, str]:
        return calib.apply(j, model[j["id"]])

    todo = [j for j in jobs if not job_is_done(j)]
    n_workers = workers or ((len(gpus) * jobs_per_gpu) if gpus else 1)
    if executor == "slurm":  # jobs queued at a time (the cluster decides how many run)
        n_workers = workers or int((slurm or {}).get("max_jobs", 32))
    total_est = sum(estimate(j)[0] for j in todo)
    done_ids = {j["id"] for j in jobs if j not in todo}
    wall = simulate_schedule(jobs, {j["id"]: estimate(j)[0] for j in todo}, n_workers, done_ids)
    refinable = [j for j in todo if refine_model.get(j["id"])]
    refined_wall = (simulate_schedule(jobs, {j["id"]: estimate(j)[0] + refine_model.get(j["id"], 0.0) for j in todo},
                                      n_workers, done_ids) if refinable else None)
    per_chunk = (time_limit - grace) if time_limit else None
    emit("plan", out=str(bench), jobs=len(jobs), to_run=len(todo), scenes=len(spec.scenes),
         strategies=[s.label for s in spec.strategies], cameras=spec.cameras, executor=executor, workers=n_workers,
         gpus=list(gpus) if gpus else None, profile=profile.name, time_limit_s=time_limit, start_limit_s=start_limit,
         estimated_worker_s=round(total_est, 0), estimated_wall_s=round(wall, 0),
         estimated_chunks=None if not per_chunk else max(1, math.ceil(wall / max(1.0, per_chunk))),
         **({"estimated_wall_s_if_all_refined": round(refined_wall, 0), "refinable_fits": len(refinable)}
            if refined_wall is not None else {}),
         note="estimates are rough until jobs of each kind have finished (basis 'model' vs 'calibrated'); the wall "
              "time follows the dependencies (stage 0 before its fits)" + (f"; with {jobs_per_gpu} jobs a GPU ({fits_a_gpu} fits) a fit is "
                                                                          f"assumed {slow_of('fit'):.2f}x slower and other "
                                                                          f"jobs {slow_of('other'):.2f}x" if gpus and jobs_per_gpu > 1 else "")
              + (f"; a fit whose estimate depends on the grid (its grid check fails, or the grid term moves a material "
                 f"parameter by more than its standard deviation) is fitted again at half the grid spacing (refine_grid), about "
                 f"{profile.refine_factor:g}x its physics stage more: estimated_wall_s_if_all_refined is the wall time "
                 "if every one does" if refined_wall is not None else ""))
    for j in todo:
        est, basis = estimate(j)
        emit("estimate", job=j["id"], est_s=round(est, 1), human=format_seconds(est), basis=basis)
    if dry_run:
        return {"complete": not todo, "counts": {"remaining": len(todo)}, "tables": None, "out": str(bench)}

    def on_done(job: dict, res: dict) -> None:
        if res.get("status") == "done":
            m = read_marker(job["folder"]) if job["kind"] != "generate" else None
            calib.add(job, (m or {}).get("wall_s_total") or res.get("wall_s"), model[job["id"]])
            if job["kind"] == "prepare" and (res.get("result") or {}).get("n_particles"):
                for f in jobs:
                    if f["kind"] == "fit" and f["depends"] == [job["id"]]:
                        price(f, int(res["result"]["n_particles"]))

    counts = {"done": sum(1 for j in jobs if j not in todo), "failed": 0, "blocked": 0, "remaining": 0, "ran": 0}
    if todo:
        ex = make_executor(executor, workers, gpus, jobs_per_gpu, threads, ray_address, job_function,
                           use_gpus=device != "cpu", slurm={"folder": bench / "slurm", **(slurm or {})})
        previous = _stop_on_sigterm()
        try:
            counts = run_jobs(jobs, ex, emit, deadline=deadline, grace=grace, retry_failed=retry_failed, heartbeat=heartbeat,
                              estimate=estimate, on_done=on_done, min_start_s=min(30.0, 0.1 * (time_limit or 0)),
                              start_deadline=start_deadline)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the jobs saved their state; tabulate what is done
            finished = sum(1 for j in jobs if job_is_done(j))
            counts = {"done": finished, "failed": 0, "blocked": 0, "remaining": len(jobs) - finished, "ran": None,
                      "stopped_by": "signal"}
        finally:
            ex.shutdown()
            _restore_sigterm(previous)
    gen = [j for j in jobs if j["kind"] == "generate"]
    if gen and all(job_is_done(j) for j in gen):
        _write_suite_index(spec)

    tables_path = None
    try:
        from toolkit.benchmark.tables import write_tables

        planned = {}
        for j in jobs:
            if j["kind"] == "fit":
                key = f"{j['material']}|{j['cameras']}|{j['strategy']}" + (f"|{j['variant']}" if j.get("variant") else "")
                planned[key] = planned.get(key, 0) + 1
        fits = {(j["scene"], j["strategy"], j["cameras"]) for j in jobs if j["kind"] == "fit"}
        md, _, tables = write_tables(bench, strategies=[s.label for s in spec.strategies], settings=_settings_summary(spec, jobs),
                                     planned=planned, only=fits)
        tables_path = str(md)
        emit("tables", markdown=str(md), rows=sum(len(t["rows"]) for t in tables["tables"]),
             headline=_headline(tables))
    except Exception as exc:  # noqa: BLE001 - the jobs' results are on disk; tables can be redone with --tables-only
        emit("tables_failed", error=f"{type(exc).__name__}: {exc}")
        tables = {}
    if export:  # the numbers first: on a lent machine the figures may outlast the time left
        _export(bench, Path(export), emit)
    if figures and tables.get("records"):
        t_fig = time.time()
        try:
            from toolkit.benchmark.plots import write_figures
            from toolkit.benchmark.tables import collect_records

            records, _ = collect_records(bench)
            emit("figures", records=len(records), note="tables are written (and exported); drawing the figures")
            written = write_figures(bench, [r for r in records if not r.get("variant")],
                                    strategies=[s.label for s in spec.strategies])
            emit("figures_done", files=len(written), wall_s=round(time.time() - t_fig, 1))
        except Exception as exc:  # noqa: BLE001 - the tables stand without the figures
            emit("figures_failed", error=f"{type(exc).__name__}: {exc}")
        if export:
            _export(bench, Path(export), emit)
    complete = counts.get("remaining", 0) == 0 and counts.get("blocked", 0) == 0
    emit("finished", complete=complete, counts=counts, wall_s=round(time.time() - t_start, 1),
         next="rerun the same command to continue" if not complete else None)
    return {"complete": complete, "counts": counts, "tables": tables_path, "out": str(bench)}


def _settings_summary(spec, jobs: Sequence[dict]) -> dict:
    """What was run, for the tables' header."""
    fits = [j for j in jobs if j["kind"] == "fit"]
    prep = next((j for j in jobs if j["kind"] == "prepare"), None)
    out: dict = {"size": spec.size, "cameras": spec.cameras, "scenes": len(spec.scenes)}
    if prep:
        s = prep["settings"]
        out["geometry"] = s.get("geometry", "stage0")
        out["stage0"] = s.get("stage0", "full") if s.get("geometry", "stage0") == "stage0" else "(oracle geometry)"
        out["sim"] = s.get("sim")
        out["device"] = s.get("device", "auto")
    if spec.iterations:
        out["iteration overrides"] = spec.iterations
    schedules = {}
    for j in fits:
        from toolkit.pipeline import resolve_curriculum

        try:
            cur = resolve_curriculum(j["settings"]["curriculum"], j["settings"].get("curriculum_options"))
            schedules.setdefault(j["strategy"], {})[j["material"]] = cur.schedule_string(j["material"])
        except Exception:  # noqa: BLE001
            pass
    out["schedules (groups:iterations@frames/cameras x frames per step)"] = schedules
    out["periodic evaluation"] = spec.periodic_eval
    if spec.variants:
        out["variants"] = spec.variants
    configs = {}
    for j in jobs:
        if j["kind"] == "prepare":
            cfg = j.get("extra", {}).get("config")
            configs[j["material"]] = Path(cfg).name if cfg else "(none: RunSettings defaults)"
    out["configs"] = configs
    return out


def _headline(tables: dict) -> list[dict]:
    out = []
    for t in tables.get("tables", []):
        for r in t["rows"]:
            v = r["values"]
            out.append({"material": t["material"], "cameras": t["cameras"], "strategy": r["strategy"],
                        **({"variant": r["variant"]} if r.get("variant") else {}), "n": r["n"],
                        **{k.replace("mae:", "mae_"): (None if c["mean"] is None else round(c["mean"], 5)) for k, c in v.items()}})
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use `projo4d benchmark` or benchmarks/strategy_comparison.py")

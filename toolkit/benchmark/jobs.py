"""Running one benchmark job in the current process (what each worker does).

:func:`execute_job` takes a job as a plain dict (:meth:`toolkit.benchmark.plan.Job.to_dict`),
sends the job's output to its log file, runs it and returns a small result dict. It writes the
job's marker ``job.json`` in the job's folder (status, fingerprint, wall time of every attempt,
the headline numbers), which is what a rerun reads to skip finished jobs.

Stopping: SIGTERM asks the current job to stop. Inside a Lightning fit (stage 0 or physics)
Lightning stops after the current iteration; the physics fit first saves ``last.ckpt`` there,
stage 0 keeps its last periodic checkpoint. Outside a fit the job stops at the next step
boundary. The job then returns ``status: "interrupted"`` and a rerun resumes it. The parent
(:mod:`toolkit.benchmark.runner`) sends SIGTERM when its time limit comes, and SIGKILL after a
grace period.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Optional

__all__ = ["execute_job", "read_marker", "job_is_done", "stopped_fit_state", "JobInterrupted", "MARKER"]

log = logging.getLogger(__name__)

MARKER = "job.json"
_STOP = threading.Event()


class JobInterrupted(Exception):
    """The job was asked to stop (SIGTERM); a rerun resumes it."""


def _on_sigterm(signum, frame) -> None:  # noqa: ARG001
    _STOP.set()


def install_stop_handler() -> None:
    """Make SIGTERM set the stop flag instead of killing the process (main thread only)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)


def _check_stop() -> None:
    if _STOP.is_set():
        raise JobInterrupted("stop requested")


# ------------------------------------------------------------------------------------ markers
def read_marker(folder: str | Path) -> Optional[dict]:
    path = Path(folder) / MARKER
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _outputs_exist(job: dict) -> bool:
    folder = Path(job["folder"])
    if job["kind"] == "prepare":
        return (folder / "physics_input.pt").is_file()
    if job["kind"] == "fit":
        return (folder / "summary.json").is_file() and (folder / "evaluation" / "evaluation.json").is_file()
    return True


def job_is_done(job: dict) -> bool:
    """Whether a job finished with the same settings (its marker and outputs are there)."""
    if job["kind"] == "generate":
        from toolkit.synthetic.scene import scene_is_complete
        from toolkit.synthetic.spec import spec_from_dict

        return scene_is_complete(job["folder"], spec_from_dict(job["settings"]["spec"]))
    if job["kind"] == "variant":  # no marker: variant.json says what the folder holds
        from toolkit.benchmark.variant_jobs import variant_job_done

        return variant_job_done(job)
    m = read_marker(job["folder"])
    return bool(m and m.get("status") == "done" and m.get("fingerprint") == job["fingerprint"] and _outputs_exist(job))


def _write_marker(job: dict, status: str, wall_s: float, result: Optional[dict] = None, error: Optional[str] = None) -> dict:
    folder = Path(job["folder"])
    folder.mkdir(parents=True, exist_ok=True)
    old = read_marker(folder) or {}
    attempts = list(old.get("attempts", [])) if old.get("fingerprint") == job["fingerprint"] else []
    attempts.append({"status": status, "wall_s": round(wall_s, 2), "pid": os.getpid(), "host": socket.gethostname(),
                     "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"), "finished": time.strftime("%Y-%m-%dT%H:%M:%S")})
    marker = {
        "id": job["id"], "kind": job["kind"], "status": status, "fingerprint": job["fingerprint"],
        "scene": job["scene"], "material": job["material"], "cameras": job.get("cameras"), "strategy": job.get("strategy"),
        **({"variant": job["variant"]} if job.get("variant") else {}),
        "wall_s_total": round(sum(a["wall_s"] for a in attempts), 2), "attempts": attempts,
        "estimate_s": job.get("extra", {}).get("estimate_s"), "result": result or {}, "error": error,
    }
    tmp = folder / (MARKER + ".tmp")
    tmp.write_text(json.dumps(marker, indent=2))
    os.replace(tmp, folder / MARKER)
    return marker


# ------------------------------------------------------------------------------------ output
@contextlib.contextmanager
def _redirect_output(path: Optional[str]):
    """Send this process's stdout/stderr (file descriptors 1 and 2, C code included) to ``path``."""
    if not path:
        yield
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(path, "a", buffering=1) as f:
        f.write(f"\n===== {time.strftime('%Y-%m-%dT%H:%M:%S')} pid {os.getpid()} gpu {os.environ.get('CUDA_VISIBLE_DEVICES')}\n")
        f.flush()
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


# ------------------------------------------------------------------------------------ a stopped fit
def stopped_fit_state(checkpoint: str | Path) -> Optional[dict]:
    """Where a stopped fit was, from its saved checkpoint; ``None`` when there is none to read.

    A fit stopped by a deadline keeps its checkpoint only on the machine it ran on, and a lent
    machine goes back with it; its marker keeps this instead. Returns ``{"iteration", "of",
    "stage", "parameters", "errors", "evaluation", "material_final"}``: the last finished
    iteration of ``of``, its stage's name, the parameter values (``param/...``, ``v0/...``) and
    errors (``error/...``, those of :func:`toolkit.metrics.parameter_errors`) at that iteration,
    the last periodic evaluation (``{"step", "cd_future", "emd_future"}`` or ``None``), and
    whether no later stage optimizes anything but appearance (``A``), so that the parameters and
    the predicted future were already final (a sequential fit stopped in its appearance stage).
    These are the training-time numbers, not the final evaluation's: a stopped fit has no summary
    and is not in the tables.
    """
    import torch

    path = Path(checkpoint)
    if not path.is_file():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=False, mmap=True).get("projo4d") or {}
    except Exception:  # noqa: BLE001 - an unreadable checkpoint: nothing to report
        return None
    history, stages = state.get("history") or [], state.get("curriculum") or []
    if not history:
        return None
    last = history[-1]
    step = int(last.get("step", 0))
    later = [st for st in stages if int(st.get("end", 0)) > step]
    evals = [r for r in history if "eval/cd_future" in r]
    return {
        "iteration": step,
        "of": int(stages[-1]["end"]) if stages else None,
        "stage": last.get("stage_name"),
        "parameters": {k: v for k, v in last.items() if k.startswith(("param/", "v0/"))},
        "errors": {k.split("/", 1)[1]: v for k, v in last.items() if k.startswith("error/")},
        "evaluation": ({"step": evals[-1].get("step"), "cd_future": evals[-1].get("eval/cd_future"),
                        "emd_future": evals[-1].get("eval/emd_future")} if evals else None),
        "material_final": bool(later) and all(set(str(st.get("groups", ""))) <= {"A"} for st in later),
    }


# ------------------------------------------------------------------------------------ entry point
def execute_job(job: dict) -> dict:
    """Run one job (``generate``, ``variant``, ``prepare`` or ``fit``) here and return its result.

    Returns:
        ``{"id", "status" ("done", "failed" or "interrupted"), "wall_s", "result", "error", "pid",
        "gpu"}``; ``result`` holds the headline numbers (metrics of a fit, particle counts of a
        preparation).
    """
    install_stop_handler()
    _STOP.clear()
    from toolkit.verbosity import configure_output, verbose_from_environment

    configure_output(verbose_from_environment())  # workers are as quiet as the command that started them
    t0 = time.perf_counter()
    status, result, error = "done", {}, None
    from toolkit.checkpointing import RunInterrupted  # a fit stopped by SIGTERM after saving its checkpoint

    with _redirect_output(job.get("extra", {}).get("log")):
        try:
            _check_stop()
            runner = {"generate": _generate, "variant": _variant, "prepare": _prepare, "fit": _fit}.get(job["kind"])
            if runner is None:
                raise ValueError(f"unknown job kind {job['kind']!r}")
            result = runner(job) or {}
        except (JobInterrupted, RunInterrupted, KeyboardInterrupt, SystemExit) as exc:  # SIGTERMException: a SystemExit
            status, error = "interrupted", f"{type(exc).__name__}: {exc}"
            print(f"job {job['id']} interrupted: {error}", flush=True)
        except Exception as exc:  # noqa: BLE001 - a failed job is recorded, the benchmark goes on
            from toolkit.device_memory import oom_note

            note = oom_note(exc)  # a GPU out of memory: who held it (this job, or the others on its card)
            status, error = "failed", f"{type(exc).__name__}: {exc}" + (f" [{note}]" if note else "")
            traceback.print_exc()
    wall = time.perf_counter() - t0
    if status == "interrupted" and job["kind"] == "fit":
        stopped = stopped_fit_state(Path(job["folder"]) / "physics" / "checkpoints" / "last.ckpt")
        if stopped is not None:
            result = {**result, "stopped_at": stopped}
    if job["kind"] not in ("generate", "variant"):  # those two are recognised by their files
        _write_marker(job, status, wall, result, error)
    return {"id": job["id"], "status": status, "wall_s": round(wall, 2), "result": result, "error": error,
            "pid": os.getpid(), "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"), "host": socket.gethostname()}


# ------------------------------------------------------------------------------------ generate
def _generate(job: dict) -> dict:
    from toolkit.synthetic.scene import generate_scene, scene_is_complete
    from toolkit.synthetic.spec import spec_from_dict

    spec = spec_from_dict(job["settings"]["spec"])
    if not scene_is_complete(job["folder"], spec):
        generate_scene(spec, job["folder"], progress=False)
    return {"shape": spec.shape, "params": spec.params}


def _variant(job: dict) -> dict:
    from toolkit.benchmark.variant_jobs import run_variant_job

    return run_variant_job(job)


# ------------------------------------------------------------------------------------ prepare
def _loadable(path: Path) -> bool:
    import torch

    try:
        torch.load(path, map_location="cpu", weights_only=False, mmap=True)
        return True
    except Exception:  # noqa: BLE001 - a truncated file from a killed run
        return False


def _drop_broken_checkpoints(folder: Path) -> None:
    """Remove checkpoints that a killed process left half-written (newest first, until one loads)."""
    if not folder.is_dir():
        return
    last = folder / "last.ckpt"
    if last.is_file() and not _loadable(last):
        print(f"removing unreadable checkpoint {last}", flush=True)
        last.unlink()
    for ckpt in sorted(folder.glob("step_*.ckpt"), reverse=True):
        if _loadable(ckpt):
            break
        print(f"removing unreadable checkpoint {ckpt}", flush=True)
        ckpt.unlink()


def _prepare(job: dict) -> dict:
    from toolkit.pipeline import RunSettings, build_physics_input

    s = RunSettings(**job["settings"])
    s.validate()
    run = Path(s.out)
    run.mkdir(parents=True, exist_ok=True)
    threads = _set_threads(s)
    (run / "settings.json").write_text(json.dumps(job["settings"], indent=2))
    path = run / "physics_input.pt"
    if path.is_file() and not _loadable(path):
        print(f"removing unreadable {path}", flush=True)
        path.unlink()
    _drop_broken_checkpoints(run / "stage0")
    timings: dict = {}
    build_physics_input(s, run, timings)
    for old in (run / "stage0").glob("step_*.ckpt"):
        old.unlink()
    _check_stop()
    import torch

    d = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
    return {"n_particles": int(d["particles"].shape[0]), "n_gaussians": int(d["gaussians"]["means"].shape[0]),
            "n_frames": int(d["images"].shape[1]), "n_train": int(d["n_train"]), "train_cameras": list(d["train_cameras"]),
            "timings_s": {k: round(v, 1) for k, v in timings.items()}, "threads": threads}


def _set_threads(s) -> dict:
    """Size this worker's CPU thread pools: the job's ``threads`` setting, else ``PROJO4D_THREADS``
    (the executor sets it to the affinity-mask cores divided among the jobs running side by side),
    else :func:`toolkit.threads.resolve_threads`'s default. Returns the choice as a dict."""
    from toolkit.pipeline import _device
    from toolkit.threads import configure_threads

    return configure_threads(s.threads, device=_device(s.device), name=f"threads of job settings ({s.out})").to_dict()


# ------------------------------------------------------------------------------------ fit
def _link_input(src: Path, dst: Path) -> None:
    """``dst`` -> ``src`` (a relative symlink; a hard link or a copy where links are not possible)."""
    if dst.is_symlink() or dst.exists():
        if dst.resolve() == src.resolve():
            return
        dst.unlink()
    try:
        dst.symlink_to(os.path.relpath(src, dst.parent))
    except OSError:
        try:
            os.link(src, dst)
        except OSError:
            import shutil

            shutil.copy2(src, dst)


def _fit(job: dict) -> dict:
    import torch

    from toolkit.atomic import write_json
    from toolkit.physics.fit import default_callbacks, fit_physics
    from toolkit.pipeline import RunSettings, _accelerator, _device, _restore_finished_fit, evaluate_and_report, make_physics_module

    extra = job.get("extra", {})
    s = RunSettings(**job["settings"])
    s.validate()
    run = Path(s.out)
    run.mkdir(parents=True, exist_ok=True)
    device = _device(s.device)
    threads = _set_threads(s)
    (run / "settings.json").write_text(json.dumps(job["settings"], indent=2))
    src = Path(extra["physics_input"])
    if not src.is_file():
        raise FileNotFoundError(f"{src} does not exist: its prepare job has not run")
    _link_input(src, run / "physics_input.pt")
    previous = read_marker(run) or {}
    timings: dict = dict((previous.get("result") or {}).get("timings_s", {})) if previous.get("fingerprint") == job["fingerprint"] else {}

    module = make_physics_module(s, run / "physics_input.pt")
    physics_dir = run / "physics"
    t = time.perf_counter()
    last = physics_dir / "checkpoints" / "last.ckpt"
    if not _restore_finished_fit(module, physics_dir, last if last.is_file() else None):
        _drop_broken_checkpoints(physics_dir / "checkpoints")
        every = int(extra.get("checkpoint_every") or s.checkpoint_every)
        from materials import MaterialError
        from toolkit.benchmark.callbacks import CheckpointOnStop, DivergenceGuard, SigtermAtStep
        from toolkit.mpm.config import SimulationError

        guard = DivergenceGuard()
        callbacks = [guard]
        if extra.get("periodic_eval") is not None:
            from toolkit.physics.periodic_eval import PeriodicEvaluation

            callbacks.append(PeriodicEvaluation(**extra["periodic_eval"]))
        if extra.get("interrupt_at_step"):
            callbacks.append(SigtermAtStep(int(extra["interrupt_at_step"])))
        callbacks.append(CheckpointOnStop(physics_dir / "checkpoints"))
        callbacks += default_callbacks(every, progress=False)
        try:
            fit_physics(module, physics_dir, resume="last", checkpoint_every=every, accelerator=_accelerator(device),
                        progress=False, callbacks=callbacks)
        except (SimulationError, MaterialError) as err:  # the simulation failed inside an iteration
            guard.restore(module, f"{type(err).__name__}: {err}")
            if guard.diverged is None:
                raise
            from types import SimpleNamespace

            from toolkit.physics.callbacks import EstimateWriter

            # Lightning skipped on_train_end: write estimate.json and history.json as it would have
            EstimateWriter().on_train_end(SimpleNamespace(default_root_dir=str(physics_dir)), module)
        finally:
            timings["physics_s"] = timings.get("physics_s", 0.0) + time.perf_counter() - t
        diverged = guard.diverged
        if diverged is None and module.curriculum_step < module.total_iterations:
            raise JobInterrupted(f"physics fit stopped at iteration {module.curriculum_step} of {module.total_iterations}")
    else:
        diverged = None  # the fit ran its whole curriculum
    _check_stop()

    timings["total_s"] = sum(v for k, v in timings.items() if k not in ("total_s", "evaluation_s"))
    summary = evaluate_and_report(module, run, s, timings)
    inp = module.input
    summary["benchmark"] = {"job": job["id"], "strategy": job.get("strategy"), "cameras": job.get("cameras"),
                            "train_cameras": list(inp.train_cameras), "optimized": list(module.optimized_material),
                            "iterations": module.total_iterations, "n_particles": int(module.particles0.shape[0]),
                            "diverged": diverged}
    summary["threads"] = threads
    write_json(run / "summary.json", summary)  # with the benchmark fields
    refined = None
    if s.refine_grid is not False:
        from toolkit.grid_refinement import refine_after_fit

        _check_stop()
        refined = refine_after_fit(s, summary, module.estimate(), device, run, stage0=src.parent / "stage0")
        if refined is not None:
            timings["refine_s"] = summary["timings_s"]["refine_s"]
    for old in (physics_dir / "checkpoints").glob("step_*.ckpt"):  # finished: last.ckpt and the stage ends are enough
        old.unlink()
    del module
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
    fut = summary["future"]
    return {"cd": fut.get("cd"), "emd": fut.get("emd"), "psnr": fut.get("psnr"), "ssim": fut.get("ssim"),
            "errors": _errors(summary), "curriculum": summary["curriculum"],
            "timings_s": {k: round(v, 1) for k, v in timings.items()}, "diverged": diverged, "threads": threads,
            **({"refined": {"cd": (refined.get("future") or {}).get("cd"), "errors": _errors(refined)}} if refined else {}),
            **({"refine_failed": summary["refined"]["failed"]} if (summary.get("refined") or {}).get("failed") else {})}


def _errors(summary: dict) -> dict:
    """A summary's numeric parameter errors keyed by parameter name (``error/E`` -> ``E``)."""
    return {k.split("/", 1)[-1]: v for k, v in (summary.get("errors") or {}).items() if isinstance(v, (int, float))}

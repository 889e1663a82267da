"""Running a benchmark's jobs in parallel: local processes (one per GPU, or N on a CPU) or Ray.

Parallelism is one independent job per worker: a scene's stage 0, or one strategy's fit of one
scene. Nothing is data-parallel: no gradient is ever averaged across scenes.

* :class:`LocalExecutor`: a fresh ``spawn`` process per job, started with the job, which gets the
  least busy GPU through ``CUDA_VISIBLE_DEVICES`` (``jobs_per_gpu`` jobs may share one: at 10^4 particles a fit does
  not fill an H100), or N CPU workers.
* :class:`RayExecutor`: the same jobs as Ray tasks (``num_gpus`` per task), on one machine or a
  Ray cluster of several (``ray start --head`` / ``ray start --address ...`` on the others,
  then ``--executor ray --ray-address auto``). Ray is optional (``pip install projo4d[ray]``);
  every machine must see the benchmark folder and the scenes at the same paths (a shared file
  system). A task whose worker process or machine dies is rerun (``max_retries``, default 2) and
  resumes from the job's checkpoints. The test suite runs it on a local Ray cluster (with logical
  GPUs and a killed task); it has not been tested on a multi-machine cluster here.
* :class:`InlineExecutor`: one job at a time in this process (debugging, tutorials).

Each job's CPU thread pools are sized for its share of the machine (issue #25): the local
executor gives every job process ``PROJO4D_THREADS`` (the affinity-mask cores divided by the jobs
running at once, at most 8, 1 for CPU workers, or ``threads``), ``OMP_NUM_THREADS`` & co. and
``PROJO4D_CONCURRENT_RUNS`` from its start; a Ray task gets its CPUs as its thread count. The job
applies it with :func:`toolkit.threads.configure_threads` (a ``threads`` setting of the job wins).

The scheduler (:func:`run_jobs`) starts a job once the jobs it depends on are done (stage 0
before the fits that share it), ``generate`` before ``prepare`` before ``fit``. With a time limit
it sends the running jobs SIGTERM ``grace`` seconds before the limit (each saves its state and
returns ``interrupted``), then SIGKILL whatever has not returned when the limit comes. Each
finished job leaves a ``job.json`` marker, so a rerun skips it and resumes the others from their
checkpoints; results of an interrupted benchmark are kept and tabulated.

Progress is one JSON object per line on stdout (and in ``BENCH/progress.jsonl``): ``plan``,
``estimate`` (one per job still to run), ``start``, ``done`` / ``failed`` / ``interrupted``,
``heartbeat``, ``stopping``, ``finished``.
"""

from __future__ import annotations

import concurrent.futures as cf
import importlib
import json
import math
import multiprocessing as mp
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

__all__ = ["LocalExecutor", "InlineExecutor", "RayExecutor", "make_executor", "run_jobs", "run_benchmark", "JOB_FUNCTION"]

#: the function each worker runs on a job dict
JOB_FUNCTION = "toolkit.benchmark.jobs:execute_job"


def _resolve(fn: str) -> Callable[[dict], dict]:
    module, _, name = fn.partition(":")
    return getattr(importlib.import_module(module), name)


# ------------------------------------------------------------------------------------ executors
def _init_worker(threads: Optional[int], concurrent: Optional[int] = None) -> None:
    """Worker start: thread count and signal handling (each worker runs one job, then exits).

    ``threads`` goes to ``PROJO4D_THREADS``, ``OMP_NUM_THREADS`` & co. (:func:`toolkit.threads.child_env`),
    which the job applies with :func:`toolkit.threads.configure_threads`; ``concurrent`` (the
    jobs sharing this machine) to ``PROJO4D_CONCURRENT_RUNS``.
    """
    if threads:
        from toolkit.threads import child_env

        os.environ.update(child_env(threads, concurrent))
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the parent, which stops the workers
    from toolkit.benchmark.jobs import install_stop_handler

    install_stop_handler()


class _SpawnableMain:
    """While workers are spawned, hide a ``__main__.__file__`` that is not a Python file.

    ``spawn`` re-runs the parent's main file in each worker (for functions defined there; the jobs
    need none). A main "file" that is not Python (e.g. a documentation page executed by a runner)
    would make every worker fail at start.
    """

    def __enter__(self):
        self.main = sys.modules.get("__main__")
        self.path = getattr(self.main, "__file__", None)
        self.hidden = bool(self.path and getattr(self.main, "__spec__", None) is None
                           and not str(self.path).endswith((".py", ".pyw")))
        if self.hidden:
            del self.main.__file__
        return self

    def __exit__(self, *exc):
        if self.hidden:
            self.main.__file__ = self.path
        return False


def _job_process(conn, fn: str, job: dict, gpu: Optional[str], threads: Optional[int],
                 concurrent: Optional[int] = None) -> None:
    """Body of one job's process: set the GPU before anything starts CUDA, run, send the result."""
    if gpu is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = str(gpu)
    _init_worker(threads, concurrent)
    try:
        result = _resolve(fn)(job)
    except BaseException as exc:  # noqa: BLE001 - an error outside the job's own error handling
        import traceback

        traceback.print_exc()
        result = {"id": job["id"], "status": "interrupted", "error": f"{type(exc).__name__}: {exc}"}
    conn.send(result)
    conn.close()


def _watch(process, conn, future: cf.Future, job_id: str) -> None:
    """Parent-side thread: wait for the job's result (or its process's end) and settle its future."""
    try:
        result = conn.recv()
    except (EOFError, OSError):  # the process ended without sending one
        result = None
    process.join()
    conn.close()
    if result is None:
        result = {"id": job_id, "status": "interrupted", "error": f"its worker process died (exit code "
                  f"{process.exitcode}); its output is in the job's log or on stderr"}
    future.set_result(result)


class LocalExecutor:
    """Jobs in worker processes on this machine, one fresh ``spawn`` process per job.

    A process is started when its job is submitted (never later, from another thread), so the
    job's GPU is set before anything in it starts CUDA, and a process crashing takes only its
    own job with it.

    Args:
        workers: number of worker processes (jobs at a time).
        gpus: one GPU id (a ``CUDA_VISIBLE_DEVICES`` value) per worker slot, e.g. ``["0", "0",
            "1", "1"]`` for two jobs on each of two GPUs; ``None`` for CPU workers. Each job
            goes to the GPU running the fewest jobs when it starts (ties: the first listed), so
            four stage-0 jobs on four GPUs get one GPU each.
        threads: CPU threads per job (torch, OpenMP, BLAS; ``PROJO4D_THREADS`` in the job's
            process); ``None``: this process's affinity-mask cores divided by ``workers``, at
            least 1 (:func:`toolkit.threads.per_job_threads`) and at most the default cap of a
            GPU or CPU run (:func:`toolkit.threads.default_cap`: 8, or 1 for CPU workers).
        fn: ``"module:function"`` run on each job dict (default :data:`JOB_FUNCTION`).
    """

    name = "local"

    def __init__(self, workers: int, gpus: Optional[Sequence[str]] = None, threads: Optional[int] = None,
                 fn: str = JOB_FUNCTION):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if gpus is not None and len(gpus) == 0:
            raise ValueError("gpus must name at least one GPU, or be None for CPU workers")
        self._ctx = mp.get_context("spawn")
        self._gpus = [str(g) for g in dict.fromkeys(gpus)] if gpus else []
        self._load = {g: 0 for g in self._gpus}
        self._running: dict = {}  # handle -> (process, GPU or None)
        self.capacity = workers
        if threads is None:
            from toolkit.threads import default_cap, per_job_threads

            threads = min(per_job_threads(workers), default_cap("cuda" if gpus else "cpu"))
        self._threads = threads
        self._fn = fn

    def submit(self, job: dict) -> cf.Future:
        gpu = min(self._gpus, key=lambda g: self._load[g]) if self._gpus else None
        receive, send = self._ctx.Pipe(duplex=False)
        process = self._ctx.Process(target=_job_process, args=(send, self._fn, job, gpu, self._threads, self.capacity),
                                    name=f"projo4d-job-{job['id']}")
        from toolkit.threads import child_environment

        # the variables are in the child's environment from its first instruction (libraries that
        # read them when they load, e.g. OpenBLAS, see them too)
        with _SpawnableMain(), child_environment(self._threads, self.capacity):
            process.start()
        send.close()  # the child holds the sending end: a dead child reads as end-of-file
        handle: cf.Future = cf.Future()
        handle.set_running_or_notify_cancel()
        threading.Thread(target=_watch, args=(process, receive, handle, job["id"]), daemon=True).start()
        self._running[handle] = (process, gpu)
        if gpu is not None:
            self._load[gpu] += 1
        return handle

    def wait(self, handles: Sequence, timeout: Optional[float]) -> list:
        done, _ = cf.wait(list(handles), timeout=timeout, return_when=cf.FIRST_COMPLETED)
        return list(done)

    def result(self, handle, job: dict) -> dict:  # noqa: ARG002 - the job is in the result already
        _, gpu = self._running.pop(handle)
        if gpu is not None:
            self._load[gpu] -= 1
        return handle.result()

    def _pids(self) -> list[int]:
        return [p.pid for p, _ in self._running.values() if p.is_alive()]

    def interrupt(self, handles: Sequence, grace: float) -> None:
        """SIGTERM every worker, wait up to ``grace`` seconds for the running jobs, then SIGKILL."""
        pids = self._pids()
        for pid in pids:
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        cf.wait(list(handles), timeout=grace)
        if any(not h.done() for h in handles):
            for pid in pids:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            cf.wait(list(handles), timeout=10)

    def shutdown(self) -> None:
        """Wait for the processes still running (the scheduler has stopped or collected them)."""
        for process, _ in self._running.values():
            process.join()


class InlineExecutor:
    """Jobs one at a time in this process (no parallelism; for debugging and tutorials)."""

    name = "inline"
    capacity = 1

    def __init__(self, fn: str = JOB_FUNCTION):
        self._fn = fn

    def submit(self, job: dict):
        fut: cf.Future = cf.Future()
        previous = signal.getsignal(signal.SIGTERM)
        try:
            fut.set_result(_resolve(self._fn)(job))
        except BaseException as exc:  # noqa: BLE001
            fut.set_exception(exc)
        finally:
            try:
                signal.signal(signal.SIGTERM, previous)
            except (ValueError, TypeError):
                pass
        return fut

    def wait(self, handles: Sequence, timeout: Optional[float]) -> list:
        return [h for h in handles if h.done()]

    def result(self, handle, job: dict) -> dict:
        try:
            return handle.result()
        except Exception as exc:  # noqa: BLE001
            return {"id": job["id"], "status": "failed", "error": f"{type(exc).__name__}: {exc}"}

    def interrupt(self, handles: Sequence, grace: float) -> None:
        pass

    def shutdown(self) -> None:
        pass


def _ray_call(fn: str, job: dict, threads: Optional[int] = None, concurrent: Optional[int] = None) -> dict:
    """Body of one Ray task: ``threads`` CPU threads (the task's CPUs), then the job.

    ``concurrent`` (``PROJO4D_CONCURRENT_RUNS``): the tasks sharing this node; ``None``: this
    node's cores divided by ``threads`` (Ray packs tasks by their CPUs).
    """
    from toolkit.benchmark.jobs import install_stop_handler

    if threads:
        from toolkit.threads import apply_threads, available_cores, child_env

        os.environ.update(child_env(threads, concurrent or max(1, available_cores() // threads)))
        apply_threads(threads)
    install_stop_handler()
    return _resolve(fn)(job)


class RayExecutor:
    """Jobs as Ray tasks (optional dependency; see the module docstring).

    Args:
        address: Ray cluster address (``"auto"`` for a running cluster; ``None`` starts a local one).
        gpus_per_job: GPUs per task; ``None``: ``1 / jobs_per_gpu`` when the cluster has GPUs, else 0.
        cpus_per_job: CPUs per task, which is also the task's thread count (``PROJO4D_THREADS``);
            ``None``: with GPUs, the cluster's CPUs divided among the tasks its GPUs hold at once
            (on a cluster of equal machines: each machine's cores divided among its tasks),
            without GPUs 1.
        fn: ``"module:function"`` run on each job dict.
        jobs_per_gpu: tasks sharing one GPU (when ``gpus_per_job`` is ``None``).
        max_retries: times Ray reruns a task whose worker process or node died (killed, out of
            memory, a machine lost); the rerun resumes from the job's checkpoints. A job that
            raises is a failure, not retried; a task cancelled at the time limit is not retried.
    """

    name = "ray"

    def __init__(self, address: Optional[str] = None, gpus_per_job: Optional[float] = None,
                 cpus_per_job: Optional[float] = None, fn: str = JOB_FUNCTION, jobs_per_gpu: int = 1,
                 max_retries: int = 2):
        try:
            import ray
        except ImportError:
            raise RuntimeError("the Ray executor needs ray: pip install 'projo4d[ray]' (or use --executor local)") from None
        self._ray = ray
        self._started = not ray.is_initialized()
        if self._started:
            ray.init(address=address, ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
        res = ray.cluster_resources()
        gpus = float(res.get("GPU", 0))
        if gpus_per_job is None:
            gpus_per_job = (1.0 / max(1, jobs_per_gpu)) if gpus else 0.0
        if gpus_per_job > 0 and not gpus:
            raise RuntimeError("the Ray cluster has no GPUs; use gpus_per_job=0 (or --device cpu)")
        cpus = float(res.get("CPU", 1))
        if cpus_per_job is None:
            cpus_per_job = float(max(1, int(cpus // max(1, int(gpus / gpus_per_job))))) if gpus_per_job else 1.0
        self.capacity = max(1, int(gpus / gpus_per_job) if gpus_per_job else int(cpus / cpus_per_job))
        self.threads = max(1, int(cpus_per_job))
        self._fn = fn
        self.max_retries = int(max_retries)
        self._interrupted: set = set()  # handles cancelled by interrupt(): "interrupted", not "failed"
        self._remote = ray.remote(num_gpus=gpus_per_job, num_cpus=cpus_per_job, max_retries=self.max_retries,
                                  retry_exceptions=False)(_ray_call)

    def submit(self, job: dict):
        return self._remote.remote(self._fn, job, self.threads)

    def wait(self, handles: Sequence, timeout: Optional[float]) -> list:
        ready, _ = self._ray.wait(list(handles), num_returns=1, timeout=timeout)
        return list(ready)

    def result(self, handle, job: dict) -> dict:
        try:
            return self._ray.get(handle)
        except Exception as exc:  # noqa: BLE001 - cancelled, or crashed after max_retries reruns
            status = "interrupted" if handle in self._interrupted else "failed"
            return {"id": job["id"], "status": status, "error": f"{type(exc).__name__}: {exc}"}

    def interrupt(self, handles: Sequence, grace: float) -> None:
        """Ask every running task to stop (KeyboardInterrupt in the task), then force-cancel."""
        self._interrupted.update(handles)
        for h in handles:
            self._ray.cancel(h, force=False)
        ready, rest = self._ray.wait(list(handles), num_returns=len(handles), timeout=grace)
        for h in rest:
            self._ray.cancel(h, force=True)

    def shutdown(self) -> None:
        if self._started:
            self._ray.shutdown()


def _visible_gpus() -> list[str]:
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [g for g in env.split(",") if g.strip() != ""]
    try:
        import torch

        return [str(i) for i in range(torch.cuda.device_count())]
    except Exception:  # noqa: BLE001
        return []


def make_executor(kind: str = "local", workers: Optional[int] = None, gpus: Optional[Sequence[str]] = None,
                  jobs_per_gpu: int = 1, threads: Optional[int] = None, ray_address: Optional[str] = None,
                  fn: str = JOB_FUNCTION, use_gpus: bool = True):
    """An executor: ``local`` (GPUs when given, else ``workers`` CPU processes), ``ray`` (the
    cluster's GPUs unless ``use_gpus`` is false) or ``inline``."""
    if threads is not None:
        from toolkit.threads import parse_count

        threads = parse_count(threads, "threads per benchmark job (--threads)")
    if kind == "inline":
        return InlineExecutor(fn)
    if kind == "ray":
        return RayExecutor(ray_address, gpus_per_job=None if use_gpus else 0.0,
                           cpus_per_job=float(threads) if threads else None, fn=fn, jobs_per_gpu=jobs_per_gpu)
    if kind != "local":
        raise ValueError(f"executor must be 'local', 'ray' or 'inline', got {kind!r}")
    if gpus:
        n = workers or len(gpus) * jobs_per_gpu
        slots = [g for g in gpus for _ in range(jobs_per_gpu)]
        return LocalExecutor(n, slots, threads, fn)  # threads None: affinity-mask cores / n
    n = workers or 1
    return LocalExecutor(n, None, threads, fn)


# ------------------------------------------------------------------------------------ scheduling
class _Events:
    """Prints events as JSON lines and appends them to a file."""

    def __init__(self, path: Optional[Path], echo: Optional[Callable[[dict], None]] = None):
        self.path = path
        self.t0 = time.time()
        self.echo = echo

    def __call__(self, event: str, **fields) -> dict:
        rec = {"event": event, "t": round(time.time() - self.t0, 1), **fields}
        line = json.dumps(rec, default=str)
        if self.echo is None:
            print(line, flush=True)
        else:
            self.echo(rec)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a") as f:
                f.write(line + "\n")
        return rec


_KIND_RANK = {"generate": 0, "prepare": 1, "fit": 2}


def run_jobs(jobs: Sequence[dict], executor, emit: Callable[..., dict], *, deadline: Optional[float] = None,
             grace: float = 45.0, retry_failed: bool = False, heartbeat: float = 60.0,
             estimate: Optional[Callable[[dict], tuple[float, str]]] = None,
             on_done: Optional[Callable[[dict, dict], None]] = None, min_start_s: float = 30.0) -> dict:
    """Run ``jobs`` (dicts of :class:`~toolkit.benchmark.plan.Job`) respecting their dependencies.

    Args:
        jobs: the jobs, in planning order (it sets the priority within a kind).
        executor: an executor (:func:`make_executor`).
        emit: event sink (``emit(event, **fields)``).
        deadline: ``time.time()`` by which everything must have stopped.
        grace: seconds between SIGTERM and the deadline.
        retry_failed: run again jobs whose marker says ``failed`` (default: report them).
        heartbeat: seconds between ``heartbeat`` events while jobs run.
        estimate: job -> (seconds, basis), printed when a job starts.
        on_done: called with (job, result) when a job finishes.
        min_start_s: no job starts later than this many seconds before ``deadline - grace``.

    Returns:
        Counts: ``done``, ``failed``, ``blocked``, ``remaining`` and ``ran`` (finished in this call).
    """
    from toolkit.benchmark.jobs import job_is_done, read_marker

    rank = {j["id"]: i for i, j in enumerate(jobs)}
    state: dict[str, str] = {}
    for j in jobs:
        if job_is_done(j):
            state[j["id"]] = "done"
            continue
        m = read_marker(j["folder"]) if j["kind"] != "generate" else None
        if m and m.get("status") == "failed" and m.get("fingerprint") == j["fingerprint"] and not retry_failed:
            state[j["id"]] = "failed"
            emit("skip_failed", job=j["id"], error=m.get("error"), hint="pass --retry-failed to run it again")
        else:
            state[j["id"]] = "pending"
    in_flight: dict = {}
    started: dict[str, float] = {}
    ran = 0
    stopping = False
    last_beat = time.time()

    def finish(handle) -> None:
        nonlocal ran
        job = in_flight.pop(handle)
        res = executor.result(handle, job)
        status = res.get("status", "failed")
        wall = res.get("wall_s", round(time.time() - started.get(job["id"], time.time()), 1))
        fields = {"job": job["id"], "wall_s": wall, "pid": res.get("pid"), "gpu": res.get("gpu")}
        if status == "done":
            state[job["id"]] = "done"
            ran += 1
            emit("done", **fields, result=res.get("result"))
        elif status == "failed":
            state[job["id"]] = "failed"
            ran += 1
            emit("failed", **fields, error=res.get("error"), log=job.get("extra", {}).get("log"))
        else:
            state[job["id"]] = "interrupted"
            emit("interrupted", **fields, error=res.get("error"))
        if on_done is not None:
            on_done(job, res)

    while True:
        for j in jobs:
            if state[j["id"]] == "pending" and any(state.get(d) in ("failed", "blocked") for d in j.get("depends", [])):
                state[j["id"]] = "blocked"
                emit("blocked", job=j["id"], by=[d for d in j["depends"] if state.get(d) in ("failed", "blocked")])
        if deadline is not None and time.time() >= deadline - grace - min_start_s:
            stopping = True  # too close to the limit to start anything
        ready = [j for j in jobs if state[j["id"]] == "pending" and all(state.get(d) == "done" for d in j.get("depends", []))]
        ready.sort(key=lambda j: (_KIND_RANK.get(j["kind"], 9), rank[j["id"]]))
        while ready and len(in_flight) < executor.capacity and not stopping:
            j = ready.pop(0)
            est = estimate(j) if estimate else (None, None)
            emit("start", job=j["id"], est_s=None if est[0] is None else round(est[0], 1), basis=est[1])
            started[j["id"]] = time.time()
            state[j["id"]] = "running"
            in_flight[executor.submit(j)] = j
        if not in_flight:
            break
        timeout = heartbeat
        if deadline is not None:
            timeout = max(0.0, min(timeout, deadline - grace - time.time()))
        try:
            for h in executor.wait(list(in_flight), timeout):
                finish(h)
        except KeyboardInterrupt:  # Ctrl-C: the running jobs save their state and stop, then we leave
            emit("stopping", running=[j["id"] for j in in_flight.values()], grace_s=grace,
                 note="interrupted by the user; rerun the same command to continue")
            executor.interrupt(list(in_flight), grace)
            for h in list(in_flight):
                finish(h)
            raise
        now = time.time()
        if deadline is not None and now >= deadline - grace and in_flight:
            emit("stopping", running=[j["id"] for j in in_flight.values()], grace_s=grace,
                 note="time limit: asking running jobs to save and stop; rerun the same command to continue")
            stopping = True
            executor.interrupt(list(in_flight), max(1.0, deadline - time.time()))
            for h in list(in_flight):
                finish(h)
            break
        if now - last_beat >= heartbeat and in_flight:
            last_beat = now
            emit("heartbeat", running=[{"job": j["id"], "elapsed_s": round(now - started[j["id"]], 0)} for j in in_flight.values()])
    counts = {k: sum(1 for v in state.values() if v == k) for k in ("done", "failed", "blocked")}
    counts["remaining"] = sum(1 for v in state.values() if v in ("pending", "interrupted", "running"))
    counts["ran"] = ran
    return counts


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


def _check_changed(jobs: Sequence[dict], redo_changed: bool, emit) -> None:
    """Jobs whose folder holds results of other settings: an error, or removed with ``redo_changed``."""
    from toolkit.benchmark.jobs import read_marker
    from toolkit.benchmark.plan import BenchmarkError

    changed = []
    for j in jobs:
        if j["kind"] == "generate":
            continue
        m = read_marker(j["folder"])
        if m and m.get("fingerprint") != j["fingerprint"]:
            changed.append(j)
    if not changed:
        return
    if not redo_changed:
        names = ", ".join(j["id"] for j in changed[:5]) + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")
        raise BenchmarkError(f"{len(changed)} job folder(s) hold results made with other settings ({names}); rerun with "
                             "the same settings, choose another --out, or pass --redo-changed to delete and redo them")
    for j in changed:
        emit("redo", job=j["id"], folder=j["folder"])
        shutil.rmtree(j["folder"], ignore_errors=True)


def _write_suite_index(spec) -> None:
    """After generate jobs: the suite's ``suite.json`` (every scene is complete, so nothing is regenerated)."""
    suites = {}
    for sc in spec.scenes:
        if sc.generate is not None:
            info = sc.generate["suite"]
            suites[info["root"]] = info
    for info in suites.values():
        from toolkit.synthetic.suite import generate_suite

        generate_suite(info["root"], families=info["families"], scenes_per_family=info["per_family"], seed=info["seed"],
                       size=info["size"], device=info["device"], spec_overrides=info["spec_overrides"] or None, progress=False)


def _export(bench: Path, export: Path, emit, budget: int = 15 * 2**20) -> list[Path]:
    """Copy what the write-up needs into ``export`` as 4 files: tables.md, tables.json,
    progress.jsonl and results.tar.gz (the plan, the run summaries, evaluations, histories and
    markers, then figures while they fit in ``budget`` bytes: a lent GPU machine brings back files
    of at most 16 MiB)."""
    import tarfile

    export.mkdir(parents=True, exist_ok=True)
    files = []
    for name in ("tables/tables.md", "tables/tables.json", "progress.jsonl"):
        src = bench / name
        if src.is_file():
            shutil.copy2(src, export / Path(name).name)
            files.append(export / Path(name).name)
    groups = [["benchmark.json", "runs/**/summary.json", "runs/**/job.json", "scenes/**/job.json", "scenes/**/settings.json",
               "runs/**/evaluation/evaluation.json", "runs/**/physics/estimate.json", "runs/**/physics/history.json"],
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
                  estimate_for: Optional[str] = None) -> dict:
    """Plan, run (in parallel, resumable) and tabulate a benchmark.

    Args:
        spec: a :class:`~toolkit.benchmark.plan.BenchmarkSpec`.
        out: the benchmark folder (see :mod:`toolkit.benchmark.plan` for its layout).
        executor: ``local``, ``ray`` or ``inline``.
        workers: worker processes (default: one per GPU x ``jobs_per_gpu``; 1 on a CPU).
        gpus: GPU ids to use (default: every visible GPU unless the settings say ``device: cpu``).
        jobs_per_gpu: workers sharing one GPU.
        threads: CPU threads per job (default: this process's affinity-mask cores divided by the
            jobs running at once; with Ray, the cluster's CPUs divided among its tasks).
        ray_address: Ray cluster address (``executor="ray"``).
        time_limit: seconds from now by which this call returns (jobs get SIGTERM ``grace`` seconds
            before); a rerun continues.
        grace: see ``time_limit``.
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

    Returns:
        ``{"complete": bool, "counts": {...}, "tables": path or None, "out": path}``.
    """
    from toolkit.benchmark.estimate import (
        PROFILES,
        Calibration,
        estimate_job,
        format_seconds,
        scene_info,
        sharing_slowdown,
        simulate_schedule,
    )
    from toolkit.benchmark.jobs import job_is_done, read_marker
    from toolkit.benchmark.plan import plan_benchmark

    t_start = time.time()
    deadline = t_start + time_limit if time_limit else None
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
    profile = PROFILES[estimate_for or ("cuda" if (gpus or (executor == "ray" and device != "cpu")) else "cpu")]

    # estimates: the model (slowed down when jobs share a GPU), rescaled by what finished jobs
    # measured (also in earlier runs: the markers keep both numbers)
    scene_by_name = {s.name: s for s in spec.scenes}
    slow = sharing_slowdown(jobs_per_gpu) if gpus else 1.0
    calib = Calibration()
    particles: dict[str, int] = {}
    for j in jobs:
        if j["kind"] == "prepare":
            m = read_marker(j["folder"]) or {}
            if (m.get("result") or {}).get("n_particles"):
                particles[j["id"]] = int(m["result"]["n_particles"])
    model: dict[str, float] = {}

    def price(j: dict, n_part: Optional[int]) -> None:
        sc = scene_by_name[j["scene"]]
        info = scene_info(sc.path, None if Path(sc.path, "all_data.json").is_file() else (sc.generate or {}).get("spec"))
        model[j["id"]] = estimate_job(j, info, profile, n_part) * slow
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
    total_est = sum(estimate(j)[0] for j in todo)
    done_ids = {j["id"] for j in jobs if j not in todo}
    wall = simulate_schedule(jobs, {j["id"]: estimate(j)[0] for j in todo}, n_workers, done_ids)
    per_chunk = (time_limit - grace) if time_limit else None
    emit("plan", out=str(bench), jobs=len(jobs), to_run=len(todo), scenes=len(spec.scenes),
         strategies=[s.label for s in spec.strategies], cameras=spec.cameras, executor=executor, workers=n_workers,
         gpus=list(gpus) if gpus else None, profile=profile.name, time_limit_s=time_limit,
         estimated_worker_s=round(total_est, 0), estimated_wall_s=round(wall, 0),
         estimated_chunks=None if not per_chunk else max(1, math.ceil(wall / max(1.0, per_chunk))),
         note="estimates are rough until jobs of each kind have finished (basis 'model' vs 'calibrated'); the wall "
              "time follows the dependencies (stage 0 before its fits)" + (f"; {jobs_per_gpu} jobs sharing a GPU are "
                                                                          f"assumed {slow:.2f}x slower each" if slow != 1 else ""))
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
                           use_gpus=device != "cpu")
        previous = _stop_on_sigterm()
        try:
            counts = run_jobs(jobs, ex, emit, deadline=deadline, grace=grace, retry_failed=retry_failed, heartbeat=heartbeat,
                              estimate=estimate, on_done=on_done, min_start_s=min(30.0, 0.1 * (time_limit or 0)))
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
                key = f"{j['material']}|{j['cameras']}|{j['strategy']}"
                planned[key] = planned.get(key, 0) + 1
        md, _, tables = write_tables(bench, strategies=[s.label for s in spec.strategies], settings=_settings_summary(spec, jobs),
                                     planned=planned)
        tables_path = str(md)
        if figures and tables.get("records"):
            from toolkit.benchmark.plots import write_figures
            from toolkit.benchmark.tables import collect_records

            records, _ = collect_records(bench)
            write_figures(bench, records, strategies=[s.label for s in spec.strategies])
        emit("tables", markdown=str(md), rows=sum(len(t["rows"]) for t in tables["tables"]),
             headline=_headline(tables))
    except Exception as exc:  # noqa: BLE001 - the jobs' results are on disk; tables can be redone with --tables-only
        emit("tables_failed", error=f"{type(exc).__name__}: {exc}")
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
            out.append({"material": t["material"], "cameras": t["cameras"], "strategy": r["strategy"], "n": r["n"],
                        **{k.replace("mae:", "mae_"): (None if c["mean"] is None else round(c["mean"], 5)) for k, c in v.items()}})
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use `projo4d benchmark` or benchmarks/strategy_comparison.py")

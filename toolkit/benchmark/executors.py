"""Executors of benchmark jobs on this machine, and the interface every executor follows.

An executor runs job dicts (:class:`~toolkit.benchmark.plan.Job`) given to it by the scheduler
(:func:`toolkit.benchmark.scheduler.run_jobs`) and has

* ``name`` and ``capacity`` (jobs at a time);
* ``submit(job) -> handle``; ``wait(handles, timeout) -> finished handles``;
  ``result(handle, job) -> result dict`` (``status`` ``done``/``failed``/``interrupted``);
* ``interrupt(handles, grace)``: ask the running jobs to save and stop (SIGTERM), force after
  ``grace`` seconds; ``shutdown()``.

Executors: :class:`LocalExecutor` and :class:`InlineExecutor` here,
:class:`~toolkit.benchmark.ray_executor.RayExecutor` (Ray, one machine or many) and
:class:`~toolkit.benchmark.slurm.SubmititExecutor` (SLURM through submitit); :func:`make_executor`
builds one by name.

:class:`LocalExecutor` uses :mod:`concurrent.futures` futures and ``cf.wait``; it starts its own
``spawn`` process per job instead of a ``ProcessPoolExecutor`` for what a pool does not give: the
job's GPU (``CUDA_VISIBLE_DEVICES``) and thread variables set in the process's environment before
it starts (a pool picks the process, and libraries such as OpenBLAS read the variables when they
load), one job's crash taking only that job (a pool breaks as a whole: ``BrokenProcessPool``), and
SIGTERM to a given job's process at a time limit.
"""

from __future__ import annotations

import concurrent.futures as cf
import importlib
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from typing import Callable, Optional, Sequence

__all__ = ["LocalExecutor", "InlineExecutor", "least_loaded_gpu", "make_executor", "job_call", "JOB_FUNCTION"]

#: the function each worker runs on a job dict
JOB_FUNCTION = "toolkit.benchmark.jobs:execute_job"


def _resolve(fn: str) -> Callable[[dict], dict]:
    module, _, name = fn.partition(":")
    return getattr(importlib.import_module(module), name)


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


def least_loaded_gpu(gpus: Sequence[str], slots: dict[str, int], running: Sequence[tuple[str, float, float]],
                     now: float) -> str:
    """The GPU for the next job: one with a free slot whose running jobs have the least
    estimated work left.

    Args:
        gpus: the GPU ids, in the order listed (ties go to the first).
        slots: jobs each GPU may run at a time.
        running: ``(gpu, start time, estimated seconds)`` of each running job (``time.time()``
            seconds).
        now: the current ``time.time()``.

    A running job's work left is its estimate less its elapsed time, but at least a tenth of
    the estimate (a job past its estimate is still running). Counting jobs alone put three of
    the longest fits of a 24-fit round on one card, where two of them did not finish.
    """
    def key(g: str) -> tuple:
        mine = [(t0, est) for gg, t0, est in running if gg == g]
        left = sum(max(est - (now - t0), 0.1 * est) for t0, est in mine)
        return (len(mine) >= slots.get(g, 1), left, len(mine), gpus.index(g))

    return min(gpus, key=key)


class LocalExecutor:
    """Jobs in worker processes on this machine, one fresh ``spawn`` process per job.

    A process is started when its job is submitted (never later, from another thread), so the
    job's GPU is set before anything in it starts CUDA, and a process crashing takes only its
    own job with it.

    Args:
        workers: number of worker processes (jobs at a time).
        gpus: one GPU id (a ``CUDA_VISIBLE_DEVICES`` value) per worker slot, e.g. ``["0", "0",
            "1", "1"]`` for two jobs on each of two GPUs; ``None`` for CPU workers. Each job
            goes to the GPU with a free slot whose running jobs have the least estimated work
            left (:func:`least_loaded_gpu`), so four stage-0 jobs on four GPUs get one GPU each
            and the longest fits do not pile up on one card.
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
        self._slots = {g: sum(1 for x in gpus if str(x) == g) for g in self._gpus} if gpus else {}
        self._running: dict = {}  # handle -> (process, GPU or None, start time, estimated seconds)
        self.capacity = workers
        if threads is None:
            from toolkit.threads import default_cap, per_job_threads

            threads = min(per_job_threads(workers), default_cap("cuda" if gpus else "cpu"))
        self._threads = threads
        self._fn = fn

    def submit(self, job: dict) -> cf.Future:
        estimate_s = float((job.get("extra") or {}).get("estimate_s") or 1.0)
        gpu = least_loaded_gpu(self._gpus, self._slots, [(g, t0, e) for _, g, t0, e in self._running.values()],
                               time.time()) if self._gpus else None
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
        self._running[handle] = (process, gpu, time.time(), estimate_s)
        return handle

    def wait(self, handles: Sequence, timeout: Optional[float]) -> list:
        done, _ = cf.wait(list(handles), timeout=timeout, return_when=cf.FIRST_COMPLETED)
        return list(done)

    def result(self, handle, job: dict) -> dict:  # noqa: ARG002 - the job is in the result already
        self._running.pop(handle)
        return handle.result()

    def _pids(self) -> list[int]:
        return [p.pid for p, *_ in self._running.values() if p.is_alive()]

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
        for process, *_ in self._running.values():
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

def job_call(fn: str, job: dict, threads: Optional[int] = None, concurrent: Optional[int] = None) -> dict:
    """Body of one job a cluster engine started (a Ray task, a SLURM job): ``threads`` CPU
    threads (its CPUs), the stop handler (SIGTERM: save and stop), then the job.

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
                  fn: str = JOB_FUNCTION, use_gpus: bool = True, slurm: Optional[dict] = None):
    """An executor: ``local`` (GPUs when given, else ``workers`` CPU processes), ``ray`` (the
    cluster's GPUs unless ``use_gpus`` is false), ``slurm`` (SLURM jobs through submitit:
    ``slurm`` holds :class:`~toolkit.benchmark.slurm.SubmititExecutor` arguments, at least
    ``folder``; ``workers`` is the jobs queued at a time, ``threads`` the CPUs of each) or ``inline``."""
    if threads is not None:
        from toolkit.threads import parse_count

        threads = parse_count(threads, "threads per benchmark job (--threads)")
    if kind == "inline":
        return InlineExecutor(fn)
    if kind == "ray":
        from toolkit.benchmark.ray_executor import RayExecutor

        return RayExecutor(ray_address, gpus_per_job=None if use_gpus else 0.0,
                           cpus_per_job=float(threads) if threads else None, fn=fn, jobs_per_gpu=jobs_per_gpu)
    if kind == "slurm":
        from toolkit.benchmark.slurm import SubmititExecutor

        kw = dict(slurm or {})
        if "folder" not in kw:
            raise ValueError("the slurm executor needs a folder for its job files (slurm={'folder': ...})")
        if not use_gpus:
            kw["gpus_per_job"] = 0
        if workers:
            kw.setdefault("max_jobs", workers)
        if threads:
            kw.setdefault("cpus_per_job", threads)
        return SubmititExecutor(kw.pop("folder"), fn=fn, **kw)
    if kind != "local":
        raise ValueError(f"executor must be 'local', 'ray', 'slurm' or 'inline', got {kind!r}")
    if gpus:
        n = workers or len(gpus) * jobs_per_gpu
        slots = [g for g in gpus for _ in range(jobs_per_gpu)]
        return LocalExecutor(n, slots, threads, fn)  # threads None: affinity-mask cores / n
    n = workers or 1
    return LocalExecutor(n, None, threads, fn)

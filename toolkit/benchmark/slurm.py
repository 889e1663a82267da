"""Benchmark jobs as SLURM jobs through submitit (``projo4d benchmark --executor slurm``).

The scheduler (:func:`toolkit.benchmark.runner.run_jobs`) runs on the login node (or in a small
job of its own) and submits one SLURM job per benchmark job once the jobs it depends on are done;
``capacity`` jobs are queued or running at a time. Every job sees the benchmark folder and the
scenes at the same paths (a shared file system), as on any cluster.

Retries, two kinds:

* **Preempted or out of time**: submitit catches SLURM's warning signal (``USR2``, 90 s before
  the end), requeues the job (:class:`_Call` is ``Checkpointable``) at most ``max_retries`` times,
  and the job resumes from its newest checkpoint (written every few minutes of work).
* **Died** (killed, out of memory, a node lost: no result): resubmitted as a new job, at most
  ``max_retries`` times; it resumes from its checkpoints. A job that *raises* is a failure of the
  job, not of the machine, and is not retried (as with Ray).

``cluster="local"`` runs the same jobs as local processes through submitit's ``LocalExecutor``
(no SLURM needed): what the test suite runs, with a job killed and resubmitted and a job
preempted (``USR2``) and requeued. Requires ``pip install 'projo4d[slurm]'``.
"""

from __future__ import annotations

import math
import shutil
import signal
import subprocess
import time
from pathlib import Path
from typing import Any, Optional, Sequence

from toolkit.benchmark.executors import JOB_FUNCTION, job_call

__all__ = ["SubmititExecutor"]

try:  # the requeue hook is submitit's; without submitit the executor refuses to start anyway
    from submitit.helpers import Checkpointable as _Checkpointable
except ImportError:  # pragma: no cover - submitit is optional
    _Checkpointable = object


class _Call(_Checkpointable):
    """What one SLURM job runs: ``threads`` CPU threads, the stop handler, then the job.

    Being ``Checkpointable``, a preempted or timed-out job is requeued with the same arguments
    (the default ``checkpoint`` resubmits this call); the job resumes from its own checkpoints.
    """

    def __call__(self, fn: str, job: dict, threads: Optional[int], concurrent: Optional[int]) -> dict:
        return job_call(fn, job, threads, concurrent)


class _Handle:
    """One benchmark job and the submitit job now running it (a new one after a resubmission)."""

    __slots__ = ("job", "sjob", "attempts", "outcome", "stopping", "errors")

    def __init__(self, job: dict, sjob: Any):
        self.job, self.sjob, self.attempts = job, sjob, 1
        self.outcome: Optional[dict] = None
        self.stopping = False
        self.errors: list[str] = []


class SubmititExecutor:
    """Jobs as SLURM jobs (or local processes with ``cluster="local"``) through submitit.

    Args:
        folder: where submitit keeps its pickles and each job's stdout/stderr
            (``BENCH/slurm`` from :func:`~toolkit.benchmark.runner.run_benchmark`).
        cluster: ``"slurm"`` (needs ``sbatch`` and ``srun`` on this machine) or ``"local"``.
        partition: SLURM partition (default: the cluster's default partition).
        time_min: wall-clock limit of each job in minutes (a job that reaches it is requeued and
            resumes, see the module docstring).
        gpus_per_job: GPUs per job (``--gpus-per-node``); 0 for CPU jobs.
        cpus_per_job: CPUs per job (``--cpus-per-task``), also the job's thread count; default
            8 with a GPU, else 1.
        mem_gb: memory per job in GB (default: the partition's default).
        max_jobs: jobs queued or running at a time.
        max_retries: requeues after preemption/timeout, and resubmissions of a job that died.
        options: more submitit parameters, e.g. ``{"slurm_account": "proj", "slurm_qos": "normal",
            "slurm_constraint": "h100", "slurm_setup": ["module load cuda"]}``.
        fn: ``"module:function"`` run on each job dict.
        poll_s: seconds between looks at the queue.
    """

    name = "slurm"

    def __init__(self, folder: str | Path, *, cluster: str = "slurm", partition: Optional[str] = None,
                 time_min: int = 240, gpus_per_job: int = 1, cpus_per_job: Optional[int] = None,
                 mem_gb: Optional[float] = None, max_jobs: int = 32, max_retries: int = 2,
                 options: Optional[dict] = None, fn: str = JOB_FUNCTION, poll_s: float = 2.0):
        try:
            import submitit
        except ImportError:
            raise RuntimeError("the SLURM executor needs submitit: pip install 'projo4d[slurm]' "
                               "(or use --executor local / ray)") from None
        if cluster not in ("slurm", "local"):
            raise ValueError(f"cluster must be 'slurm' or 'local', got {cluster!r}")
        missing = [c for c in ("sbatch", "srun") if shutil.which(c) is None] if cluster == "slurm" else []
        if missing:
            raise RuntimeError(f"--executor slurm needs SLURM's sbatch and srun on this machine (run it on a login "
                               f"node); not on PATH: {', '.join(missing)}")
        for name, value, low in (("time_min", time_min, 1), ("gpus_per_job", gpus_per_job, 0), ("max_jobs", max_jobs, 1),
                                 ("max_retries", max_retries, 0)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        self._submitit = submitit
        self.cluster = cluster
        self.capacity = max_jobs
        self.max_retries = max_retries
        self.threads = int(cpus_per_job or (8 if gpus_per_job else 1))
        self.poll_s = float(poll_s)
        self._fn = fn
        self.folder = Path(folder)
        self._executor = submitit.AutoExecutor(folder=str(self.folder), cluster=cluster,
                                               slurm_max_num_timeout=max_retries)
        params: dict[str, Any] = {"timeout_min": time_min, "gpus_per_node": gpus_per_job, "cpus_per_task": self.threads,
                                  "tasks_per_node": 1, "nodes": 1, "name": "projo4d"}
        if mem_gb is not None:
            params["mem_gb"] = mem_gb
        if partition:
            params["slurm_partition"] = partition
        params.update(options or {})
        try:
            self._executor.update_parameters(**params)
        except (ValueError, TypeError, NameError) as err:  # submitit names an unknown parameter with NameError
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ValueError(f"SLURM job parameters (--slurm-options): {first}") from None
        # jobs on one machine share it (local); a SLURM job has its own allocation
        self._concurrent = max_jobs if cluster == "local" else 1

    def _submit(self, job: dict):
        sjob = self._executor.submit(_Call(), self._fn, job, self.threads, self._concurrent)
        if self.cluster == "local":  # no network file system to wait for: a job with no result died
            sjob._results_timeout_s = 1
        return sjob

    def submit(self, job: dict) -> _Handle:
        return _Handle(job, self._submit(job))

    def _settled(self, h: _Handle) -> bool:
        """Whether ``h`` has an outcome now; resubmits a job that died while retries remain."""
        if h.outcome is not None:
            return True
        if not h.sjob.done():
            return False
        errors = self._submitit.core.utils
        try:
            h.outcome = dict(h.sjob.result())
        except errors.FailedJobError as exc:  # the job raised: its own failure, never retried
            h.outcome = {"id": h.job["id"], "status": "interrupted" if h.stopping else "failed",
                         "error": _last_line(exc)}
        except errors.UncompletedJobError as exc:  # no result: the job's process or node died
            h.errors.append(_last_line(exc))
            if not h.stopping and h.attempts <= self.max_retries:
                h.sjob = self._submit(h.job)
                h.attempts += 1
                return False
            h.outcome = {"id": h.job["id"], "status": "interrupted" if h.stopping else "failed",
                         "error": f"job {h.sjob.job_id} died after {h.attempts} attempt(s): {h.errors[-1]} "
                                  f"(its output: {h.sjob.paths.stderr})"}
        h.outcome.setdefault("attempts", h.attempts)
        return True

    def wait(self, handles: Sequence[_Handle], timeout: Optional[float]) -> list:
        end = time.time() + (math.inf if timeout is None else timeout)
        while True:
            ready = [h for h in handles if self._settled(h)]
            if ready or time.time() >= end:
                return ready
            time.sleep(max(0.0, min(self.poll_s, end - time.time())))

    def result(self, handle: _Handle, job: dict) -> dict:  # noqa: ARG002 - the handle holds its job
        self._settled(handle)
        return handle.outcome or {"id": job["id"], "status": "interrupted", "error": "still running"}

    def _ask_to_stop(self, h: _Handle) -> None:
        """SIGTERM to the job (it saves at the end of its iteration and returns ``interrupted``)."""
        h.stopping = True
        if self.cluster == "local":
            process = getattr(h.sjob, "_process", None)  # submitit's controller forwards SIGTERM to the task
            if process is not None and process.poll() is None:
                process.send_signal(signal.SIGTERM)
        else:
            subprocess.run(["scancel", "--signal=TERM", str(h.sjob.job_id)], check=False, capture_output=True)

    def interrupt(self, handles: Sequence[_Handle], grace: float) -> None:
        """Ask every job to save and stop, wait up to ``grace`` seconds, then cancel the rest."""
        for h in handles:
            self._ask_to_stop(h)
        end = time.time() + grace
        while time.time() < end and not all(self._settled(h) for h in handles):
            time.sleep(min(self.poll_s, 0.5))
        for h in handles:
            if not self._settled(h):
                h.sjob.cancel(check=False)
                h.outcome = {"id": h.job["id"], "status": "interrupted", "error": f"cancelled after {grace:.0f} s",
                             "attempts": h.attempts}

    def shutdown(self) -> None:
        pass


def _last_line(exc: BaseException) -> str:
    """The line that says what went wrong: the exception line of a job's traceback, else the
    message's last line that is not one of submitit's log paths."""
    text = str(exc)
    if "Traceback" in text:
        text = text[text.rindex("Traceback"):].split("\n----", 1)[0]
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip() and not ln.strip().startswith("- /")]
    return lines[-1][:500] if lines else type(exc).__name__


def sbatch_script(executor: SubmititExecutor) -> str:
    """The ``sbatch`` file a job of ``executor`` would be submitted with (for checks and docs;
    needs ``cluster="slurm"`` parameters but no SLURM)."""
    from submitit.slurm.slurm import _make_sbatch_string

    params = dict(executor._executor._executor.parameters)
    return _make_sbatch_string(command="python -m submitit.core._submit FOLDER", folder=str(executor.folder), **params)

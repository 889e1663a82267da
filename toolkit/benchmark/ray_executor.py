"""Benchmark jobs as Ray tasks (``projo4d benchmark --executor ray``), on one machine or a cluster.

Start a cluster with ``ray start --head`` (and ``ray start --address HEAD:6379`` on the other
machines), then ``--executor ray --ray-address auto``. Ray is optional (``pip install
'projo4d[ray]'``); every machine must see the benchmark folder and the scenes at the same paths
(a shared file system). A task whose worker process or machine dies is rerun (``max_retries``) and
resumes from the job's checkpoints. tests/test_ray_executor.py runs it on a local Ray cluster
(logical GPUs, a killed task); it has not been tested on a multi-machine cluster here.
"""

from __future__ import annotations

from typing import Optional, Sequence

from toolkit.benchmark.executors import JOB_FUNCTION, job_call

__all__ = ["RayExecutor"]


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
                                  retry_exceptions=False)(job_call)

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

"""The Ray executor on a real local Ray cluster (Ray is in the test extra, so CI runs this).

One cluster for the module: 2 CPUs and 2 *logical* GPUs (Ray schedules GPU resources and sets
``CUDA_VISIBLE_DEVICES`` per task without any GPU present), so the GPU path is exercised on CPU.
A job kills its own worker process on its first attempt (SIGKILL, as the OOM killer or a lost node
would): with retries Ray reruns it and every job finishes; without, that job is reported failed.
"""

from __future__ import annotations

import time

import pytest

pytestmark = pytest.mark.xdist_group("benchmark")  # one Ray cluster at a time (with test_benchmark's)

from tests.executor_contract import FN, check_killed_job_rerun, check_raising_job_not_retried, contract_jobs as _jobs, run_contract as _run


@pytest.fixture(scope="module")
def ray_cluster():
    import ray

    t0 = time.time()
    ray.init(num_cpus=2, num_gpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        yield time.time() - t0
    finally:
        ray.shutdown()


def test_killed_job_is_retried_and_every_job_finishes(ray_cluster, tmp_path):
    from toolkit.benchmark.runner import RayExecutor

    ex = RayExecutor(None, gpus_per_job=0.0, cpus_per_job=1.0, fn=FN, max_retries=2)
    assert ex.capacity == 2 and ex.threads == 1
    check_killed_job_rerun(tmp_path, *_run(_jobs(tmp_path), ex))


def test_without_retries_a_killed_job_fails_and_a_raising_job_is_not_retried(ray_cluster, tmp_path):
    from toolkit.benchmark.runner import RayExecutor

    ex = RayExecutor(None, gpus_per_job=0.0, cpus_per_job=1.0, fn=FN, max_retries=0)
    counts, events = _run(_jobs(tmp_path, crash=(1,)), ex)
    assert counts["done"] == 2 and counts["failed"] == 1
    failed = [e for e in events if e["event"] == "failed"]
    assert [e["job"] for e in failed] == ["j1"] and "Worker" in failed[0]["error"]  # WorkerCrashedError
    # an exception in the job is a failure of the job, not of the machine: never retried
    ex = RayExecutor(None, gpus_per_job=0.0, cpus_per_job=1.0, fn=FN, max_retries=3)
    check_raising_job_not_retried(tmp_path / "raise", *_run(_jobs(tmp_path / "raise", n=1, crash=(), raises=(0,)), ex))


def test_gpu_resources_one_task_per_gpu(ray_cluster, tmp_path):
    from toolkit.benchmark.runner import RayExecutor

    ex = RayExecutor(None, gpus_per_job=None, fn=FN)  # the cluster's GPUs: one task each
    assert ex.capacity == 2 and ex.threads == 1  # 2 CPUs shared by the tasks the 2 GPUs hold
    counts, events = _run(_jobs(tmp_path, n=4, crash=()), ex)
    assert counts["done"] == 4
    gpus = [e["gpu"] for e in events if e["event"] == "done"]
    assert sorted(set(gpus)) == ["0", "1"]  # each task saw exactly one (logical) GPU

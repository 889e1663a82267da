"""The SLURM executor (submitit), run for real with submitit's local cluster (jobs are local processes).

The same contract as the Ray test (tests/test_ray_executor.py): a job that kills its own process
on its first attempt (SIGKILL, as the OOM killer or a lost node would) is resubmitted and every job
finishes; without retries it is reported failed; a job that raises is a failure, never retried; at
a time limit running jobs get SIGTERM, save and report ``interrupted``. The SLURM-only parameters
(partition, GPUs, time, CPUs) are checked in the ``sbatch`` file submitit would submit.
"""

from __future__ import annotations

import json
import time

import pytest

pytest.importorskip("submitit")

pytestmark = pytest.mark.xdist_group("benchmark")

from tests.executor_contract import FN, check_killed_job_rerun, check_raising_job_not_retried, contract_jobs as _jobs, run_contract as _run


def _executor(tmp_path, **kw):
    from toolkit.benchmark.slurm import SubmititExecutor

    return SubmititExecutor(tmp_path / "submitit", cluster="local", gpus_per_job=0, max_jobs=2, fn=FN, poll_s=0.2, **kw)


def test_killed_job_is_resubmitted_and_every_job_finishes(tmp_path):
    ex = _executor(tmp_path, max_retries=2)
    assert ex.capacity == 2 and ex.threads == 1
    done = check_killed_job_rerun(tmp_path, *_run(_jobs(tmp_path), ex))
    assert len({e["pid"] for e in done.values()}) == 3  # each job in a process of its own


def test_without_retries_a_killed_job_fails_and_a_raising_job_is_not_retried(tmp_path):
    counts, events = _run(_jobs(tmp_path, n=2, crash=(1,)), _executor(tmp_path, max_retries=0))
    assert counts["done"] == 1 and counts["failed"] == 1
    failed = [e for e in events if e["event"] == "failed"]
    assert [e["job"] for e in failed] == ["j1"] and "died after 1 attempt(s)" in failed[0]["error"]
    check_raising_job_not_retried(tmp_path / "raise", *_run(_jobs(tmp_path / "raise", n=1, crash=(), raises=(0,)),
                                                            _executor(tmp_path, max_retries=3)))


def test_time_limit_asks_running_jobs_to_save_and_stop(tmp_path):
    """SIGTERM reaches the job through submitit's controller: it stops early and says interrupted."""
    from toolkit.benchmark.slurm import SubmititExecutor

    ex = SubmititExecutor(tmp_path / "submitit", cluster="local", gpus_per_job=0, max_jobs=2, poll_s=0.2,
                          fn="tests.bench_helpers:sleepy_job")
    jobs = [{"id": f"s{i}", "kind": "fit", "folder": str(tmp_path / f"s{i}"), "fingerprint": "x", "depends": [],
             "seconds": 60} for i in range(2)]
    t0 = time.time()
    counts, events = _run(jobs, ex, deadline=time.time() + 12, grace=6)
    assert time.time() - t0 < 30
    assert counts["done"] == 0 and counts["remaining"] == 2
    stopped = [e for e in events if e["event"] == "interrupted"]
    assert sorted(e["job"] for e in stopped) == ["s0", "s1"]


def test_sbatch_file_carries_partition_gpus_time_and_cpus(tmp_path, monkeypatch):
    import shutil

    from toolkit.benchmark.slurm import SubmititExecutor, sbatch_script

    real_which = shutil.which
    monkeypatch.setattr(shutil, "which", lambda name: f"/usr/bin/{name}" if name in ("sbatch", "srun") else real_which(name))
    ex = SubmititExecutor(tmp_path / "submitit", partition="gpu-h100", time_min=90, gpus_per_job=1, mem_gb=64,
                          max_retries=3, options={"slurm_account": "physics"})
    text = sbatch_script(ex)
    for line in ("#SBATCH --partition=gpu-h100", "#SBATCH --time=90", "#SBATCH --gpus-per-node=1",
                 "#SBATCH --cpus-per-task=8", "#SBATCH --mem=64GB", "#SBATCH --account=physics",
                 "#SBATCH --signal=USR2@"):
        assert line in text, (line, text)
    assert ex.threads == 8 and ex.max_retries == 3


def test_bad_parameters_are_named(tmp_path, monkeypatch):
    from toolkit.benchmark.slurm import SubmititExecutor

    monkeypatch.setenv("PATH", str(tmp_path))  # no SLURM here
    with pytest.raises(RuntimeError, match="needs SLURM's sbatch and srun.*not on PATH: sbatch, srun"):
        SubmititExecutor(tmp_path, cluster="slurm")

    with pytest.raises(ValueError, match="time_min must be an integer >= 1, got 0"):
        SubmititExecutor(tmp_path, cluster="local", time_min=0)
    with pytest.raises(ValueError, match="cluster must be 'slurm' or 'local'"):
        SubmititExecutor(tmp_path, cluster="pbs")
    with pytest.raises(ValueError, match="--slurm-options.*Unknown argument 'acount' for executor 'slurm'"):
        SubmititExecutor(tmp_path, cluster="local", options={"slurm_acount": "physics"})


def test_make_executor_and_the_benchmark_flags_reach_the_executor(tmp_path, monkeypatch):
    from toolkit.benchmark import commands
    from toolkit.benchmark.executors import make_executor
    from toolkit.cli import main

    ex = make_executor("slurm", workers=3, threads=2, use_gpus=False, slurm={"folder": tmp_path, "cluster": "local"})
    assert (ex.name, ex.capacity, ex.threads, ex.cluster) == ("slurm", 3, 2, "local")
    with pytest.raises(ValueError, match="needs a folder"):
        make_executor("slurm")

    seen = {}

    def fake_run_benchmark(spec, out, **kw):
        seen.update(kw)
        return {"complete": True}

    monkeypatch.setattr(commands, "spec_from_args", lambda args: None)
    monkeypatch.setattr("toolkit.benchmark.runner.run_benchmark", fake_run_benchmark)
    assert main(["benchmark", "--out", str(tmp_path / "b"), "--executor", "slurm", "--slurm-partition", "gpu-h100",
                 "--slurm-time", "90", "--slurm-retries", "3", "--workers", "8",
                 "--slurm-options", json.dumps({"slurm_account": "physics"})]) == 0
    assert seen["executor"] == "slurm"
    assert seen["slurm"] == {"cluster": "slurm", "time_min": 90, "gpus_per_job": 1, "max_retries": 3, "partition": "gpu-h100",
                             "mem_gb": None, "options": {"slurm_account": "physics"}, "max_jobs": 8}


def test_a_preempted_job_is_requeued_by_submitit_and_finishes(tmp_path):
    """SLURM warns a job it is preempted or out of time with USR2: submitit's handler in the job
    checkpoints our Checkpointable call and requeues it (locally: the controller restarts it), and
    the job's second attempt finishes: the same submitit job, no resubmission of ours."""
    import os
    import signal

    from toolkit.benchmark.slurm import SubmititExecutor

    ex = SubmititExecutor(tmp_path / "submitit", cluster="local", gpus_per_job=0, max_jobs=1, poll_s=0.2,
                          fn="tests.slurm_helpers:preempted_once_job")
    job = {"id": "p0", "kind": "fit", "folder": str(tmp_path / "p0"), "fingerprint": "x", "depends": []}
    handle = ex.submit(job)
    pid_file = tmp_path / "p0" / "pid"
    t0 = time.time()
    while not pid_file.is_file() and time.time() - t0 < 30:
        time.sleep(0.1)
    time.sleep(0.5)  # the job is in its sleep, submitit's signal handlers installed
    first_pid = int(pid_file.read_text())
    os.kill(first_pid, signal.SIGUSR2)
    assert ex.wait([handle], timeout=40) == [handle]
    res = ex.result(handle, job)
    assert res["status"] == "done" and res["attempts"] == 2 and res["pid"] != first_pid, res
    assert handle.attempts == 1  # requeued by submitit, not resubmitted by the executor
    assert time.time() - t0 < 40

"""CPU thread pools of a run (issue #25): resolution, application, and what executors pass to jobs.

Whatever changes process-wide state (torch's pools, the inter-op pool that can be set only
once, OpenBLAS) runs in a child process, so this pytest process keeps its own settings.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from toolkit.threads import (
    DEFAULT_CAP,
    ENV_CONCURRENT,
    ENV_THREADS,
    ThreadSettingError,
    available_cores,
    child_environment,
    parse_count,
    per_job_threads,
    resolve_threads,
)

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, env: dict, timeout: float = 60) -> dict:
    """Run ``code`` in a fresh interpreter with ``env`` added; its last stdout line is JSON."""
    full = {k: v for k, v in os.environ.items() if k not in (ENV_THREADS, ENV_CONCURRENT, "OMP_NUM_THREADS",
                                                              "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    full.update(env)
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=full, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------------ resolution
def test_default_divides_the_cores_among_concurrent_runs():
    # 16 cores (the H100 machine) shared by N GPU runs: 16 // N threads each, at least 1, at most the cap
    for n, want in [(1, DEFAULT_CAP), (2, 8), (3, 5), (4, 4), (8, 2), (16, 1), (40, 1)]:
        c = resolve_threads(environ={ENV_CONCURRENT: str(n)}, cores=16, device="cuda")
        assert (c.threads, c.source, c.cores, c.concurrent) == (want, "default", 16, n)
    assert resolve_threads(environ={}, cores=2, device="cuda:0").threads == 2  # nothing told: one run owns the mask
    assert resolve_threads(environ={}, cores=128).threads == DEFAULT_CAP
    # a CPU run defaults to one thread (measured faster at the toolkit's CPU sizes), told or not
    assert [resolve_threads(environ={ENV_CONCURRENT: str(n)}, cores=16, device="cpu").threads for n in (1, 2, 32)] == [1, 1, 1]
    assert resolve_threads(environ={}, cores=16, device="cpu", cap=4).threads == 4
    # the sum over concurrent runs never exceeds the cores (when there are at least as many cores as runs)
    for cores in (2, 6, 16, 64):
        for n in range(1, cores + 1):
            assert n * resolve_threads(environ={ENV_CONCURRENT: str(n)}, cores=cores).threads <= cores


def test_precedence_settings_then_env_then_default():
    env = {ENV_THREADS: "3", ENV_CONCURRENT: "8"}
    c = resolve_threads(5, environ=env, cores=16)
    assert (c.threads, c.source) == (5, "settings")
    c = resolve_threads(None, environ=env, cores=16)
    assert (c.threads, c.source) == (3, "env")
    assert resolve_threads(None, environ={ENV_CONCURRENT: "8"}, cores=16).source == "default"
    # explicit counts are honoured beyond the default's cap and beyond the cores
    assert resolve_threads(32, environ={}, cores=16).threads == 32
    assert resolve_threads(None, environ={ENV_THREADS: "12"}, cores=2).threads == 12
    assert resolve_threads(None, environ={ENV_THREADS: ""}, cores=4).source == "default"  # empty = unset


def test_per_job_threads_uses_the_affinity_mask(monkeypatch):
    assert available_cores() == len(os.sched_getaffinity(0))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)))  # a fake 16-core mask
    assert available_cores() == 16
    assert [per_job_threads(n) for n in (1, 2, 3, 4, 8, 16, 32)] == [16, 8, 5, 4, 2, 1, 1]
    assert resolve_threads(environ={ENV_CONCURRENT: "4"}).threads == 4
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3, 7})  # e.g. `taskset -c 3,7`
    assert per_job_threads(1) == 2 and per_job_threads(2) == 1


@pytest.mark.parametrize("bad", [0, -1, "x", "0", "-2", "", 1.5, True, None, [2]])
def test_invalid_counts_name_the_field(bad):
    with pytest.raises(ThreadSettingError, match=r"RunSettings\.threads must be an integer >= 1.*got"):
        parse_count(bad, "RunSettings.threads")
    if bad is not None:
        with pytest.raises(ThreadSettingError, match="RunSettings.threads"):
            resolve_threads(bad, environ={}, cores=4, name="RunSettings.threads")


def test_invalid_environment_and_settings_name_their_source(tmp_path):
    with pytest.raises(ThreadSettingError, match=f"environment variable {ENV_THREADS} .*'x'"):
        resolve_threads(environ={ENV_THREADS: "x"}, cores=4)
    with pytest.raises(ThreadSettingError, match=f"environment variable {ENV_CONCURRENT} .*'0'"):
        resolve_threads(environ={ENV_CONCURRENT: "0"}, cores=4)
    assert parse_count("4", "x") == 4 and parse_count(4.0, "x") == 4
    from toolkit.pipeline import RunSettings

    for bad in (0, -1, "x"):
        with pytest.raises(ValueError, match=r"RunSettings\.threads \(--threads\) must be an integer >= 1"):
            RunSettings(scene=str(tmp_path), threads=bad).validate()
    try:  # a valid count passes (this empty folder then fails as a scene, which is checked afterwards)
        RunSettings(scene=str(tmp_path), threads=2).validate()
    except ValueError as err:
        assert "threads" not in str(err)


def test_run_command_threads_flag(tmp_path, capsys):
    import argparse

    from toolkit.commands.run import configure, settings_from_args

    parser = argparse.ArgumentParser()
    configure(parser)
    assert settings_from_args(parser.parse_args([str(tmp_path), "--threads", "3"])).threads == 3
    assert settings_from_args(parser.parse_args([str(tmp_path)])).threads is None
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"scene: {tmp_path}\nthreads: 2\n")
    assert settings_from_args(parser.parse_args(["--config", str(cfg)])).threads == 2  # config key
    assert settings_from_args(parser.parse_args(["--config", str(cfg), "--threads", "5"])).threads == 5  # flag wins
    for bad in ("0", "-1", "x"):
        with pytest.raises(SystemExit):
            parser.parse_args([str(tmp_path), "--threads", bad])
        assert "--threads must be an integer >= 1" in capsys.readouterr().err


def test_child_environment_is_restored():
    env = {"OMP_NUM_THREADS": "7"}
    with child_environment(2, 8, environ=env) as new:
        assert env["OMP_NUM_THREADS"] == env["OPENBLAS_NUM_THREADS"] == env[ENV_THREADS] == "2"
        assert env[ENV_CONCURRENT] == "8" and new[ENV_THREADS] == "2"
    assert env == {"OMP_NUM_THREADS": "7"}


# ------------------------------------------------------------------------------------ application
def test_configure_sets_torch_blas_and_child_variables_in_a_fresh_process():
    code = ("import json, os, numpy, torch\n"
            "from toolkit.threads import configure_threads, blas_threads\n"
            "before = torch.get_num_threads()\n"
            "c = configure_threads({explicit})\n"
            "import scipy.linalg  # its own OpenBLAS, loaded after: reads OPENBLAS_NUM_THREADS\n"
            "print(json.dumps({{'choice': c.to_dict(), 'torch': torch.get_num_threads(), 'before': before,\n"
            "  'interop': torch.get_num_interop_threads(), 'blas': sorted(set(blas_threads().values())),\n"
            "  'omp': os.environ.get('OMP_NUM_THREADS'), 'openblas': os.environ.get('OPENBLAS_NUM_THREADS'),\n"
            "  'mine': os.environ.get('PROJO4D_THREADS')}}))")
    cores = available_cores()
    # default with two runs told: cores // 2 (1 on this 2-core machine)
    got = _python(code.format(explicit="None, device='cuda'"), {ENV_CONCURRENT: "2"})
    want = max(1, cores // 2)
    assert got["choice"] == {"threads": want, "source": "default", "cores": cores, "concurrent": 2}
    assert got["torch"] == got["interop"] == want
    assert got["blas"] in ([want], [])  # numpy's and scipy's OpenBLAS (empty only where none is loaded)
    assert got["omp"] == got["openblas"] == str(want)
    assert got["mine"] is None  # a run does not pin PROJO4D_THREADS for later runs in its process
    # an explicit count wins over the environment, and may exceed the cores
    got = _python(code.format(explicit="3"), {ENV_THREADS: "1", ENV_CONCURRENT: "2"})
    assert got["choice"]["source"] == "settings" and got["torch"] == got["interop"] == 3 and got["omp"] == "3"
    # the environment variable a parent sets
    got = _python(code.format(explicit="None"), {ENV_THREADS: "1"})
    assert got["choice"]["source"] == "env" and got["torch"] == 1 and got["blas"] in ([1], [])


# ------------------------------------------------------------------------------------ executors
def test_local_executor_gives_each_job_its_share_of_the_affinity_mask(tmp_path, monkeypatch):
    from toolkit.benchmark.runner import make_executor, run_jobs

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)))  # the parent sees 16 cores
    for var in (ENV_THREADS, ENV_CONCURRENT):
        monkeypatch.delenv(var, raising=False)
    assert make_executor("local", workers=2)._threads == 1  # CPU workers: at most the CPU default (1)
    assert make_executor("local", workers=2, threads=3)._threads == 3
    for bad in (0, -1):
        with pytest.raises(ThreadSettingError, match=r"threads per benchmark job \(--threads\) must be an integer >= 1"):
            make_executor("local", workers=2, threads=bad)
    assert make_executor("local", gpus=["0"], jobs_per_gpu=1)._threads == DEFAULT_CAP  # one GPU job: capped at 8
    # four jobs sharing one GPU ("g0" is only a label here: the job touches no GPU)
    ex = make_executor("local", gpus=["g0"], jobs_per_gpu=4, fn="tests.thread_helpers:report_threads_job")
    jobs = [{"id": "a", "kind": "fit", "folder": str(tmp_path / "a"), "fingerprint": "x", "depends": []},
            {"id": "b", "kind": "fit", "folder": str(tmp_path / "b"), "fingerprint": "x", "depends": [], "threads": 3}]
    events = []
    t = time.time()
    try:
        counts = run_jobs(jobs, ex, lambda e, **f: events.append({"event": e, **f}), heartbeat=100, deadline=t + 120,
                          grace=5, min_start_s=0)
    finally:
        ex.shutdown()
    assert counts["done"] == 2, events
    res = {e["job"]: e["result"] for e in events if e["event"] == "done"}
    # 16 cores / 4 workers = 4 threads, in torch and in the variables the job's process started with
    a = res["a"]
    assert (a["torch"], a["interop"], a["omp_env"], a["openblas_env"], a["threads_env"], a["concurrent_env"]) == \
        (4, 4, "4", "4", "4", "4")
    assert a["choice"]["source"] == "env" and a["blas"] in ([4], [])
    # a job whose settings name a count keeps it (settings > environment)
    assert res["b"]["torch"] == 3 and res["b"]["choice"]["source"] == "settings"
    assert os.environ.get(ENV_THREADS) is None  # the parent's environment is as it was


def test_ray_task_body_applies_the_task_cpus():
    # what a Ray task runs (without Ray): threads = the task's CPUs, in torch and in the environment
    code = ("import json\nfrom toolkit.benchmark.runner import _ray_call\n"
            "r = _ray_call('tests.thread_helpers:report_threads_job', {'id': 'r', 'folder': '/tmp/r'}, 3, 5)\n"
            "q = _ray_call('tests.thread_helpers:report_threads_job', {'id': 'q', 'folder': '/tmp/q'}, 1)\n"
            "print(json.dumps([r['result'], q['result']]))")
    got, second = _python(code, {})
    assert (got["torch"], got["omp_env"], got["threads_env"], got["concurrent_env"]) == (3, "3", "3", "5")
    # without a count of tasks on the node: its cores divided by the task's threads
    assert (second["torch"], second["threads_env"], second["concurrent_env"]) == (1, "1", str(available_cores()))


def test_ray_executor_sets_threads_per_task(tmp_path):
    pytest.importorskip("ray")  # optional extra: projo4d[ray]
    from toolkit.benchmark.runner import RayExecutor, run_jobs

    ex = RayExecutor(None, gpus_per_job=0.0, cpus_per_job=1.0, fn="tests.thread_helpers:report_threads_job")
    events = []
    try:
        run_jobs([{"id": "r", "kind": "fit", "folder": str(tmp_path / "r"), "fingerprint": "x", "depends": []}], ex,
                 lambda e, **f: events.append({"event": e, **f}), heartbeat=100, min_start_s=0)
    finally:
        ex.shutdown()
    res = next(e["result"] for e in events if e["event"] == "done")
    assert res["torch"] == 1 and res["omp_env"] == "1"


# ------------------------------------------------------------------------------------ the pipeline
def test_run_applies_and_records_its_thread_count(tmp_path, capsys):
    import torch

    from tests.physics_fixtures import tiny_scene
    from toolkit.cli import main

    scene = tiny_scene(tmp_path / "scene")
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        args = ["run", str(scene), "--out", str(tmp_path / "run"), "--geometry", "oracle", "--config", "configs/demo.yaml",
                "--sim", '{"dx": 0.04, "substeps": 30}', "--curriculum", "XAS:2@3,XASM:2", "--device", "cpu", "--threads", "1"]
        assert main(args) == 0
        assert torch.get_num_threads() == 1  # applied in this process
    finally:
        torch.set_num_threads(before)
    capsys.readouterr()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["threads"] == {"threads": 1, "source": "settings", "cores": available_cores(), "concurrent": 1}

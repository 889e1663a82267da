"""Helpers for the benchmark tests: job functions for the executor tests (importable by spawned
worker processes) and a loader for the scripts in ``benchmarks/`` (not a package)."""

from __future__ import annotations

import importlib.util
import os
import time
from pathlib import Path
from types import ModuleType

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark_script(stem: str) -> ModuleType:
    """``benchmarks/<stem>.py`` as a module (executed fresh on every call)."""
    spec = importlib.util.spec_from_file_location(stem, BENCHMARKS / f"{stem}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def sleepy_job(job: dict) -> dict:
    """Sleeps ``job["seconds"]`` unless asked to stop (SIGTERM sets the runner's stop flag)."""
    from toolkit.benchmark.jobs import _STOP, install_stop_handler

    install_stop_handler()
    _STOP.clear()
    t0 = time.time()
    while time.time() - t0 < job.get("seconds", 0.1):
        if _STOP.is_set():
            return {"id": job["id"], "status": "interrupted", "pid": os.getpid(), "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"),
                    "wall_s": round(time.time() - t0, 2)}
        time.sleep(0.02)
    return {"id": job["id"], "status": "done", "pid": os.getpid(), "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"),
            "wall_s": round(time.time() - t0, 2), "result": {}}

"""Job functions for the executor tests (importable by spawned worker processes)."""

from __future__ import annotations

import os
import time


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

"""Job functions for the Ray executor tests (imported by Ray worker processes)."""

from __future__ import annotations

import os
import signal
from pathlib import Path


def crash_once_job(job: dict) -> dict:
    """Counts its attempts in ``job["folder"]/attempts``; with ``job["crash_first"]`` the first
    attempt kills its own worker process (SIGKILL, as the OOM killer or a lost node would)."""
    folder = Path(job["folder"])
    folder.mkdir(parents=True, exist_ok=True)
    counter = folder / "attempts"
    attempts = int(counter.read_text()) + 1 if counter.is_file() else 1
    counter.write_text(str(attempts))
    if job.get("crash_first") and attempts == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    if job.get("raise"):
        raise ValueError(f"job {job['id']} raises on purpose")
    return {"id": job["id"], "status": "done", "attempts": attempts, "pid": os.getpid(),
            "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"), "result": {}}

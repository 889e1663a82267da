"""Job functions for the SLURM executor tests (run by submitit's local job processes)."""

from __future__ import annotations

import os
import time
from pathlib import Path


def preempted_once_job(job: dict) -> dict:
    """Counts its attempts in ``job["folder"]/attempts`` and writes its pid to ``pid``; the first
    attempt waits (up to 60 s) to be preempted, a later one returns at once."""
    folder = Path(job["folder"])
    folder.mkdir(parents=True, exist_ok=True)
    counter = folder / "attempts"
    attempts = int(counter.read_text()) + 1 if counter.is_file() else 1
    counter.write_text(str(attempts))
    (folder / "pid").write_text(str(os.getpid()))
    if attempts == 1:
        time.sleep(60)
    return {"id": job["id"], "status": "done", "attempts": attempts, "pid": os.getpid(), "result": {}}

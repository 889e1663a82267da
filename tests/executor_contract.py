"""The contract every cluster executor of `projo4d benchmark` is tested against (Ray, SLURM):
tiny jobs (``tests.ray_helpers:crash_once_job``), one killed on its first attempt."""

from __future__ import annotations

from pathlib import Path

#: the job function the contract's jobs run
FN = "tests.ray_helpers:crash_once_job"


def contract_jobs(tmp_path: Path, n: int = 3, crash=(1,), raises=()) -> list[dict]:
    """``n`` independent jobs; those in ``crash`` kill their process on the first attempt, those in
    ``raises`` raise."""
    return [{"id": f"j{i}", "kind": "fit", "folder": str(tmp_path / f"j{i}"), "fingerprint": "x", "depends": [],
             "crash_first": i in crash, "raise": i in raises} for i in range(n)]


def run_contract(jobs: list[dict], executor, **kw) -> tuple[dict, list[dict]]:
    """Run ``jobs`` on ``executor`` through the scheduler; returns its counts and the events."""
    from toolkit.benchmark.scheduler import run_jobs

    events: list[dict] = []
    counts = run_jobs(jobs, executor, lambda e, **f: events.append({"event": e, **f}), heartbeat=100, min_start_s=0, **kw)
    return counts, events


def check_killed_job_rerun(tmp_path: Path, counts: dict, events: list[dict]) -> dict:
    """The three default jobs all done, job 1 after one kill; returns the ``done`` events by job."""
    assert counts == {"done": 3, "failed": 0, "blocked": 0, "remaining": 0, "ran": 3}
    attempts = {i: int((tmp_path / f"j{i}" / "attempts").read_text()) for i in range(3)}
    assert attempts == {0: 1, 1: 2, 2: 1}  # j1 was killed once and rerun
    done = {e["job"]: e for e in events if e["event"] == "done"}
    assert set(done) == {"j0", "j1", "j2"}
    return done


def check_raising_job_not_retried(tmp_path: Path, counts: dict, events: list[dict]) -> None:
    """A job that raises fails once: an error of the job, not of the machine, is never retried."""
    assert counts["failed"] == 1 and int((tmp_path / "j0" / "attempts").read_text()) == 1
    assert "raises on purpose" in [e for e in events if e["event"] == "failed"][0]["error"]

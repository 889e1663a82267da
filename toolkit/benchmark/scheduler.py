"""The scheduler of a benchmark's jobs: dependencies, priorities, time limit, events.

:func:`run_jobs` starts a job once the jobs it depends on are done (stage 0 before the fits that
share it), ``generate`` before ``prepare`` before ``fit``, as many at a time as the executor's
``capacity`` (any executor of :mod:`toolkit.benchmark.executors`). With a time limit it asks the
running jobs to save and stop ``grace`` seconds before it (SIGTERM), then forces them. Each
finished job leaves a ``job.json`` marker (:mod:`toolkit.benchmark.jobs`), so a rerun skips it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

__all__ = ["run_jobs", "Events"]


class Events:
    """Prints events as JSON lines and appends them to a file."""

    def __init__(self, path: Optional[Path], echo: Optional[Callable[[dict], None]] = None):
        self.path = path
        self.t0 = time.time()
        self.echo = echo

    def __call__(self, event: str, **fields) -> dict:
        rec = {"event": event, "t": round(time.time() - self.t0, 1), **fields}
        line = json.dumps(rec, default=str)
        if self.echo is None:
            print(line, flush=True)
        else:
            self.echo(rec)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a") as f:
                f.write(line + "\n")
        return rec


_KIND_RANK = {"generate": 0, "variant": 0, "prepare": 1, "fit": 2}


def _interleaved_rank(jobs: Sequence[dict]) -> dict[str, tuple[int, int]]:
    """Priority within a kind: the k-th scene of every material before the (k+1)-th of any, then
    planning order. A chunk that ends early leaves every family with the same number of scenes."""
    seen: dict[str, list[str]] = {}
    rank = {}
    for i, j in enumerate(jobs):
        scenes = seen.setdefault(str(j.get("material")), [])
        if j.get("scene") not in scenes:
            scenes.append(j.get("scene"))
        rank[j["id"]] = (scenes.index(j.get("scene")), i)
    return rank


def _skip_unneeded(jobs: Sequence[dict], state: dict[str, str], emit: Callable[..., dict]) -> None:
    """Mark ``done`` a pending job whose dependants are all done already (a scene whose fits
    finished in an earlier chunk, or on another machine, is not generated or prepared again)."""
    dependants: dict[str, list[str]] = {}
    for j in jobs:
        for d in j.get("depends", []):
            dependants.setdefault(d, []).append(j["id"])
    changed = True
    while changed:
        changed = False
        for j in jobs:
            users = dependants.get(j["id"])
            if state[j["id"]] == "pending" and users and all(state.get(u) == "done" for u in users):
                state[j["id"]] = "done"
                emit("skip_unneeded", job=j["id"], reason="every job that needs it is done")
                changed = True


def run_jobs(jobs: Sequence[dict], executor, emit: Callable[..., dict], *, deadline: Optional[float] = None,
             grace: float = 45.0, retry_failed: bool = False, heartbeat: float = 60.0,
             estimate: Optional[Callable[[dict], tuple[float, str]]] = None,
             on_done: Optional[Callable[[dict, dict], None]] = None, min_start_s: float = 30.0,
             start_deadline: Optional[float] = None) -> dict:
    """Run ``jobs`` (dicts of :class:`~toolkit.benchmark.plan.Job`) respecting their dependencies.

    Args:
        jobs: the jobs, in planning order (it sets the priority within a kind).
        executor: an executor (:func:`make_executor`).
        emit: event sink (``emit(event, **fields)``).
        deadline: ``time.time()`` by which everything must have stopped.
        grace: seconds between SIGTERM and the deadline.
        retry_failed: run again jobs whose marker says ``failed`` (default: report them).
        heartbeat: seconds between ``heartbeat`` events while jobs run.
        estimate: job -> (seconds, basis), printed when a job starts.
        on_done: called with (job, result) when a job finishes.
        min_start_s: no job starts later than this many seconds before ``deadline - grace``.
        start_deadline: ``time.time()`` after which no job starts; the running ones go on until
            they finish (or until ``deadline``). For a lent machine whose time is counted: stop
            starting fits that cannot finish without stopping the ones that can.

    Returns:
        Counts: ``done``, ``failed``, ``blocked``, ``remaining`` and ``ran`` (finished in this call).
    """
    from toolkit.benchmark.jobs import job_is_done, read_marker

    rank = _interleaved_rank(jobs)
    state: dict[str, str] = {}
    for j in jobs:
        if job_is_done(j):
            state[j["id"]] = "done"
            continue
        m = read_marker(j["folder"]) if j["kind"] != "generate" else None
        if m and m.get("status") == "failed" and m.get("fingerprint") == j["fingerprint"] and not retry_failed:
            state[j["id"]] = "failed"
            emit("skip_failed", job=j["id"], error=m.get("error"), hint="pass --retry-failed to run it again")
        else:
            state[j["id"]] = "pending"
    _skip_unneeded(jobs, state, emit)
    in_flight: dict = {}
    started: dict[str, float] = {}
    ran = 0
    stopping = False
    last_beat = time.time()

    def finish(handle) -> None:
        nonlocal ran
        job = in_flight.pop(handle)
        res = executor.result(handle, job)
        status = res.get("status", "failed")
        wall = res.get("wall_s", round(time.time() - started.get(job["id"], time.time()), 1))
        fields = {"job": job["id"], "wall_s": wall, "pid": res.get("pid"), "gpu": res.get("gpu")}
        if status == "done":
            state[job["id"]] = "done"
            ran += 1
            emit("done", **fields, result=res.get("result"))
        elif status == "failed":
            state[job["id"]] = "failed"
            ran += 1
            emit("failed", **fields, error=res.get("error"), log=job.get("extra", {}).get("log"))
        else:
            state[job["id"]] = "interrupted"
            stopped = (res.get("result") or {}).get("stopped_at")
            emit("interrupted", **fields, error=res.get("error"), **({"stopped_at": stopped} if stopped else {}))
        if on_done is not None:
            on_done(job, res)

    while True:
        for j in jobs:
            if state[j["id"]] == "pending" and any(state.get(d) in ("failed", "blocked") for d in j.get("depends", [])):
                state[j["id"]] = "blocked"
                emit("blocked", job=j["id"], by=[d for d in j["depends"] if state.get(d) in ("failed", "blocked")])
        if deadline is not None and time.time() >= deadline - grace - min_start_s:
            stopping = True  # too close to the limit to start anything
        if start_deadline is not None and not stopping and time.time() >= start_deadline:
            stopping = True
            emit("start_limit", running=[j["id"] for j in in_flight.values()],
                 not_started=sum(1 for v in state.values() if v == "pending"),
                 note="no job starts from now on; the running ones finish")
        ready = [j for j in jobs if state[j["id"]] == "pending" and all(state.get(d) == "done" for d in j.get("depends", []))]
        ready.sort(key=lambda j: (_KIND_RANK.get(j["kind"], 9), rank[j["id"]]))
        while ready and len(in_flight) < executor.capacity and not stopping:
            j = ready.pop(0)
            est = estimate(j) if estimate else (None, None)
            emit("start", job=j["id"], est_s=None if est[0] is None else round(est[0], 1), basis=est[1])
            started[j["id"]] = time.time()
            state[j["id"]] = "running"
            in_flight[executor.submit(j)] = j
        if not in_flight:
            break
        timeout = heartbeat
        if deadline is not None:
            timeout = max(0.0, min(timeout, deadline - grace - time.time()))
        if start_deadline is not None and not stopping:  # wake up to say that nothing starts any more
            timeout = max(0.0, min(timeout, start_deadline - time.time()))
        try:
            for h in executor.wait(list(in_flight), timeout):
                finish(h)
        except KeyboardInterrupt:  # Ctrl-C: the running jobs save their state and stop, then we leave
            emit("stopping", running=[j["id"] for j in in_flight.values()], grace_s=grace,
                 note="interrupted by the user; rerun the same command to continue")
            executor.interrupt(list(in_flight), grace)
            for h in list(in_flight):
                finish(h)
            raise
        now = time.time()
        if deadline is not None and now >= deadline - grace and in_flight:
            emit("stopping", running=[j["id"] for j in in_flight.values()], grace_s=grace,
                 note="time limit: asking running jobs to save and stop; rerun the same command to continue")
            stopping = True
            executor.interrupt(list(in_flight), max(1.0, deadline - time.time()))
            for h in list(in_flight):
                finish(h)
            break
        if now - last_beat >= heartbeat and in_flight:
            last_beat = now
            emit("heartbeat", running=[{"job": j["id"], "elapsed_s": round(now - started[j["id"]], 0)} for j in in_flight.values()])
    counts = {k: sum(1 for v in state.values() if v == k) for k in ("done", "failed", "blocked")}
    counts["remaining"] = sum(1 for v in state.values() if v in ("pending", "interrupted", "running"))
    counts["ran"] = ran
    return counts

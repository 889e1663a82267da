"""How the benchmark's time model compares with what its runs measured, from their event logs.

``projo4d benchmark`` logs, for every job, the model's estimate when the job was planned
(``"event": "estimate"``, ``"basis": "model"``: the job alone on a worker, times the sharing
slowdown the plan assumed, named in the plan's note) and its measured wall time (``"done"``, with
the GPU it ran on) in ``OUT/progress.jsonl``. This script reads such logs (also the
``benchmark_log.jsonl`` copies under ``docs/results/``)
and prints one JSON line per fit:

* ``k``: how many jobs shared its GPU, averaged over its run time (from the start and done events);
* ``measured_s``: its wall time less any refit on a finer grid (``timings_s.refine_s``), so that a
  first fit is compared with the first fit's model;
* ``alone_model_s``: the model's estimate for it alone on the GPU (the logged estimate divided by
  the slowdown the plan assumed);
* ``slowdown``: measured over alone; ``overlap``: the GPU's overlap it implies in
  ``k / (1 + overlap (k - 1))`` (:func:`toolkit.benchmark.estimate.sharing_slowdown`), for k > 1.5;

then one ``{"summary": ...}`` line with the median overlap over the fits and per-kind ratios of
measured to logged estimates. Fits that never finished have no ``done`` event and are skipped.

Usage::

    python benchmarks/estimate_check.py docs/results/paper_size/round1[4-7]*/benchmark_log.jsonl
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from pathlib import Path

#: the plan note's fit slowdown: runs before 2026-11-28 named one for every job, later ones one for fits
_NOTE = re.compile(r"jobs sharing a GPU are assumed ([0-9.]+)x slower each|a fit is assumed ([0-9.]+)x slower")


def _events(path: Path) -> list[dict]:
    out = []
    for line in path.read_text().splitlines():
        if line.startswith("{"):
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut by a killed run
    return out


def assumed_slowdown(plan: dict) -> float:
    """The fit slowdown a plan event's note says its estimates include (1 without GPU sharing)."""
    m = _NOTE.search(plan.get("note", ""))
    if not m:
        return 1.0
    return float(m.group(1) or m.group(2))


def mean_sharing(job: str, spans: dict[str, tuple[float, float, str]]) -> float:
    """Time-averaged number of jobs (itself included) running on ``job``'s GPU while it ran."""
    t0, t1, gpu = spans[job]
    if t1 <= t0:
        return 1.0
    total = 0.0
    for other, (s0, s1, g) in spans.items():
        if g == gpu:
            total += max(0.0, min(t1, s1) - max(t0, s0))
    return total / (t1 - t0)


def check_log(path: Path) -> tuple[list[dict], dict[str, list[float]]]:
    """Per-fit records of one log, and measured / logged-estimate ratios per job kind."""
    events = _events(path)
    plan = next((e for e in events if e.get("event") == "plan"), {})
    slow = assumed_slowdown(plan)
    est = {e["job"]: e["est_s"] for e in events if e.get("event") == "estimate" and e.get("basis") == "model"}
    start = {e["job"]: e["t"] for e in events if e.get("event") == "start"}
    spans, done = {}, {}
    for e in events:
        if e.get("event") == "done" and e["job"] in start:
            spans[e["job"]] = (start[e["job"]], e["t"], str(e.get("gpu")))
            done[e["job"]] = e
    ratios: dict[str, list[float]] = {}
    fits = []
    for job, e in done.items():
        if not est.get(job):
            continue
        kind = job.split(":")[0]
        refine = float(((e.get("result") or {}).get("timings_s") or {}).get("refine_s") or 0.0)
        measured = e["wall_s"] - refine
        ratios.setdefault(kind, []).append(measured / est[job])
        if kind != "fit":
            continue
        k = mean_sharing(job, spans)
        alone = est[job] / slow
        rec = {"log": str(path), "job": job, "k": round(k, 2), "measured_s": round(measured, 1),
               "alone_model_s": round(alone, 1), "slowdown": round(measured / alone, 2), "refit_s": round(refine, 1)}
        if k > 1.5:
            rec["overlap"] = round((k * alone / measured - 1.0) / (k - 1.0), 3)
        fits.append(rec)
    return fits, ratios


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("logs", nargs="+", type=Path, help="benchmark_log.jsonl files of projo4d benchmark runs")
    args = p.parse_args(argv)
    overlaps, kinds = [], {}
    for path in args.logs:
        if not path.is_file():
            p.error(f"{path}: no such file (expected a benchmark event log, benchmark_log.jsonl)")
        fits, ratios = check_log(path)
        for rec in fits:
            print(json.dumps(rec))
            if "overlap" in rec:
                overlaps.append(rec["overlap"])
        for kind, r in ratios.items():
            kinds.setdefault(kind, []).extend(r)
    summary = {"fits_with_sharing": len(overlaps),
               "median_overlap": round(statistics.median(overlaps), 3) if overlaps else None,
               "measured_over_logged_estimate": {k: {"n": len(v), "median": round(statistics.median(v), 2),
                                                     "min": round(min(v), 2), "max": round(max(v), 2)}
                                                 for k, v in sorted(kinds.items())}}
    print(json.dumps({"summary": summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

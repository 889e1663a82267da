"""Discovery decisions over several runs of the same suite: which scenes are named in every run.

One run of ``benchmarks/discovery.py --geometry stage0`` gives one decision per scene, but stage 0
is not bit-reproducible on a GPU (atomic accumulation order), so the same scene run twice can be
named differently (2026-11-28: two medium slides missed on the GPU were named on the CPU). This
script reads several runs' folders (``OUT`` of ``benchmarks/discovery.py``, each its own stage-0
seed or machine), decides every record again with one set of thresholds, and reports

* each run's own summary (the numbers of ``benchmarks/discovery.py --report-only``);
* their mean over runs (top-1 on the effects the data show, false positives, the median
  future-gap shrink over all hidden physics scenes);
* per scene, its decision in each run, and whether the data show its effect in each run
  (refitting the true effect halves the future gap);
* **the stable rate**: of the scenes that ran in every run and whose effect the data show in
  each, those named in *every* run, and those named in at least one;
* the scenes whose decision changes between runs.

Usage::

    python benchmarks/discovery_runs.py D1 D2 --thresholds docs/results/discovery_images_full/thresholds.json
    python benchmarks/discovery_runs.py D1 D2 --calibrate --md runs.md    # thresholds from all runs' null scenes

Prints one JSON line per run and one ``{"runs": ...}`` line with the comparison; ``--md`` also
writes the tables.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Optional

import numpy as np

HERE = Path(__file__).resolve().parent


def _benchmark():
    spec = importlib.util.spec_from_file_location("discovery_benchmark", HERE / "discovery.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def load_run(folder: Path, bench) -> list[dict]:
    """The finished records of one run folder (``results*.jsonl``, read by the benchmark's
    ``iter_records``; failed scenes left out); a later line for the same scene replaces an earlier one."""
    folder = Path(folder)
    if not any(folder.glob("results*.jsonl")):
        raise SystemExit(f"{folder}: no results*.jsonl (expected the --out folder of benchmarks/discovery.py)")
    return list({r["scene"]: r for _, r in bench.iter_records(folder) if "error" not in r}.values())


def compare(runs: dict[str, list[dict]], truth_shrink, controls=("density", "camera_pose")) -> dict:
    """Per-scene agreement of decided runs (``{run name: records}``, records already decided).

    ``truth_shrink(record)`` is the future-gap shrink of refitting the true effect (``None`` when
    unknown); the data show a scene's effect in a run when it is at least 0.5. Returns ``scenes``
    (per scene: ``expected``, ``decisions`` and ``shows`` per run), ``in_every_run`` (how many
    scenes ran in every run), ``observable_every_run`` (those of them whose effect the data show
    in each run), ``named_every_run`` / ``named_some_run`` (their fractions named in every / at
    least one run; the first is what ``projo4d discover RUN_A RUN_B`` names,
    :func:`toolkit.discovery.consensus.consensus`),
    ``unstable`` (scenes decided differently by two runs) and ``null_flagged_any`` (null scenes
    flagged by at least one run).
    """
    by_scene: dict[str, dict] = defaultdict(lambda: {"expected": None, "effect": None, "decisions": {}, "shows": {}})
    for name, recs in runs.items():
        for r in recs:
            s = by_scene[r["scene"]]
            s["expected"], s["effect"] = r["expected"], r["effect"]
            s["decisions"][name] = r["decision"]
            phys = r["expected"] is not None and r["effect"] not in controls and r["effect"] != "none"
            s["shows"][name] = bool(phys and (truth_shrink(r) or 0.0) >= 0.5)
    in_all = [n for n, s in by_scene.items() if len(s["decisions"]) == len(runs)]
    obs = sorted(n for n in in_all if all(by_scene[n]["shows"].values()))
    every = [n for n in obs if all(d == by_scene[n]["expected"] for d in by_scene[n]["decisions"].values())]
    some = [n for n in obs if any(d == by_scene[n]["expected"] for d in by_scene[n]["decisions"].values())]
    unstable = sorted(n for n, s in by_scene.items() if len(set(s["decisions"].values())) > 1)
    nulls = [n for n, s in by_scene.items() if s["effect"] == "none"]
    return {
        "scenes": {n: dict(s) for n, s in sorted(by_scene.items())},
        "in_every_run": len(in_all),
        "observable_every_run": obs,
        "named_every_run": len(every) / len(obs) if obs else None,
        "named_some_run": len(some) / len(obs) if obs else None,
        "named_every_run_scenes": every,
        "unstable": unstable,
        "null_scenes": len(nulls),
        "null_flagged_any": sorted(n for n in nulls if any(d is not None for d in by_scene[n]["decisions"].values())),
    }


def _mean(xs) -> Optional[float]:
    xs = [x for x in xs if x is not None]
    return float(np.mean(xs)) if xs else None


def markdown(per_run: dict[str, dict], cmp: dict, thresholds_source: str) -> str:
    def pct(x):
        return "-" if x is None else f"{100 * x:.0f} %"

    lines = [f"# Discovery decisions over {len(per_run)} runs", "",
             "| run | scenes (hidden / null) | top-1 on effects the data show | named first or tied | false positives | "
             "median gap shrink, all hidden physics |", "|---|---|---|---|---|---|"]
    for name, s in per_run.items():
        obs = s.get("observable") or {}
        lines.append(f"| {name} | {s.get('n_hidden', 0)} / {s.get('n_null', 0)} | {pct(obs.get('top1'))} "
                     f"({obs.get('n', 0)} of {obs.get('of', 0)} show it) | {pct(obs.get('named_or_tied'))} | "
                     f"{pct(s.get('false_positive_rate'))} | {pct(s.get('median_gap_shrink_all'))} |")
    n_obs = len(cmp["observable_every_run"])
    lines += ["", f"Scenes in every run: {cmp['in_every_run']}; the data show the effect in every run in {n_obs} of "
              f"them; named in every run: {pct(cmp['named_every_run'])}, in at least one: {pct(cmp['named_some_run'])}. Null scenes flagged by "
              f"any run: {len(cmp['null_flagged_any'])} of {cmp['null_scenes']}. Thresholds: {thresholds_source}.", ""]
    names = list(per_run)
    lines += ["| scene | expected | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for scene, s in cmp["scenes"].items():
        if scene not in cmp["unstable"] and scene not in cmp["observable_every_run"]:
            continue
        cells = []
        for n in names:
            d = s["decisions"].get(n, "")
            mark = "" if n not in s["decisions"] else (" ✓" if d == s["expected"] else "")
            show = "" if not s["shows"].get(n) else " (shows)"
            cells.append(f"{'none' if d is None else d}{mark}{show}" if n in s["decisions"] else "-")
        lines.append(f"| {scene} | {s['expected'] or 'none'} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="run folders (--out of benchmarks/discovery.py); NAME=FOLDER names a run")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--thresholds", help="decide every run with this thresholds JSON")
    g.add_argument("--calibrate", action="store_true", help="calibrate on the null scenes of all runs together")
    p.add_argument("--md", help="write the tables here")
    args = p.parse_args(argv)
    if len(args.runs) < 2:
        p.error("give at least two run folders to compare")
    bench = _benchmark()
    from toolkit.discovery.calibration import DEFAULT_THRESHOLDS, Thresholds, calibrate, null_statistics

    runs: dict[str, list[dict]] = {}
    for item in args.runs:
        name, _, folder = item.rpartition("=") if "=" in item else (Path(item).name, "", item)
        if not Path(folder).is_dir():
            p.error(f"run folder {folder!r} does not exist")
        if name in runs:
            p.error(f"two runs are named {name!r}; name them NAME=FOLDER")
        runs[name] = load_run(Path(folder), bench)
    if args.thresholds:
        thr = Thresholds.load(args.thresholds)
    elif args.calibrate:
        stats = [null_statistics({"validation": r["validation"]}) for recs in runs.values() for r in recs if r["effect"] == "none"]
        if not stats:
            p.error("--calibrate: no null scene in any run")
        thr = calibrate(stats, source=f"calibrated on {len(stats)} null scenes of {len(runs)} runs")
    else:
        thr = DEFAULT_THRESHOLDS
    decided = {n: bench.redecide(recs, thr) for n, recs in runs.items()}
    per_run = {n: bench.summarize(recs, thr) for n, recs in decided.items()}
    for n, s in per_run.items():
        print(json.dumps({"run": n, "summary": s}), flush=True)
    cmp = compare(decided, bench.truth_shrink, bench.CONTROLS)
    cmp["mean_over_runs"] = {
        "top1_observable": _mean((s.get("observable") or {}).get("top1") for s in per_run.values()),
        "false_positive_rate": _mean(s.get("false_positive_rate") for s in per_run.values()),
        "median_gap_shrink_all": _mean(s.get("median_gap_shrink_all") for s in per_run.values()),
    }
    cmp["thresholds"] = thr.to_dict()
    print(json.dumps({"runs": cmp}), flush=True)
    if args.md:
        Path(args.md).write_text(markdown(per_run, cmp, thr.to_dict().get("source", "")))
    return 0


if __name__ == "__main__":
    sys.exit(main())

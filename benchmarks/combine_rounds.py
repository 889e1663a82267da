"""Combine the tables of several benchmark rounds into one table.

A benchmark too large for one machine or one session runs in rounds (``projo4d benchmark
--only``), each exporting its own ``tables.json`` (with its ``records``), or leaving only its
benchmark folder (``runs/**/summary.json``, e.g. unpacked from ``results.tar.gz`` when the round
ended before its export). This script joins them: the records of every round (a ``tables.json``
or a benchmark folder), plus single runs given by their ``summary.json`` (a
``projo4d run`` or ``benchmarks/whole_scene.py`` fit of the same scene), then the same tables
``projo4d benchmark`` writes (``tables.md``, ``tables.json``). A fit present in several rounds
(same scene, strategy, camera count and variant) is taken from the last one given.

Usage::

    python benchmarks/combine_rounds.py round1/tables.json round2/tables.json \\
        --summary sand/001=runs/sand_001/summary.json --out docs/results/paper_size/combined

A what-if table puts one arm of a round in another strategy's place: ``--stand-in held=progressive``
relabels every given round's ``held`` fits as ``progressive`` and drops that round's own
``progressive`` fits of those scenes, so ``benchmarks/paper_count.py`` counts the arm against the
other's paper row (round 19's ``whatif_counts/``).

Prints one JSON line: the fits per material and the output paths. Not part of the test run.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from toolkit.atomic import write_json  # noqa: E402
from toolkit.benchmark.tables import collect_records, record_from_summary, write_records_tables  # noqa: E402


def _key(rec: dict) -> tuple:
    return rec["scene"], rec["strategy"], rec.get("cameras"), rec.get("variant")


def _leaf_rounds(path: str, settings: dict) -> dict:
    """``{round: its own settings}`` oldest first: a combined table's rounds are listed one by one
    (they nested one level deeper with each combination before)."""
    inner = settings.get("rounds") if isinstance(settings, dict) else None
    if not isinstance(inner, dict):
        return {path: settings}
    flat: dict = {}
    for sub, sub_settings in inner.items():
        flat.update(_leaf_rounds(sub, sub_settings))
    for scene, summary in (settings.get("single runs") or {}).items():
        flat[f"{scene}={summary}"] = {"from": "single run summary"}
    return flat


def stand_in(found: list[dict], arms: dict[str, str]) -> list[dict]:
    """One round's records with each ``arm`` fit relabelled as the strategy ``arms[arm]``; the
    round's own fits of that strategy for the same scene and camera count are dropped."""
    replaced = {(r["scene"], arms[r["strategy"]], r.get("cameras")) for r in found if r["strategy"] in arms}
    out = []
    for rec in found:
        if rec["strategy"] in arms:
            out.append({**rec, "strategy": arms[rec["strategy"]], "stands_in_for": rec["strategy"]})
        elif (rec["scene"], rec["strategy"], rec.get("cameras")) not in replaced:
            out.append(rec)
    return out


def combine(rounds: list[pathlib.Path], summaries: list[tuple[str, pathlib.Path]], strategy: str = "progressive",
            cameras: int = 3, arms: dict[str, str] | None = None) -> tuple[list[dict], dict]:
    """Records of the rounds (later ones win) and of the single-run summaries; and the settings
    of each round, keyed by its file name, with a combined table's own rounds listed in its place.
    ``arms`` (``{arm: strategy}``): see :func:`stand_in`."""
    records: dict[tuple, dict] = {}
    settings = {}
    for path in rounds:
        if path.is_dir():
            found, _ = collect_records(path)
            if not found:
                raise SystemExit(f"{path} holds no finished fit (runs/**/summary.json)")
            settings[str(path)] = {"from": "run folders"}
        else:
            data = json.loads(path.read_text())
            if "records" not in data:
                raise SystemExit(f"{path} has no 'records': export it with a projo4d benchmark that writes them")
            found = data["records"]
            settings.update(_leaf_rounds(str(path), data.get("settings") or {}))
        for rec in stand_in(found, arms or {}):
            records[_key(rec)] = rec
    for scene, path in summaries:
        summary = json.loads(path.read_text())
        rec = record_from_summary(path.parent, summary, {"scene": scene, "strategy": strategy, "cameras": cameras})
        rec["run_dir"] = str(path)
        records[_key(rec)] = rec
    return sorted(records.values(), key=_key), settings


def _summary_arg(text: str) -> tuple[str, pathlib.Path]:
    scene, sep, path = text.partition("=")
    p = pathlib.Path(path)
    if not sep or not scene or not p.is_file():
        raise argparse.ArgumentTypeError(f"expected SCENE=PATH to a summary.json that exists, got {text!r}")
    return scene, p


def _stand_in_arg(text: str) -> tuple[str, str]:
    arm, sep, strategy = text.partition("=")
    if not sep or not arm or not strategy or arm == strategy:
        raise argparse.ArgumentTypeError(f"expected ARM=STRATEGY with two different labels (e.g. held=progressive), got {text!r}")
    return arm, strategy


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rounds", nargs="+", type=pathlib.Path,
                   help="each round's tables.json or benchmark folder, oldest first")
    p.add_argument("--summary", action="append", type=_summary_arg, default=[], metavar="SCENE=PATH",
                   help="a single run's summary.json for SCENE (family/index), e.g. sand/001=run/summary.json")
    p.add_argument("--strategy", default="progressive", help="strategy label of the --summary runs")
    p.add_argument("--stand-in", action="append", type=_stand_in_arg, default=[], metavar="ARM=STRATEGY",
                   help="count the rounds' ARM fits as STRATEGY's, replacing STRATEGY's own fits of those scenes "
                        "(a what-if table, e.g. held=progressive)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="folder for tables.md and tables.json")
    p.add_argument("--title", default="Strategy comparison (combined rounds)")
    args = p.parse_args(argv)
    for path in args.rounds:
        if not path.exists():
            p.error(f"{path} does not exist")
    arms = dict(args.stand_in)
    records, settings = combine(args.rounds, args.summary, args.strategy, arms=arms)
    singles = {s: str(f) for s, f in args.summary}
    extra = {"stand-ins": arms} if arms else {}
    write_records_tables(records, args.out, settings={"rounds": ", ".join(settings), "single runs": singles, **extra},
                         title=args.title)
    js = args.out / "tables.json"
    data = json.loads(js.read_text())
    data["settings"]["rounds"] = settings  # each round's own settings, in the JSON only (one long line in the table)
    write_json(js, data)
    per_material: dict[str, int] = {}
    for r in records:
        per_material[r["material"]] = per_material.get(r["material"], 0) + 1
    print(json.dumps({"benchmark": "combine_rounds", "fits": per_material, "tables": str(args.out / "tables.md")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The paper-style tables of a benchmark: per material, mean ± std over scenes, one row per strategy.

Input: one *record* per finished fit (:func:`record_from_run` reads a run folder's
``summary.json`` and ``evaluation/evaluation.json``)::

    {"scene": "neo_hookean/000", "material": "neo_hookean", "strategy": "progressive", "cameras": 3,
     "metrics": {"cd": 0.91, "emd": 0.042, "psnr": 22.3, "ssim": 0.91, "init_cd": 0.34, ...},
     "errors": {"E": 0.12, "nu": 0.05, "v0": 0.007}, "optimized": ["E", "nu"], "curriculum": "..."}

Output of :func:`build_tables` (also written as ``tables.json``; :func:`tables_markdown` renders it):

* ``tables``: per material and camera count, the columns CD, EMD (future frames), PSNR, SSIM
  (future frames, all cameras) and the MAE of v0 and of each optimized material parameter
  (log10 for E, mu, kappa, tau_Y, eta; absolute for nu and the friction angle in degrees), as
  ``{"mean", "std", "n"}`` per strategy (the paper's Tables 2, 3, 6, 7). The standard deviation is
  the population one (``ddof = 0``) over scenes; a value missing in a scene (no ground truth, a
  failed metric) leaves that scene out of that cell.
* ``per_scene``: the same numbers per scene (Table 2's layout: scenes as columns).
* ``ablation``: per material, when several camera counts ran: Init CD (frame 0), CD, PSNR and
  the parameter MAEs per strategy and camera count (Table 8's layout).
* ``claims``: pairwise comparisons of strategies on the means and the per-scene wins (e.g. does
  ``progressive`` beat ``sequential`` on future CD), for the write-up.

Scene variants (:mod:`toolkit.benchmark.variant_jobs`): a record of a variant carries
``"variant": NAME`` (scene ``<scene>@NAME``). Its rows sit in the same table as the original
scenes' rows, one row per strategy and variant (``row["variant"]``; rows of the scenes as
generated have no such key and come first); claims are made within each variant; the ablation
and the figures use the original scenes only.

A fit that *diverged* (its parameters left the valid set, see
:class:`~toolkit.benchmark.callbacks.DivergenceGuard`) is evaluated at its last valid estimate
and counted in the means, and listed with the iteration and the reason; a job that *failed*
(an error, e.g. a simulation that fails on the final estimate) has no numbers and is listed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Collection, Iterable, Optional, Sequence

from toolkit.grid_refinement import REFINED_FOLDER

__all__ = ["METRICS", "PARAM_LABELS", "record_from_run", "collect_records", "build_tables", "tables_markdown",
           "write_tables", "write_records_tables", "record_from_summary", "mean_std"]

#: metric key -> (label, better: "lower"/"higher", decimals)
METRICS: dict[str, tuple[str, str, int]] = {
    "cd": ("CD", "lower", 3),
    "emd": ("EMD", "lower", 4),
    "psnr": ("PSNR", "higher", 2),
    "ssim": ("SSIM", "higher", 3),
    "init_cd": ("Init CD", "lower", 3),
    "cd_train": ("CD (train)", "lower", 3),
    "emd_train": ("EMD (train)", "lower", 4),
    "psnr_held_out": ("PSNR held-out", "higher", 2),
    "ssim_held_out": ("SSIM held-out", "higher", 3),
}
MAIN_METRICS = ("cd", "emd", "psnr", "ssim")
ABLATION_METRICS = ("init_cd", "cd", "psnr")

#: parameter -> (label of its MAE, decimals), in the paper's order
PARAM_LABELS: dict[str, tuple[str, int]] = {
    "v0": ("MAE v0", 4),
    "E": ("MAE log E", 3),
    "nu": ("MAE nu", 3),
    "mu": ("MAE log mu", 3),
    "kappa": ("MAE log kappa", 3),
    "yield_stress": ("MAE log tau_Y", 3),
    "plastic_viscosity": ("MAE log eta", 3),
    "friction_angle": ("MAE friction angle (deg)", 2),
}


# ------------------------------------------------------------------------------------ records
def _num(x) -> Optional[float]:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def record_from_run(run_dir: str | Path, meta: Optional[dict] = None) -> Optional[dict]:
    """The record of one finished run folder (``None`` when its ``summary.json`` is missing).

    Args:
        run_dir: a pipeline run folder (``summary.json``, ``evaluation/evaluation.json``).
        meta: ``scene``, ``strategy``, ``cameras`` (default: from the summary's ``benchmark``
            section, else the folder names ``.../<scene>/cams<k>/<strategy>``).

    A fit refined on a finer grid (``summary["refined"]``, :mod:`toolkit.grid_refinement`) is
    recorded by its refined result, the method's final answer; the first fit's metrics and errors
    are kept under ``coarse``, and the timings add the refinement's.
    """
    run = Path(run_dir)
    sp = run / "summary.json"
    if not sp.is_file():
        return None
    summary = json.loads(sp.read_text())
    refined = run / REFINED_FOLDER  # by position, not the recorded path: an exported folder has moved
    if summary.get("refined") and (refined / "summary.json").is_file():
        first = record_from_summary(run, summary, meta)
        rec = record_from_summary(refined, json.loads((refined / "summary.json").read_text()),
                      {"scene": first["scene"], "strategy": first["strategy"], "cameras": first["cameras"],
                       **({"variant": first["variant"]} if first.get("variant") else {})})
        rec.update(optimized=first["optimized"], diverged=first["diverged"], run_dir=str(run),
                   timings_s=first["timings_s"], coarse={"metrics": first["metrics"], "errors": first["errors"]})
        return rec
    return record_from_summary(run, summary, meta)


def record_from_summary(run: Path, summary: dict, meta: Optional[dict] = None) -> dict:
    """The record of one fit from its ``summary`` (already read) and, when present, its run folder
    ``run``'s ``evaluation/evaluation.json`` (per-frame curves, held-out images). ``meta``: see
    :func:`record_from_run`. A summary without its folder (e.g. one kept in the docs) gives a
    record without those."""
    ev_path = run / "evaluation" / "evaluation.json"
    ev = json.loads(ev_path.read_text()) if ev_path.is_file() else {}
    bench = summary.get("benchmark") or {}
    meta = dict(meta or {})
    cams = meta.get("cameras", bench.get("cameras"))
    if cams is None and run.parent.name.startswith("cams"):
        cams = int(run.parent.name[4:])
    geo = ev.get("geometry") or {}
    images = ev.get("images") or {}
    held = images.get("held_out_cameras") or {}
    fut, tr = summary.get("future") or {}, summary.get("train") or {}
    cd_frames = geo.get("cd_per_frame") or []
    metrics = {"cd": _num(fut.get("cd")), "emd": _num(fut.get("emd")), "psnr": _num(fut.get("psnr")), "ssim": _num(fut.get("ssim")),
               "init_cd": _num(cd_frames[0]) if cd_frames else None, "cd_train": _num(tr.get("cd")),
               "emd_train": _num(tr.get("emd")), "psnr_held_out": _num(held.get("psnr_future")),
               "ssim_held_out": _num(held.get("ssim_future"))}
    errors = {k.split("/", 1)[-1]: _num(v) for k, v in (summary.get("errors") or {}).items() if _num(v) is not None}
    optimized = bench.get("optimized")
    if optimized is None:
        from materials import get_material

        try:
            optimized = [p.name for p in get_material(summary["material"]).params if p.optimize]
        except Exception:  # noqa: BLE001 - an unknown (plugin) material: report every error
            optimized = [k for k in errors if k != "v0"]
    return {
        **({"variant": meta["variant"]} if meta.get("variant") else {}),
        "scene": meta.get("scene") or str(run.parent.parent.name),
        "material": summary.get("material"),
        "strategy": meta.get("strategy") or bench.get("strategy") or run.name,
        "cameras": cams,
        "curriculum": summary.get("curriculum"),
        "metrics": metrics,
        "errors": errors,
        "optimized": list(optimized),
        "timings_s": summary.get("timings_s") or {},
        "per_frame": {"cd": geo.get("cd_per_frame"), "emd": geo.get("emd_per_frame"),
                      "psnr": (images.get("all_cameras") or {}).get("psnr_per_frame")},
        "n_train": ev.get("n_train"),
        "diverged": bench.get("diverged"),
        "stage0_lost_frames": (summary.get("stage0_coverage") or {}).get("lost_frames") or [],
        "run_dir": str(run),
    }


def collect_records(bench_dir: str | Path, only: Optional[Collection[tuple]] = None) -> tuple[list[dict], list[dict]]:
    """Records of every finished fit of a benchmark folder, and the failed jobs (from their markers).

    ``only``: ``(scene, strategy, cameras)`` triples to keep (the fits of the current plan); fits
    of an earlier, larger plan left in the folder are then not counted. Default: every fit.
    """
    from toolkit.benchmark.jobs import read_marker

    records, failures = [], []
    runs = Path(bench_dir) / "runs"
    if not runs.is_dir():
        return records, failures
    for marker_path in sorted(runs.rglob("job.json")):
        m = read_marker(marker_path.parent)
        if not m or m.get("kind") != "fit":
            continue
        meta = {"scene": m.get("scene"), "strategy": m.get("strategy"), "cameras": m.get("cameras")}
        if m.get("variant"):
            meta["variant"] = m["variant"]
        if only is not None and (meta["scene"], meta["strategy"], meta["cameras"]) not in only:
            continue
        if m.get("status") == "done":
            rec = record_from_run(marker_path.parent, meta)
            if rec is not None:
                rec["wall_s"] = m.get("wall_s_total")
                records.append(rec)
        elif m.get("status") == "failed":
            failures.append({**meta, "material": m.get("material"), "error": m.get("error"), "job": m.get("id")})
    return records, failures


# ------------------------------------------------------------------------------------ aggregation
def mean_std(values: Iterable[Optional[float]]) -> dict:
    """``{"mean", "std", "n"}`` of the finite values (population std); ``None`` entries when empty."""
    vals = [v for v in values if v is not None and math.isfinite(v)]
    if not vals:
        return {"mean": None, "std": None, "n": 0}
    m = sum(vals) / len(vals)
    return {"mean": m, "std": math.sqrt(sum((v - m) ** 2 for v in vals) / len(vals)), "n": len(vals)}


def _value(rec: dict, key: str) -> Optional[float]:
    if key.startswith("mae:"):
        return rec["errors"].get(key[4:])
    return rec["metrics"].get(key)


def _param_columns(records: Sequence[dict]) -> list[str]:
    names = set()
    for r in records:
        names |= {p for p in r.get("optimized", []) if p in r["errors"]}
        if "v0" in r["errors"]:
            names.add("v0")
    order = list(PARAM_LABELS)
    return [p for p in order if p in names] + sorted(names - set(order))


def _columns(keys: Sequence[str], params: Sequence[str]) -> list[dict]:
    cols = [{"key": k, "label": METRICS[k][0], "better": METRICS[k][1], "decimals": METRICS[k][2]} for k in keys]
    for p in params:
        label, dec = PARAM_LABELS.get(p, (f"MAE {p}", 3))
        cols.append({"key": f"mae:{p}", "label": label, "better": "lower", "decimals": dec})
    return cols


def _order(values: Iterable[str], preferred: Optional[Sequence[str]]) -> list[str]:
    values = list(dict.fromkeys(values))
    pref = [v for v in (preferred or []) if v in values]
    return pref + sorted(v for v in values if v not in pref)


def build_tables(records: Sequence[dict], strategies: Optional[Sequence[str]] = None, failures: Sequence[dict] = (),
                 settings: Optional[dict] = None, planned: Optional[dict] = None) -> dict:
    """Aggregate records into the tables described in the module docstring.

    Args:
        records: one per finished fit.
        strategies: row order (default: alphabetical).
        failures: failed jobs, listed with the tables.
        settings: what was run (stored as is under ``settings``).
        planned: ``{(material, cameras, strategy): number of scenes planned}`` as
            ``"material|cameras|strategy"`` keys (``"...|variant"`` for a variant's rows), to show
            ``done/planned``.
    """
    out: dict = {"format": "projo4d-benchmark-tables", "version": 1, "settings": settings or {}, "tables": [],
                 "ablation": [], "claims": [], "failures": list(failures)}
    materials = _order((r["material"] for r in records), None)
    for mat in materials:
        mrecs = [r for r in records if r["material"] == mat]
        params = _param_columns(mrecs)
        strat_order = _order((r["strategy"] for r in mrecs), strategies)
        cam_counts = sorted({r["cameras"] for r in mrecs}, key=lambda c: (c is None, c))
        for cams in cam_counts:
            crecs = [r for r in mrecs if r["cameras"] == cams]
            cols = _columns(MAIN_METRICS, params)
            scenes = _order((r["scene"] for r in crecs), None)
            rows = []
            variants = _order((r.get("variant") or "" for r in crecs), [""])
            for var, st in ((v, st) for v in variants for st in strat_order):
                srecs = [r for r in crecs if r["strategy"] == st and (r.get("variant") or "") == var]
                if not srecs:
                    continue
                row = {"strategy": st, **({"variant": var} if var else {}), "n": len(srecs),
                       "curriculum": srecs[0].get("curriculum"),
                       "diverged": [{"scene": r["scene"], **r["diverged"]} for r in srecs if r.get("diverged")],
                       "stage0_lost": [{"scene": r["scene"], "frames": r["stage0_lost_frames"]} for r in srecs
                                       if r.get("stage0_lost_frames")],
                       "values": {c["key"]: mean_std(_value(r, c["key"]) for r in srecs) for c in cols}}
                if planned is not None:
                    row["planned"] = planned.get(f"{mat}|{cams}|{st}" + (f"|{var}" if var else ""))
                rows.append(row)
            per_scene = {sc: {r["strategy"]: {c["key"]: _value(r, c["key"]) for c in cols} for r in crecs if r["scene"] == sc}
                         for sc in scenes}
            out["tables"].append({"material": mat, "cameras": cams, "columns": cols, "rows": rows, "scenes": scenes,
                                  "per_scene": per_scene})
            for var in variants:
                claims = _claims(mat, cams, [r for r in crecs if (r.get("variant") or "") == var], strat_order, cols)
                out["claims"] += [{**c, "variant": var} for c in claims] if var else claims
        mrecs = [r for r in mrecs if not r.get("variant")]  # the ablation: the scenes as generated
        cam_counts = sorted({r["cameras"] for r in mrecs}, key=lambda c: (c is None, c))
        if len(cam_counts) > 1:
            cols = _columns(ABLATION_METRICS, params)
            cells = {}
            for st in strat_order:
                for cams in cam_counts:
                    srecs = [r for r in mrecs if r["strategy"] == st and r["cameras"] == cams]
                    if srecs:
                        cells[f"{st}|{cams}"] = {c["key"]: mean_std(_value(r, c["key"]) for r in srecs) for c in cols}
            out["ablation"].append({"material": mat, "cameras": cam_counts, "strategies": strat_order, "columns": cols,
                                    "cells": cells})
    return out


_PAIRS = (("progressive", "sequential"), ("progressive", "joint"), ("progressive", "cyclic"))


def _claims(material: str, cams, records: Sequence[dict], strategies: Sequence[str], cols: Sequence[dict]) -> list[dict]:
    """For each pair (A, B) present: per column, is A's mean better, and in how many scenes A beats B.

    Both the means and the wins are taken over the scenes where both strategies have a value
    (paired), so an unfinished or failed fit of one strategy cannot tilt the comparison.
    """
    out = []
    present = set(strategies)
    by_scene: dict = {}
    for r in records:
        by_scene.setdefault(r["scene"], {})[r["strategy"]] = r
    for a, b in _PAIRS:
        if a not in present or b not in present:
            continue
        for c in cols:
            pairs = []
            for recs in by_scene.values():
                if a in recs and b in recs:
                    va, vb = _value(recs[a], c["key"]), _value(recs[b], c["key"])
                    if all(v is not None and math.isfinite(v) for v in (va, vb)):
                        pairs.append((va, vb))
            if not pairs:
                continue
            pa, pb = (mean_std(p[i] for p in pairs)["mean"] for i in (0, 1))
            lower = c["better"] == "lower"
            wins = sum((va < vb) if lower else (va > vb) for va, vb in pairs)
            better = pa < pb if lower else pa > pb
            out.append({"material": material, "cameras": cams, "a": a, "b": b, "metric": c["key"], "label": c["label"],
                        "mean_a": pa, "mean_b": pb, "a_better": bool(better), "scene_wins_a": wins, "scenes": len(pairs)})
    return out


# ------------------------------------------------------------------------------------ Markdown
def _fmt(cell: dict, decimals: int, with_std: bool = True) -> str:
    if not cell or cell.get("mean") is None:
        return "-"
    m = f"{cell['mean']:.{decimals}f}"
    if with_std and cell.get("n", 0) > 1:
        return f"{m} ± {cell['std']:.{decimals}f}"
    return m


def _best(rows: Sequence[dict], col: dict) -> Optional[float]:
    means = [r["values"][col["key"]]["mean"] for r in rows if r["values"][col["key"]]["mean"] is not None]
    if len(means) < 2:
        return None
    return min(means) if col["better"] == "lower" else max(means)


def _arrow(col: dict) -> str:
    return "↓" if col["better"] == "lower" else "↑"


def tables_markdown(tables: dict, title: str = "Strategy comparison") -> str:
    """Markdown of :func:`build_tables`' result: settings, one table per material and camera count
    (best mean in bold), per-scene tables, the camera-count ablation, the pairwise comparisons and
    the failures."""
    lines = [f"# {title}", ""]
    settings = tables.get("settings") or {}
    if settings:
        lines += ["## What was run", ""]
        for k, v in settings.items():
            lines.append(f"- **{k}**: {v if isinstance(v, str) else json.dumps(v)}")
        lines.append("")
    lines += ["Values are mean ± standard deviation over scenes (population std; `n` scenes per row). CD (x1e3) and "
              "EMD (m) compare the predicted particles with the ground-truth clouds over the future frames; PSNR (dB) "
              "and SSIM are over the future frames of all cameras; MAE is the absolute error of log10 E, mu, kappa, "
              "tau_Y, eta and of nu, the friction angle (degrees) and v0 (m/s, mean of the components). Best mean in "
              "bold.", ""]
    for t in tables.get("tables", []):
        cols, rows = t["columns"], t["rows"]
        lines += [f"## {t['material']}, {t['cameras']} views", ""]
        var = any(r.get("variant") for r in rows)  # a variant column only when variants ran
        head = ["strategy"] + (["variant"] if var else []) + ["n"] + [f"{c['label']} {_arrow(c)}" for c in cols]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * (2 + var) + "---:|" * len(cols)]
        best = {c["key"]: _best(rows, c) for c in cols}
        for r in rows:
            n = f"{r['n']}" + (f"/{r['planned']}" if r.get("planned") else "")
            if r.get("diverged"):
                n += f" ({len(r['diverged'])} diverged)"
            if r.get("stage0_lost"):
                n += f" ({len(r['stage0_lost'])} with lost stage-0 frames)"
            cells = []
            for c in cols:
                cell = r["values"][c["key"]]
                text = _fmt(cell, c["decimals"])
                if best[c["key"]] is not None and cell["mean"] == best[c["key"]]:
                    text = f"**{text}**"
                cells.append(text)
            lines.append("| " + " | ".join([r["strategy"]] + ([r.get("variant") or "(as generated)"] if var else []) + [n] + cells) + " |")
        lines.append("")
        sched = [f"`{r['strategy']}`: `{r['curriculum']}`" for r in rows if r.get("curriculum")]
        if sched:
            lines += ["Schedules: " + "; ".join(sched) + ".", ""]
        lines += [f"Per scene ({len(t['scenes'])}):", ""]
        head = ["metric", "strategy"] + t["scenes"]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * 2 + "---:|" * len(t["scenes"])]
        for c in cols:
            for st in dict.fromkeys(r["strategy"] for r in rows):  # variants are scenes (<scene>@<variant>) here
                vals = []
                for sc in t["scenes"]:
                    v = t["per_scene"].get(sc, {}).get(st, {}).get(c["key"])
                    vals.append("-" if v is None else f"{v:.{c['decimals']}f}")
                lines.append("| " + " | ".join([f"{c['label']} {_arrow(c)}", st] + vals) + " |")
        lines.append("")
    for a in tables.get("ablation", []):
        lines += [f"## {a['material']}: number of cameras", ""]
        head = ["metric", "strategy"] + [str(c) for c in a["cameras"]]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * 2 + "---:|" * len(a["cameras"])]
        for c in a["columns"]:
            for st in a["strategies"]:
                vals = [_fmt((a["cells"].get(f"{st}|{cams}") or {}).get(c["key"]), c["decimals"], with_std=False)
                        for cams in a["cameras"]]
                lines.append("| " + " | ".join([f"{c['label']} {_arrow(c)}", st] + vals) + " |")
        lines.append("")
    if tables.get("claims"):
        lines += ["## Pairwise comparisons", "",
                  "| material | views | comparison | metric | mean A (paired) | mean B (paired) | A better | scenes A wins |",
                  "|---|---|---|---|---:|---:|---|---:|"]
        for c in tables["claims"]:
            dec = 4 if c["metric"] in ("emd",) else 3
            lab = c["material"] + (f" ({c['variant']})" if c.get("variant") else "")
            lines.append(f"| {lab} | {c['cameras']} | {c['a']} (A) vs {c['b']} (B) | {c['label']} | "
                         f"{c['mean_a']:.{dec}f} | {c['mean_b']:.{dec}f} | {'yes' if c['a_better'] else 'no'} | "
                         f"{c['scene_wins_a']}/{c['scenes']} |")
        lines.append("")
    diverged = [(t["material"], t["cameras"], r["strategy"], d) for t in tables.get("tables", []) for r in t["rows"]
                for d in r.get("diverged") or []]
    if diverged:
        lines += ["## Diverged fits", "",
                  "These fits left the valid parameter set (NaN, or a parameter out of its material's range); they stopped "
                  "there and their last valid estimate was evaluated (it is included in the means).", ""]
        for mat, cams, st, d in diverged:
            lines.append(f"- {mat} {d.get('scene')} {cams} views, {st}: iteration {d.get('step')}: {d.get('reason')}")
        lines.append("")
    lost = [(t["material"], t["cameras"], r["strategy"], d) for t in tables.get("tables", []) for r in t["rows"]
            for d in r.get("stage0_lost") or []]
    if lost:
        from toolkit.scene.coverage import format_frames

        lines += ["## Stage 0 lost the object", "",
                  "In these fits stage 0's Gaussians covered under half of a fitting camera's mask in some training frames "
                  "(`stage0/coverage.json`); those frames' surfaces were left out of the geometric loss, and the estimates "
                  "rest on less data than the others (they are included in the means).", ""]
        for mat, cams, st, d in lost:
            lines.append(f"- {mat} {d['scene']} {cams} views, {st}: frames {format_frames(d['frames'])}")
        lines.append("")
    if tables.get("failures"):
        lines += ["## Failed jobs", ""]
        for f in tables["failures"]:
            lines.append(f"- {f.get('material')} {f.get('scene')} {f.get('cameras')} views, {f.get('strategy')}: {f.get('error')}")
        lines.append("")
    return "\n".join(lines)


def write_tables(bench_dir: str | Path, out_dir: Optional[str | Path] = None, strategies: Optional[Sequence[str]] = None,
                 settings: Optional[dict] = None, planned: Optional[dict] = None, title: str = "Strategy comparison",
                 only: Optional[Collection[tuple]] = None) -> tuple[Path, Path, dict]:
    """Collect a benchmark folder's records (``only``: see :func:`collect_records`) and write
    ``tables.md`` and ``tables.json``.

    Returns:
        The two paths and the tables dict.
    """
    records, failures = collect_records(bench_dir, only)
    return write_records_tables(records, Path(out_dir) if out_dir else Path(bench_dir) / "tables", strategies, failures,
                                settings, planned, title)


def write_records_tables(records: Sequence[dict], out_dir: str | Path, strategies: Optional[Sequence[str]] = None,
                         failures: Sequence[dict] = (), settings: Optional[dict] = None, planned: Optional[dict] = None,
                         title: str = "Strategy comparison") -> tuple[Path, Path, dict]:
    """:func:`build_tables` of ``records`` written atomically as ``out_dir/tables.md`` and
    ``out_dir/tables.json`` (the latter with the records, less their per-frame curves).

    Returns:
        The two paths and the tables dict.
    """
    from toolkit.atomic import write_json, write_text

    tables = build_tables(records, strategies, failures, settings, planned)
    tables["records"] = [{k: v for k, v in r.items() if k != "per_frame"} for r in records]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "tables.md", out / "tables.json"
    write_text(md, tables_markdown(tables, title))
    write_json(js, tables)
    return md, js, tables

"""The discovery benchmark's tables: the summary of a run's records and its Markdown.

Used by ``benchmarks/discovery.py`` (``--report-only``, ``--update-docs``) and
``benchmarks/discovery_runs.py`` (several runs compared). A record is one line of a run's
``results*.jsonl`` (see ``run_scene`` there). Rates are fractions (0..1); gap shrinks are
relative (1 - after / before) of the future Chamfer distance.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from typing import Optional

import numpy as np

__all__ = ["CONTROLS", "summarize", "truth_shrink", "markdown", "decide_record"]

#: hidden effects that are controls (not physics to name): excluded from the gap-shrink rates
CONTROLS = ("density", "camera_pose")


def summarize(records: list[dict], thresholds) -> dict:
    from toolkit.discovery.calibration import calibrate, null_statistics

    nulls = [r for r in records if r["effect"] == "none"]
    hidden = [r for r in records if r["effect"] != "none"]
    out: dict = {"geometry": sorted({r.get("geometry", "oracle") for r in records}), "n_scenes": len(records), "n_null": len(nulls), "n_hidden": len(hidden), "thresholds": thresholds.to_dict()}
    # false positives: with the thresholds used, and 2-fold cross-calibrated
    out["false_positive_rate"] = float(np.mean([r["decision"] is not None for r in nulls])) if nulls else None
    if len(nulls) >= 2:
        halves = [nulls[0::2], nulls[1::2]]
        fp = []
        for a, b in ((0, 1), (1, 0)):
            thr = calibrate([null_statistics({"validation": r["validation"]}) for r in halves[a]])
            fp += [decide_record(r, thr)[0] is not None for r in halves[b]]
        out["false_positive_rate_cross"] = float(np.mean(fp))
    if hidden:
        out["top1"] = float(np.mean([r["correct"] for r in hidden]))
        out["top3"] = float(np.mean([(r["expected"] in r["top3"]) if r["expected"] else r["correct"] for r in hidden]))
        phys = [r for r in hidden if r["expected"] is not None and r["effect"] not in CONTROLS]
        shr = [r["cd_shrink"] for r in phys if r["correct"] and r["cd_shrink"] is not None]
        out["median_gap_shrink_identified"] = float(np.median(shr)) if shr else None
        shr_all = [r["cd_shrink"] if r["cd_shrink"] is not None else 0.0 for r in phys]
        out["median_gap_shrink_all"] = float(np.median(shr_all)) if shr_all else None
        # observable: refitting the true effect halves the future gap (otherwise the data hardly
        # shows the effect, and "no missing effect" is all they support)
        obs = [r for r in phys if (truth_shrink(r) or 0.0) >= 0.5]
        out["observable"] = {"n": len(obs), "of": len(phys),
                             "top1": float(np.mean([r["correct"] for r in obs])) if obs else None,
                             "top3": float(np.mean([r["expected"] in r["top3"] for r in obs])) if obs else None,
                             "named_or_tied": float(np.mean([_named_or_tied(r) for r in obs])) if obs else None,
                             "median_gap_shrink": _median([r["cd_shrink"] or 0.0 for r in obs])}
        per = defaultdict(list)
        for r in hidden:
            per[r["effect"]].append(r)
        out["per_effect"] = {}
        for e, rs in sorted(per.items()):
            errs = defaultdict(list)
            for r in rs:
                for k, v in (r.get("strength_errors") or {}).items():
                    errs[k].append(v)
            out["per_effect"][e] = {
                "n": len(rs), "top1": float(np.mean([r["correct"] for r in rs])),
                "top3": float(np.mean([(r["expected"] in r["top3"]) if r["expected"] else r["correct"] for r in rs])),
                "median_cd_shrink": _median([r["cd_shrink"] for r in rs if r["correct"]]),
                "strength_error": {k: float(np.median(v)) for k, v in errs.items()},
                "truth_strengths": rs[0]["truth_strengths"] if rs else {},
            }
    labels = sorted({r["effect"] for r in records})
    cols = sorted({r["decision"] or "none" for r in records})
    conf = {e: Counter((r["decision"] or "none") for r in records if r["effect"] == e) for e in labels}
    out["confusion"] = {e: dict(c) for e, c in conf.items()}
    out["confusion_columns"] = cols
    return out


def _named_or_tied(rec: dict) -> bool:
    """The true effect is the decision or one of the candidates the report names as tied with it
    (the data explain it as well; the report says what would separate them)."""
    return bool(rec["correct"]) or (rec["expected"] is not None and rec["expected"] in (rec.get("indistinguishable") or []))


def truth_shrink(rec: dict) -> Optional[float]:
    """Future-Chamfer gap shrink of refitting the true hidden effect (the decision's own refit when
    it named the true effect); ``None`` when unknown."""
    from toolkit.discovery.gap import gap_shrink

    truth = rec.get("cd_truth_effect")
    if truth is None and rec.get("correct"):
        truth = rec.get("cd_after")
    return gap_shrink(rec.get("cd_before"), truth)


def _median(v):
    v = [x for x in v if x is not None]
    return float(np.median(v)) if v else None


def markdown(summary: dict, title: str) -> str:
    def pct(x):
        return "-" if x is None else f"{100 * x:.0f} %"

    s = summary
    obs = s.get("observable") or {}
    lines = [f"**{title}**: {s['n_hidden']} scenes with a hidden effect, {s['n_null']} null scenes.", "",
             "| metric | value |", "|---|---|",
             f"| top-1 identification accuracy | {pct(s.get('top1'))} |",
             f"| top-3 identification accuracy | {pct(s.get('top3'))} |",
             f"| median future-Chamfer gap shrink (identified) | {pct(s.get('median_gap_shrink_identified'))} |",
             f"| median future-Chamfer gap shrink (all hidden physics effects, 0 when missed) | {pct(s.get('median_gap_shrink_all'))} |",
             f"| top-1 / top-3 on hidden physics effects the data show (refitting the true effect halves the future gap: "
             f"{obs.get('n', 0)} of {obs.get('of', 0)} scenes) | {pct(obs.get('top1'))} / {pct(obs.get('top3'))} |",
             f"| named first or among the tied candidates the report names, on those | {pct(obs.get('named_or_tied'))} |",
             f"| median future-Chamfer gap shrink on those (the decision's refit; 0 for \"no missing effect\") | "
             f"{pct(obs.get('median_gap_shrink'))} |",
             f"| false-positive rate on null scenes (thresholds used) | {pct(s.get('false_positive_rate'))} |",
             f"| false-positive rate on null scenes (2-fold cross-calibrated) | {pct(s.get('false_positive_rate_cross'))} |",
             "", "| hidden effect | scenes | top-1 | top-3 | median gap shrink | median strength error (truth) |",
             "|---|---|---|---|---|---|"]
    for e, v in (s.get("per_effect") or {}).items():
        err = "; ".join(f"{k.split('.', 1)[1]} {val:.3g} ({_truth(v, k)})" for k, val in v["strength_error"].items()) or "-"
        lines.append(f"| {e} | {v['n']} | {pct(v['top1'])} | {pct(v['top3'])} | {pct(v['median_cd_shrink'])} | {err} |")
    cols = s["confusion_columns"]
    lines += ["", "Confusion matrix (rows: hidden effect; columns: decision):", "",
              "| hidden \\ decided | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for e, c in s["confusion"].items():
        lines.append(f"| {e} | " + " | ".join(str(c.get(k, 0)) or "0" for k in cols) + " |")
    thr = s["thresholds"]
    lines += ["", f"Thresholds: validation {thr['validation']:.3f}, fit {thr['fit']:.3f}, camera {thr['camera']:.3f} ({thr['source']})."]
    return "\n".join(lines) + "\n"


def _truth(v: dict, k: str) -> str:
    t = v.get("truth_strengths", {}).get(k)
    return "-" if t is None else f"{t:.3g}"


def decide_record(rec: dict, thr):
    """The decision of a stored record under thresholds ``thr``, as :func:`toolkit.discovery.discover`
    made it: with the noise, the single camera, the observed motion's preference among tied
    candidates and the silhouette check's suspect, when recorded."""
    from toolkit.discovery.kinematics import ObservedMotion, preferred_candidates
    from toolkit.discovery.workflow import decide

    motion = ObservedMotion.from_dict(rec["motion"]) if rec.get("motion") else None
    suspect = (rec.get("silhouettes") or {}).get("suspect")
    return decide(rec["validation"], rec["dofs"], thr, noise=rec.get("noise"), single_camera=rec.get("single_camera"),
                  prefer=preferred_candidates(motion, list(rec["validation"])), silhouette_suspect=suspect)

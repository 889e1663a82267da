"""The discovery report: Markdown and HTML with matplotlib figures.

:func:`write_report` writes into a folder:

* ``residual_heatmap.png``: 3D residual over time x region (contact band, bulk, top), the
  phases marked, and the per-camera 2D image residual over time (fitted cameras marked);
* ``residual_split.png``: rigid (centre-of-mass, rotation) and non-rigid residual per frame with
  the noise band and the first frame that leaves it;
* ``gap.png``: per-frame Chamfer distance, PSNR and held-out-camera loss before and after adding
  the discovered effect (and with the true effect, when known), training and future frames;
* ``report.md`` and ``report.html``: the verdict, the localization summary, the ranking table
  (score, predicted and actual loss drop, held-out improvement, strength with its interval, the
  most confusable partner, decision), the gap before/after and the base parameters before and
  after.
"""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from toolkit.plotting import pyplot, save_figure

__all__ = ["write_report", "ranking_rows", "RANKING_COLUMNS"]

RANKING_COLUMNS = ("rank", "candidate", "score (pred. drop)", "actual drop", "gradient (proj.)", "held-out improvement",
                   "strength [interval]", "confusable with", "decision")


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        if math.isnan(x) or math.isinf(x):
            return "-"
        return f"{x:.{digits}g}"
    return str(x)


def _pct(x: Optional[float]) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{100 * x:+.1f} %"


def ranking_rows(result) -> list[list[str]]:
    """The ranking table's rows (strings), one per candidate, best first."""
    rows = []
    for s in result.ranking.scores:
        v = result.validation.get(s.name)
        rf = result.refits.get(s.name)
        final = result.final if (result.final is not None and result.final.name == s.name) else None
        src = final or rf
        if src is not None and src.strengths:
            parts = []
            for k, val in src.strengths.items():
                lo, hi = src.intervals.get(k, (float("nan"), float("nan")))
                short = k.split(".", 1)[1]
                parts.append(f"{short} {_fmt(val)} [{_fmt(lo)}, {_fmt(hi)}]")
            strength = "; ".join(parts[:3]) + (" ..." if len(parts) > 3 else "")
        else:
            strength = ", ".join(f"{k.split('.', 1)[1]} {_fmt(val)}" for k, val in list(s.predicted_strength.items())[:3]) + " (pred.)"
        if s.search:
            strength += " " + ", ".join(f"{k} {_fmt_vec(val) if isinstance(val, list) else _fmt(val)}"
                                        for k, val in s.search.items() if k != "index")
        grad = max(s.projected_gradient.values(), key=abs) if s.projected_gradient else None
        if s.name == result.decision:
            decision = "**discovered**" if result.decision_kind == "physics" else "**observation error**"
        elif s.name in result.indistinguishable:
            decision = "indistinguishable"
        elif v is None:
            decision = "not confirmed"
        elif s.control:
            decision = "control"
        elif v["passed"]:
            decision = "passed"
        else:
            decision = "rejected"
        rows.append([str(s.rank), s.name + (" (control)" if s.control else ""), _pct(s.score),
                     _pct(v.get("actual_drop")) if v else "-", _fmt(grad), _pct(v["validation"]) if v else "-", strength,
                     f"{s.partner} ({s.overlap:.2f})" if s.partner else "-", decision])
    return rows


def _heatmap(result, path: Path) -> Path:
    plt = pyplot()
    loc = result.localization
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4), gridspec_kw={"width_ratios": [1, 1.3]})
    ax = axes[0]
    heat = np.asarray(loc.heat, dtype=float).T * 1e3  # (R, F) mm
    im = ax.imshow(np.where(np.isfinite(heat), heat, np.nan), aspect="auto", cmap="magma", origin="lower")
    ax.set_yticks(range(3), ["contact", "bulk", "top"])
    ax.set_xticks(range(len(loc.frames)), [f"{f}\n{p[:3]}" for f, p in zip(loc.frames, loc.phases)], fontsize=7)
    ax.set_title("3D residual (mm RMS) by region", fontsize=9)
    fig.colorbar(im, ax=ax, fraction=0.046)
    ax = axes[1]
    if loc.image is not None:
        im = ax.imshow(loc.image, aspect="auto", cmap="viridis")
        ax.set_yticks(range(len(loc.cameras)), [f"{c}{'*' if c in loc.train_cameras else ''}" for c in loc.cameras], fontsize=7)
        ax.set_xticks(range(len(loc.frames)), [str(f) for f in loc.frames], fontsize=7)
        ax.set_title("image loss per camera (* fitted)", fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.046)
    for a in axes:
        a.set_xlabel("frame", fontsize=8)
    return save_figure(fig, path, dpi=110)


def _split(result, path: Path) -> Path:
    plt = pyplot()
    loc = result.localization
    fig, ax = plt.subplots(figsize=(6, 3))
    f = loc.frames
    ax.plot(f, np.asarray(loc.total) * 1e3, "k-o", ms=3, label="total")
    ax.plot(f, np.asarray(loc.rigid_translation) * 1e3, "-s", ms=3, label="rigid translation")
    ax.plot(f, np.asarray(loc.nonrigid) * 1e3, "-^", ms=3, label="non-rigid")
    ax2 = ax.twinx()
    ax2.plot(f, loc.rotation_deg, ":", color="C3", label="rotation (deg)")
    ax2.set_ylabel("rotation (deg)", fontsize=8)
    ax.axhline(loc.noise_band * 1e3, color="0.5", ls="--", lw=0.8, label="noise band")
    if loc.first_departure is not None:
        ax.axvline(loc.first_departure, color="C1", lw=0.8, label="leaves the band")
    if loc.contact_frame is not None:
        ax.axvspan(loc.contact_frame - 0.5, loc.contact_frame + 1.5, color="C0", alpha=0.08, lw=0, label="impact")
    ax.set_xlabel("frame", fontsize=8)
    ax.set_ylabel("residual (mm)", fontsize=8)
    ax.legend(fontsize=7, loc="upper left")
    return save_figure(fig, path, dpi=110)


def _gap_plot(result, path: Path) -> Path:
    plt = pyplot()
    series = [("cd_per_frame", "Chamfer (x1e3)"), ("psnr_per_frame", "PSNR (dB), all cameras"),
              ("held_out_loss_per_frame", "held-out camera loss")]
    series = [s for s in series if result.metrics["before"].get(s[0]) is not None]
    fig, axes = plt.subplots(1, len(series), figsize=(3.6 * len(series), 2.9), squeeze=False)
    n_train = result.lib.input.n_train if result.lib is not None else None
    labels = {"before": "before (base)", "after": f"after (+{result.decision})", "truth": "with the true effect"}
    for ax, (key, title) in zip(axes.flat, series):
        for which, style in (("before", "k-o"), ("after", "C2-s"), ("truth", "C3--^")):
            m = result.metrics.get(which)
            if m is None or m.get(key) is None:
                continue
            vals = [np.nan if v is None else v for v in m[key]]
            ax.plot(range(len(vals)), vals, style, ms=3, label=labels[which])
        if n_train is not None:
            ax.axvspan(n_train - 0.5, len(result.metrics["before"][key]) - 0.5, color="C1", alpha=0.1, lw=0)
        for f in result.holdout_frames:
            ax.axvspan(f - 0.5, f + 0.5, color="C0", alpha=0.06, lw=0)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("frame (orange: future)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes.flat[0].legend(fontsize=7)
    return save_figure(fig, path, dpi=110)


def _blocks(result, figures: dict[str, str]) -> list[tuple[str, Any]]:
    b: list[tuple[str, Any]] = [("h1", "Discovery report"), ("p", f"**Verdict.** {result.verdict}")]
    thr = result.thresholds
    b.append(("p", f"Decision: **{result.decision or 'no missing effect'}** ({result.decision_kind}). Thresholds: validation "
                   f"{_pct(thr.validation)}, fit {_pct(thr.fit)}, camera {_pct(thr.camera)}, max worsening "
                   f"{_pct(thr.max_worsening)} ({thr.source})."))
    if result.truth:
        tc = result.truth.get("candidate")
        b.append(("p", f"Ground truth: hidden effect **{tc or 'none'}** {result.truth.get('strengths', {})}; expected answer "
                       f"**{result.truth.get('expected') or 'no missing effect'}**; identified: {result.identified}."))
    b.append(("h2", "1. Where the model and the measurements disagree"))
    b.append(("p", result.localization.summary[0].upper() + result.localization.summary[1:] + "."))
    if "heatmap" in figures:
        b.append(("img", figures["heatmap"]))
    if "split" in figures:
        b.append(("img", figures["split"]))
    rp = result.localization.region_phase_table()
    b.append(("table", (["phase"] + ["contact (mm)", "bulk (mm)", "top (mm)"],
                        [[ph] + [_fmt(v * 1e3 if np.isfinite(v) else float("nan")) for v in regs.values()] for ph, regs in rp.items()])))
    b.append(("h2", "2. Candidates"))
    b.append(("p", "Score: predicted relative drop of the Gauss-Newton objective when the candidate is added and refitted with the "
                   "base parameters (projected score test at zero strength). Actual drop: the same after the confirmation refit. "
                   "Held-out improvement: mean relative improvement, over the base-only refit, of the held-out cameras, the "
                   f"held-out training frames {result.holdout_frames} and their stage-0 surfaces. Intervals: 1 % profile intervals."))
    b.append(("table", (list(RANKING_COLUMNS), ranking_rows(result))))
    if result.indistinguishable:
        b.append(("p", f"Cannot be told apart from the decision on these data: {', '.join(result.indistinguishable)}."))
    for d in getattr(result, "separation", []):
        b.append(("p", f"To separate {d['candidates'][0]} from {d['candidates'][1]}: {d['sentence']}"))
    if getattr(result, "joint", None):
        b.append(("p", "Confirmed because a base parameter the clip does not determine absorbed the score test (refitted "
                       "jointly): " + ", ".join(f"{c} with {u}" for c, u in result.joint.items()) + "."))
    if getattr(result, "motion", None):
        from toolkit.discovery.kinematics import motion_sentence

        b.append(("p", motion_sentence(result.motion)))
    if getattr(result, "floors", None):
        b.append(("p", "Stage-0 geometric uncertainty carried as a floor under the held-out losses (the base model's loss at "
                       "frame 0): " + ", ".join(f"{k} {v:.3g}" for k, v in result.floors.items()) + "."))
    b.append(("h2", "3. The gap before and after"))
    g = result.gap
    rows = []
    for key, label in (("cd_future", "future Chamfer (x1e3)"), ("emd_future", "future EMD (m)"), ("psnr_future", "future PSNR (dB)"),
                       ("psnr_future_held_out", "future PSNR, held-out cameras"), ("held_out_loss_train", "held-out camera loss, training frames"),
                       ("held_out_loss_future", "held-out camera loss, future frames")):
        rows.append([label, _fmt(g.get(f"{key}_before"), 4), _fmt(g.get(f"{key}_after"), 4), _fmt(g.get(f"{key}_truth_effect"), 4)])
    b.append(("table", (["metric", "before", "after", "true effect"], rows)))
    b.append(("p", f"Future Chamfer gap removed: {_pct(g.get('cd_shrink'))}; EMD: {_pct(g.get('emd_shrink'))}."))
    if "gap" in figures:
        b.append(("img", figures["gap"]))
    b.append(("h2", "4. Base parameters"))
    before, after = result.params.get("before") or {}, result.params.get("after") or {}
    truth = result.params.get("truth") or {}
    names = list((before.get("params") or {}).keys())
    rows = [[n, _fmt(before["params"].get(n)), _fmt((after.get("params") or {}).get(n)), _fmt((truth.get("params") or {}).get(n))]
            for n in names]
    rows.append(["v0 (m/s)", _fmt_vec(before.get("v0")), _fmt_vec(after.get("v0")), _fmt_vec(truth.get("v0"))])
    rows.append(["shift (m)", _fmt_vec(before.get("shift")), _fmt_vec(after.get("shift")), "-"])
    b.append(("table", (["parameter", "before", "after", "truth"], rows)))
    b.append(("p", "Timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in result.seconds.items())))
    return b


def _fmt_vec(v: Optional[Sequence[float]]) -> str:
    return "-" if v is None else "(" + ", ".join(f"{x:.3g}" for x in v) + ")"


def _md(blocks) -> str:
    out = []
    for kind, x in blocks:
        if kind == "h1":
            out.append(f"# {x}\n")
        elif kind == "h2":
            out.append(f"## {x}\n")
        elif kind == "p":
            out.append(f"{x}\n")
        elif kind == "img":
            out.append(f"![{x}]({x})\n")
        elif kind == "table":
            head, rows = x
            out.append("| " + " | ".join(head) + " |")
            out.append("|" + "|".join("---" for _ in head) + "|")
            out += ["| " + " | ".join(c.replace("|", "/") for c in r) + " |" for r in rows]
            out.append("")
    return "\n".join(out)


def _inline(text: str) -> str:
    t = html.escape(text)
    parts = t.split("**")
    return "".join(f"<b>{p}</b>" if i % 2 else p for i, p in enumerate(parts))


def _html(blocks) -> str:
    out = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>Discovery report</title>",
           "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse;font-size:13px}"
           "td,th{border:1px solid #ccc;padding:3px 6px}th{background:#eee}img{max-width:100%}</style></head><body>"]
    for kind, x in blocks:
        if kind in ("h1", "h2"):
            out.append(f"<{kind}>{html.escape(x)}</{kind}>")
        elif kind == "p":
            out.append(f"<p>{_inline(x)}</p>")
        elif kind == "img":
            out.append(f"<img src='{html.escape(x)}' alt='{html.escape(x)}'>")
        elif kind == "table":
            head, rows = x
            out.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>")
            out += ["<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>" for r in rows]
            out.append("</table>")
    out.append("</body></html>")
    return "\n".join(out)


def write_report(result, out_dir: str | Path) -> list[Path]:
    """Figures, ``report.md`` and ``report.html`` of a
    :class:`~toolkit.discovery.workflow.DiscoveryResult` into ``out_dir``; returns the files."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [_heatmap(result, out / "residual_heatmap.png"), _split(result, out / "residual_split.png"),
             _gap_plot(result, out / "gap.png")]
    figures = {"heatmap": files[0].name, "split": files[1].name, "gap": files[2].name}
    blocks = _blocks(result, figures)
    from toolkit.atomic import write_text

    md = write_text(out / "report.md", _md(blocks))
    page = write_text(out / "report.html", _html(blocks))
    return files + [md, page]

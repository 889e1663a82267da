"""Figures and videos of a run: optimization trajectories, per-frame errors, prediction vs truth.

* :func:`plot_trajectories`: loss terms, material parameters, v0 and parameter errors against the
  iteration, with the curriculum's stages shaded (as the paper's appendix figure);
* :func:`plot_per_frame`: Chamfer/EMD/PSNR per frame, training and future frames marked;
* :func:`comparison_video`: ground truth and prediction side by side for a few cameras, every
  frame (MP4, with a PNG strip of the future frames);
* :func:`plot_evaluation_trajectories`: future-state EMD and PSNR and the parameter errors
  against the iteration, stages shaded (the paper's appendix figure), from the ``eval/...``
  records of :class:`~toolkit.physics.periodic_eval.PeriodicEvaluation` (written by
  :func:`write_report` when the history has them).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from toolkit.atomic import write_with
from toolkit.plotting import pyplot, save_figure

__all__ = ["plot_trajectories", "plot_per_frame", "comparison_video", "write_report", "plot_evaluation_trajectories",
           "compressed_axis", "write_uncertainty_table", "plot_grid_check"]

_LOG_PARAMS = {"E", "mu", "kappa", "yield_stress", "plastic_viscosity"}


def _shade_stages(ax, curriculum: Sequence[dict]) -> None:
    for i, s in enumerate(curriculum):
        ax.axvspan(s["start"], s["end"], color="0.85" if i % 2 == 0 else "0.95", zorder=0, lw=0)
        ax.text((s["start"] + s["end"]) / 2, 1.0, s["name"], transform=ax.get_xaxis_transform(), ha="center", va="bottom",
                fontsize=7, color="0.3")


def plot_trajectories(history: Sequence[dict], curriculum: Sequence[dict], path: str | Path,
                      truth: Optional[dict] = None) -> Path:
    """One figure: losses, each material parameter (log10 where optimized in log space), v0, errors."""
    plt = pyplot()
    truth = truth or {}
    steps = np.array([h["step"] for h in history])
    params = sorted({k[6:] for h in history for k in h if k.startswith("param/")})
    panels = ["loss"] + [f"param/{p}" for p in params] + ["v0"] + (["error"] if any(k.startswith("error/") for k in history[-1]) else [])
    ncols = 3
    nrows = math.ceil(len(panels) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 2.9 * nrows), squeeze=False)
    for ax, panel in zip(axes.flat, panels):
        _shade_stages(ax, curriculum)
        if panel == "loss":
            for key in sorted({k for h in history for k in h if k.startswith("loss/")}):
                ax.plot(steps, [h.get(key, np.nan) for h in history], label=key[5:])
            ax.set_yscale("log")
            ax.set_title("loss", fontsize=9, pad=12)
        elif panel.startswith("param/"):
            name = panel[6:]
            vals = np.array([h.get(panel, np.nan) for h in history], dtype=float)
            log = name in _LOG_PARAMS
            ax.plot(steps, np.log10(vals) if log else vals, color="C0", label="estimate")
            gt = truth.get("params", {}).get(name)
            if gt is not None:
                ax.axhline(math.log10(gt) if log else gt, color="C3", ls="--", label="truth")
            ax.set_title(f"log10 {name}" if log else name, fontsize=9, pad=12)
        elif panel == "v0":
            for i, c in enumerate("xyz"):
                ax.plot(steps, [h.get(f"v0/{c}", np.nan) for h in history], color=f"C{i}", label=f"v0 {c}")
                if truth.get("v0") is not None:
                    ax.axhline(truth["v0"][i], color=f"C{i}", ls="--", lw=0.8)
            ax.set_title("initial velocity (m/s)", fontsize=9, pad=12)
        else:
            for key in sorted({k for h in history for k in h if k.startswith("error/")}):
                ax.plot(steps, [h.get(key, np.nan) for h in history], label=key[6:])
            ax.set_title("parameter error (MAE)", fontsize=9, pad=12)
        ax.set_xlabel("iteration", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7, loc="best")
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    return save_figure(fig, path)


def plot_per_frame(evaluation: dict, path: str | Path) -> Optional[Path]:
    """Per-frame Chamfer, EMD, PSNR and SSIM with the training/future split marked."""
    series = []
    if evaluation.get("geometry"):
        series += [("Chamfer distance (x1e3)", evaluation["geometry"]["cd_per_frame"]),
                   ("EMD (m)", evaluation["geometry"]["emd_per_frame"])]
    if evaluation.get("images"):
        im = evaluation["images"]["all_cameras"]
        series += [("PSNR (dB), all cameras", im["psnr_per_frame"]), ("SSIM, all cameras", im["ssim_per_frame"])]
    if not series:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(1, len(series), figsize=(3.6 * len(series), 2.8), squeeze=False)
    n_train = evaluation["n_train"]
    for ax, (title, vals) in zip(axes.flat, series):
        ax.plot(range(len(vals)), [np.nan if v is None else v for v in vals], marker="o", ms=3)
        ax.axvspan(n_train - 0.5, len(vals) - 0.5, color="C1", alpha=0.12, lw=0, label="future")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("frame", fontsize=8)
        ax.tick_params(labelsize=7)
    axes.flat[0].legend(fontsize=7)
    return save_figure(fig, path)


def plot_grid_check(rec: dict, path: str | Path) -> Optional[Path]:
    """The grid check (:mod:`toolkit.physics.grid_check`): per training frame, how far the
    estimate moves on a grid of half the spacing (mm), against the fit's mean residual."""
    shifts = rec.get("shift_per_frame_m")
    if not shifts:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4.6, 2.9))
    ax.plot(range(len(shifts)), [1e3 * v for v in shifts], marker="o", ms=3,
            label=f"shift, dx {rec['dx']:g} -> {rec['fine_dx']:g} m")
    if rec.get("residual_m") is not None:
        ax.axhline(1e3 * rec["residual_m"], color="C3", ls="--", lw=1, label="fit's mean residual")
    if rec.get("first_frame_residual_m") is not None:
        ax.axhline(1e3 * rec["first_frame_residual_m"], color="C2", ls=":", lw=1, label="residual at the first frame")
    verdict = {True: "the grid moves it less than the misfit", False: "grid-dependent: fit at the finer dx"}.get(rec.get("converged"), "")
    ax.set_title(f"grid check{': ' + verdict if verdict else ''}", fontsize=9)
    ax.set_xlabel("training frame", fontsize=8)
    ax.set_ylabel("mm", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def caption_below(img: np.ndarray, text: str, band: int = 14) -> np.ndarray:
    """``img`` (H, W, 3) uint8 with a white band of ``band`` px *below* it holding ``text`` in black:
    the caption never covers the picture, which keeps its own resolution."""
    from PIL import Image, ImageDraw

    h, w = img.shape[:2]
    canvas = Image.new("RGB", (w, h + band), (255, 255, 255))
    canvas.paste(Image.fromarray(np.ascontiguousarray(img)), (0, 0))
    ImageDraw.Draw(canvas).text((3, h + 1), text, fill=(0, 0, 0))
    return np.asarray(canvas)


_label = caption_below  # the name older callers use


def comparison_video(gt: np.ndarray, pred: np.ndarray, n_train: int, path: str | Path, fps: float = 8.0,
                     camera_names: Sequence[str] | None = None) -> list[Path]:
    """Side-by-side ground truth (top) and prediction (bottom) for C cameras and T frames.

    Args:
        gt, pred: (C, T, H, W, 3) uint8.
        n_train: first future frame (labelled "future" in the video).
        path: the MP4 path; a PNG strip of the future frames is written next to it.

    Returns:
        The files written.
    """
    import imageio.v3 as iio

    C, T = gt.shape[:2]
    frames = []
    for t in range(T):
        top = np.concatenate(list(gt[:, t]), axis=1)
        bottom = np.concatenate(list(pred[:, t]), axis=1)
        tile = np.concatenate([top, bottom], axis=0)
        tag = "future" if t >= n_train else "fit"
        frames.append(_label(np.ascontiguousarray(tile), f"t={t} {tag} | top: truth, bottom: prediction"))
    path = Path(path)
    written = []
    try:
        write_with(path, lambda p: iio.imwrite(p, np.stack(frames), fps=fps, codec="libx264", macro_block_size=1))
        written.append(path)
    except Exception:  # no ffmpeg available: a GIF instead
        gif = path.with_suffix(".gif")
        write_with(gif, lambda p: iio.imwrite(p, np.stack(frames), duration=1000 / fps, loop=0))
        written.append(gif)
    future = frames[n_train:] or frames[-1:]
    strip = path.with_name(path.stem + "_future.png")
    strip_image = np.concatenate(future if len(future) < 5 else future[:: max(1, len(future) // 4)], axis=1)
    write_with(strip, lambda p: iio.imwrite(p, strip_image))
    written.append(strip)
    return written


def write_report(run_dir: str | Path, history: Sequence[dict], curriculum: Sequence[dict], evaluation: dict,
                 truth: Optional[dict], gt_images: Optional[np.ndarray], pred_images: Optional[np.ndarray],
                 cameras: Sequence[int], uncertainty: Optional[dict] = None,
                 grid_check: Optional[dict] = None) -> list[Path]:
    """All figures and the video into ``run_dir/report``; returns the files.

    ``uncertainty`` (an :meth:`toolkit.physics.uncertainty.Uncertainty.to_dict` result) adds
    ``uncertainty.md``: each parameter's estimate, interval and identifiability label.
    ``grid_check`` (a :func:`toolkit.physics.grid_check.grid_convergence` record) adds
    ``grid_check.png``.
    """
    report = Path(run_dir) / "report"
    report.mkdir(parents=True, exist_ok=True)
    files = [plot_trajectories(history, curriculum, report / "trajectories.png", truth)]
    if uncertainty:
        files.append(write_uncertainty_table(uncertainty, report / "uncertainty.md", truth))
    p = plot_per_frame(evaluation, report / "per_frame.png")
    if p:
        files.append(p)
    if grid_check:
        p = plot_grid_check(grid_check, report / "grid_check.png")
        if p:
            files.append(p)
    if gt_images is not None and pred_images is not None:
        files += comparison_video(gt_images[list(cameras)], pred_images[list(cameras)], evaluation["n_train"],
                                  report / "prediction_vs_truth.mp4")
    if any(k.startswith("eval/") for h in history for k in h):
        files.append(plot_evaluation_trajectories(history, curriculum, report / "evaluation_trajectories.png"))
    return files


def write_uncertainty_table(uncertainty: dict, path: str | Path, truth: Optional[dict] = None) -> Path:
    """A markdown table: parameter, estimate, interval at the result's level, the estimate on a grid of
    half the spacing (the grid term, :mod:`toolkit.physics.grid_term`), label, note (and the truth
    when known)."""
    truth = truth or {}
    known = dict(truth.get("params") or {})
    if truth.get("v0") is not None:
        known.update({f"v0_{c}": truth["v0"][i] for i, c in enumerate("xyz")})
    level = round(100 * float(uncertainty.get("level", 0.9)))
    lines = [f"| parameter | estimate | {level} % interval | on a grid of half the spacing | label | truth | note |",
             "|---|---|---|---|---|---|---|"]
    for name, p in uncertainty["parameters"].items():
        tr = known.get(name)
        fine = p.get("grid_value")
        lines.append(f"| {name} | {p['value']:.4g} | [{p['low']:.3g}, {p['high']:.3g}] | {'-' if fine is None else f'{fine:.4g}'} | "
                     f"{p['label']} | "
                     f"{'-' if tr is None else f'{tr:.4g}'} | {p.get('note', '')} |")
    path = Path(path)
    write_with(path, lambda t: Path(t).write_text("\n".join(lines) + "\n"))
    return path


def compressed_axis(curriculum: Sequence[dict], cap: Optional[int] = None):
    """A piecewise-linear map from iterations to plot coordinates that shrinks long stages.

    Each stage keeps its width when it has at most ``cap`` iterations and is squeezed to ``cap``
    otherwise (the paper rescales its 40k-iteration stage 0 the same way), so a 40k-iteration
    appearance stage does not flatten the stages before it.

    Args:
        curriculum: stages with ``start`` and ``end`` (:meth:`strategies.Strategy.describe`).
        cap: widest stage in plot units (default: the longest stage of at most 1000 iterations,
            at least 100).

    Returns:
        ``(to_plot, compressed)``: a function mapping an array of iterations to plot
        coordinates, and whether any stage was squeezed.
    """
    spans = [(int(s["start"]), int(s["end"])) for s in curriculum]
    if cap is None:
        short = [e - b for b, e in spans if e - b <= 1000]
        cap = max(100, max(short) if short else 100)
    widths = [min(e - b, cap) for b, e in spans]
    compressed = any(e - b > cap for b, e in spans)
    offsets = np.concatenate([[0.0], np.cumsum(widths)])

    def to_plot(steps):
        x = np.asarray(steps, dtype=float)
        out = np.array(x, dtype=float)
        for i, (b, e) in enumerate(spans):
            inside = (x >= b) & (x <= e) if i == len(spans) - 1 else (x >= b) & (x < e)
            scale = widths[i] / max(1, e - b)
            out[inside] = offsets[i] + (x[inside] - b) * scale
        if spans:
            out[x > spans[-1][1]] = offsets[-1] + (x[x > spans[-1][1]] - spans[-1][1])
        return out

    return to_plot, compressed


def _eval_panels(history: Sequence[dict]) -> list[tuple[str, list[str]]]:
    keys = {k for h in history for k in h}
    panels = []
    if keys & {"eval/emd_future", "eval/emd_x0"}:
        panels.append(("EMD (m), future frames", [k for k in ("eval/emd_future", "eval/emd_x0") if k in keys]))
    if keys & {"eval/cd_future", "eval/cd_x0"}:
        panels.append(("Chamfer distance (x1e3), future frames", [k for k in ("eval/cd_future", "eval/cd_x0") if k in keys]))
    if "eval/psnr_future" in keys:
        panels.append(("PSNR (dB), future frames, held-out camera", ["eval/psnr_future"]))
    errors = sorted(k for k in keys if k.startswith("error/") and k != "error/v0")
    if errors:
        panels.append(("material parameter error (MAE)", errors))
    if "error/v0" in keys:
        panels.append(("initial velocity error (MAE, m/s)", ["error/v0"]))
    return panels


def plot_evaluation_trajectories(history: Sequence[dict], curriculum: Sequence[dict], path: str | Path,
                                 cap: Optional[int] = None) -> Path:
    """Future EMD/CD and PSNR and the parameter errors against the iteration, stages shaded.

    The EMD/CD/PSNR points are the iterations where
    :class:`~toolkit.physics.periodic_eval.PeriodicEvaluation` ran; parameter errors are drawn at
    every iteration. Stages longer than ``cap`` iterations are drawn squeezed
    (:func:`compressed_axis`), and the stage boundaries are labelled with their iteration.
    """
    plt = pyplot()
    to_plot, compressed = compressed_axis(curriculum, cap)
    panels = _eval_panels(history)
    ncols = min(3, max(1, len(panels)))
    nrows = max(1, math.ceil(len(panels) / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.0 * nrows), squeeze=False)
    shaded = [{**s, "start": float(to_plot([s["start"]])[0]), "end": float(to_plot([s["end"]])[0])} for s in curriculum]
    ticks = sorted({int(s["start"]) for s in curriculum} | {int(s["end"]) for s in curriculum})
    for ax, (title, keys) in zip(axes.flat, panels):
        _shade_stages(ax, shaded)
        for key in keys:
            pts = [(h["step"], h[key]) for h in history if isinstance(h.get(key), (int, float)) and h.get(key) is not None]
            if not pts:
                continue
            steps, vals = zip(*pts)
            marker = "o" if key.startswith("eval/") else None
            label = {"eval/emd_x0": "frame 0", "eval/cd_x0": "frame 0", "eval/emd_future": "future",
                     "eval/cd_future": "future", "eval/psnr_future": "future"}.get(key, key.split("/", 1)[1])
            ax.plot(to_plot(steps), vals, marker=marker, ms=3, label=label, ls="--" if key.endswith("_x0") else "-")
        ax.set_title(title, fontsize=9, pad=12)
        ax.set_xticks(to_plot(ticks))
        ax.set_xticklabels([str(t) for t in ticks], fontsize=7)
        ax.set_xlabel("iteration" + (" (long stages squeezed)" if compressed else ""), fontsize=8)
        ax.tick_params(labelsize=7)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="best")
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    return save_figure(fig, path)

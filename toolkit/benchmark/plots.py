"""Figures comparing strategies: optimization trajectories, per-frame errors, image strips.

* :func:`plot_strategy_trajectories`: future EMD, future PSNR (one held-out camera) and the
  parameter errors against the iteration, one curve per strategy, averaged over the scenes of a
  material (the paper's strategy-comparison figure); the EMD/PSNR points come from
  :class:`~toolkit.physics.periodic_eval.PeriodicEvaluation`;
* :func:`plot_per_frame_by_strategy`: CD, EMD and PSNR per frame, one curve per strategy, the
  future frames shaded;
* :func:`comparison_strip` and :func:`comparison_strip_video`: the ground truth and each
  strategy's prediction side by side (rows) at the future frames (columns) of one camera, as a
  PNG, and as a video over every frame;
* :func:`write_figures`: all of these for a benchmark folder.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from toolkit.plotting import pyplot, save_figure

__all__ = ["plot_strategy_trajectories", "plot_per_frame_by_strategy", "comparison_strip", "comparison_strip_video",
           "write_figures"]


def _mean_series(histories: Sequence[Sequence[dict]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """Mean over histories of ``key`` at each iteration where at least one history has it."""
    acc: dict[int, list[float]] = {}
    for hist in histories:
        for h in hist:
            v = h.get(key)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                acc.setdefault(int(h["step"]), []).append(float(v))
    steps = np.array(sorted(acc), dtype=float)
    return steps, np.array([np.mean(acc[int(s)]) for s in steps])


def plot_strategy_trajectories(histories: dict[str, Sequence[Sequence[dict]]], curricula: dict[str, Sequence[dict]],
                               path: str | Path, params: Sequence[str] = (), title: str = "", cap: Optional[int] = None) -> Path:
    """One curve per strategy (mean over scenes) of future EMD, future PSNR and parameter errors.

    Args:
        histories: strategy -> one physics history (``history.json``) per scene.
        curricula: strategy -> its stages (:meth:`strategies.Strategy.describe`), for the stage
            ticks and for squeezing very long stages.
        path: the PNG.
        params: material parameters whose error to plot (``v0`` is always plotted when present).
        title: figure title.
        cap: stages longer than this are squeezed to it (default: the longest stage of at most
            1000 iterations over all strategies).
    """
    from toolkit.report import compressed_axis

    plt = pyplot()
    if cap is None:
        spans = [s["end"] - s["start"] for cur in curricula.values() for s in cur if s["end"] - s["start"] <= 1000]
        cap = max(100, max(spans) if spans else 100)
    panels = [("eval/emd_future", "EMD (m), future frames"), ("eval/psnr_future", "PSNR (dB), future frames, held-out camera")]
    panels += [(f"error/{p}", f"MAE {'log10 ' if p in ('E', 'mu', 'kappa', 'yield_stress', 'plastic_viscosity') else ''}{p}")
               for p in params]
    panels.append(("error/v0", "MAE v0 (m/s)"))
    panels = [(k, t) for k, t in panels if any(k in h for hs in histories.values() for hist in hs for h in hist)]
    ncols = min(3, max(1, len(panels)))
    nrows = max(1, math.ceil(len(panels) / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.3 * ncols, 3.1 * nrows), squeeze=False)
    squeezed = False
    for ax, (key, label) in zip(axes.flat, panels):
        for i, (strategy, hists) in enumerate(histories.items()):
            to_plot, comp = compressed_axis(curricula.get(strategy) or [{"start": 0, "end": 1}], cap)
            squeezed |= comp
            steps, vals = _mean_series(hists, key)
            if len(steps) == 0:
                continue
            ax.plot(to_plot(steps), vals, color=f"C{i}", marker="o" if key.startswith("eval/") else None, ms=3,
                    label=f"{strategy} (n={len(hists)})")
            for s in (curricula.get(strategy) or [])[1:]:
                ax.axvline(float(to_plot([s["start"]])[0]), color=f"C{i}", lw=0.6, ls=":", alpha=0.8)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("iteration" + (f" (stages over {cap} iterations squeezed)" if squeezed else ""), fontsize=8)
        ax.tick_params(labelsize=7)
        lines = [ln.get_ydata() for ln in ax.get_lines() if len(ln.get_ydata())]
        if lines:
            ys = np.concatenate([np.asarray(y, dtype=float) for y in lines])
            ys = ys[np.isfinite(ys)]
            if ys.size and ys.min() > 0 and ys.max() / ys.min() > 20:
                ax.set_yscale("log")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="best")
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def plot_per_frame_by_strategy(per_frame: dict[str, Sequence[dict]], n_train: int, path: str | Path, title: str = "") -> Path:
    """CD, EMD and PSNR per frame, one curve per strategy (mean over scenes), future frames shaded.

    Args:
        per_frame: strategy -> one ``{"cd": [...], "emd": [...], "psnr": [...]}`` per scene.
        n_train: first future frame.
        path: the PNG.
        title: figure title.
    """
    plt = pyplot()
    keys = [("cd", "Chamfer distance (x1e3)"), ("emd", "EMD (m)"), ("psnr", "PSNR (dB), all cameras")]
    keys = [(k, t) for k, t in keys if any(pf.get(k) for runs in per_frame.values() for pf in runs)]
    fig, axes = plt.subplots(1, max(1, len(keys)), figsize=(4.0 * max(1, len(keys)), 3.0), squeeze=False)
    for ax, (key, label) in zip(axes.flat, keys):
        T = 0
        for i, (strategy, runs) in enumerate(per_frame.items()):
            series = [np.array([np.nan if v is None else v for v in pf[key]], dtype=float) for pf in runs if pf.get(key)]
            if not series:
                continue
            T = max(T, max(len(s) for s in series))
            stack = np.full((len(series), T), np.nan)
            for j, s in enumerate(series):
                stack[j, : len(s)] = s
            with np.errstate(all="ignore"):
                mean = np.nanmean(stack, axis=0)
            ax.plot(range(T), mean, color=f"C{i}", marker="o", ms=3, label=f"{strategy} (n={len(series)})")
        if T:
            ax.axvspan(n_train - 0.5, T - 0.5, color="0.85", lw=0, zorder=0)
            ax.text((n_train + T - 1) / 2, 1.0, "future", transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=7)
        ax.set_title(label, fontsize=9, pad=12)
        ax.set_xlabel("frame", fontsize=8)
        ax.tick_params(labelsize=7)
        if key in ("cd",):
            ax.set_yscale("log")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def _upscale(img: np.ndarray, min_height: int = 160) -> np.ndarray:
    """Nearest-neighbour upscaling by an integer factor so small renders stay legible."""
    f = max(1, int(np.ceil(min_height / img.shape[0])))
    return img if f == 1 else np.repeat(np.repeat(img, f, axis=0), f, axis=1)


def _grid(tiles: list[list[np.ndarray]], row_labels: Sequence[str], col_labels: Sequence[str]) -> np.ndarray:
    """Tiles (rows x columns of equal-sized images) on a white canvas with row and column labels."""
    from PIL import Image, ImageDraw

    h, w = tiles[0][0].shape[:2]
    left = 8 + 7 * max(len(t) for t in row_labels)
    top, pad = 18, 2
    H = top + len(tiles) * (h + pad)
    W = left + len(tiles[0]) * (w + pad)
    canvas = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for j, text in enumerate(col_labels):
        draw.text((left + j * (w + pad) + 3, 3), text, fill=(0, 0, 0))
    for i, row in enumerate(tiles):
        y = top + i * (h + pad)
        draw.text((4, y + h // 2 - 6), row_labels[i], fill=(0, 0, 0))
        for j, tile in enumerate(row):
            canvas.paste(Image.fromarray(np.ascontiguousarray(tile)), (left + j * (w + pad), y))
    return np.asarray(canvas)


def comparison_strip(gt: np.ndarray, preds: dict[str, np.ndarray], frames: Sequence[int], path: str | Path,
                     n_train: Optional[int] = None) -> Path:
    """Rows: ground truth, then each strategy; columns: ``frames``. Images are (T, H, W, 3) uint8.

    Args:
        gt: ground-truth images of one camera (masked on black), (T, H, W, 3) uint8.
        preds: strategy -> its rendered prediction of the same camera, (T, H, W, 3) uint8.
        frames: the frames shown (e.g. the future ones).
        path: the PNG.
        n_train: first future frame (columns from it on are labelled "future").
    """
    import imageio.v3 as iio

    names = ["truth"] + list(preds)
    seqs = [gt] + list(preds.values())
    tiles = [[_upscale(seq[t]) for t in frames] for seq in seqs]
    cols = [f"t={t}" + (" future" if n_train is not None and t >= n_train else "") for t in frames]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, _grid(tiles, names, cols))
    return path


def comparison_strip_video(gt: np.ndarray, preds: dict[str, np.ndarray], n_train: int, path: str | Path,
                           fps: float = 6.0) -> Path:
    """Ground truth and each strategy side by side over every frame (MP4; GIF without ffmpeg)."""
    import imageio.v3 as iio

    names = ["truth"] + list(preds)
    seqs = [gt] + list(preds.values())
    frames = []
    digits = len(str(gt.shape[0] - 1))  # one label width for every frame: the video's frames share one size
    for t in range(gt.shape[0]):
        tag = f"t={t:0{digits}d} {'future' if t >= n_train else 'fitted'}"
        img = _grid([[_upscale(seq[t]) for seq in seqs]], [tag], names)
        frames.append(img[: img.shape[0] // 2 * 2, : img.shape[1] // 2 * 2])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        iio.imwrite(path, np.stack(frames), fps=fps, codec="libx264", macro_block_size=1)
        return path
    except Exception:  # noqa: BLE001 - no ffmpeg here: a GIF instead
        gif = path.with_suffix(".gif")
        iio.imwrite(gif, np.stack(frames), duration=1000 / fps, loop=0)
        return gif


def _ground_truth_images(physics_input: Path, camera: Optional[int]) -> tuple[np.ndarray, int, int, list[int]]:
    """(T, H, W, 3) uint8 masked ground truth of ``camera`` (default: the first held-out one)."""
    import torch

    d = torch.load(physics_input, map_location="cpu", weights_only=False, mmap=True)
    train = list(d["train_cameras"])
    C = int(d["images"].shape[0])
    held = [c for c in range(C) if c not in train]
    cam = camera if camera is not None else (held[0] if held else train[0])
    img = d["images"][cam].numpy().astype(np.float32)
    mask = d["masks"][cam].numpy().astype(np.float32)[..., None] / 255.0
    return np.round(img * mask).astype(np.uint8), int(d["n_train"]), cam, train


def write_figures(bench_dir: str | Path, records: Sequence[dict], out_dir: Optional[str | Path] = None,
                  strategies: Optional[Sequence[str]] = None, camera: Optional[int] = None, max_strips: int = 8) -> list[Path]:
    """Trajectories and per-frame curves per material and camera count, and one strip (PNG + video)
    per scene and camera count (at most ``max_strips``), into ``out_dir`` (default ``BENCH/tables``)."""
    bench = Path(bench_dir)
    out = Path(out_dir) if out_dir else bench / "tables"
    out.mkdir(parents=True, exist_ok=True)
    order = list(strategies or [])
    written: list[Path] = []
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        groups.setdefault((r["material"], r["cameras"]), []).append(r)
    for (mat, cams), recs in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][1] or 0)):
        strats = [s for s in order if any(r["strategy"] == s for r in recs)] + sorted(
            {r["strategy"] for r in recs} - set(order))
        histories, curricula, per_frame = {}, {}, {}
        for st in strats:
            for r in (r for r in recs if r["strategy"] == st):
                run = Path(r["run_dir"])
                hp = run / "physics" / "history.json"
                if hp.is_file():
                    histories.setdefault(st, []).append(json.loads(hp.read_text()))
                ep = run / "physics" / "estimate.json"
                if ep.is_file() and st not in curricula:
                    curricula[st] = json.loads(ep.read_text()).get("curriculum") or []
                if r.get("per_frame"):
                    per_frame.setdefault(st, []).append(r["per_frame"])
        params = sorted({p for r in recs for p in r.get("optimized", [])})
        tag = f"{mat}_cams{cams}"
        if histories:
            written.append(plot_strategy_trajectories(histories, curricula, out / f"trajectories_{tag}.png", params,
                                                      title=f"{mat}, {cams} views: optimization trajectories (mean over scenes)"))
        n_train = next((r["n_train"] for r in recs if r.get("n_train")), None)
        if per_frame and n_train:
            written.append(plot_per_frame_by_strategy(per_frame, n_train, out / f"per_frame_{tag}.png",
                                                      title=f"{mat}, {cams} views: error per frame (mean over scenes)"))
    strips = 0
    by_scene: dict[tuple, list[dict]] = {}
    for r in records:
        by_scene.setdefault((r["scene"], r["cameras"]), []).append(r)
    for (scene, cams), recs in sorted(by_scene.items(), key=lambda kv: (kv[0][0], kv[0][1] or 0)):
        if strips >= max_strips:
            break
        inp = bench / "scenes" / scene / f"cams{cams}" / "physics_input.pt"
        if not inp.is_file():
            continue
        gt, n_train, cam, _ = _ground_truth_images(inp, camera)
        preds = {}
        for st in [s for s in order if any(r["strategy"] == s for r in recs)] + sorted({r["strategy"] for r in recs} - set(order)):
            rec = next(r for r in recs if r["strategy"] == st)
            rp = Path(rec["run_dir"]) / "evaluation" / "renders.npz"
            if rp.is_file():
                preds[st] = np.load(rp)["renders"][:, cam]
        if not preds:
            continue
        T = gt.shape[0]
        future = list(range(n_train, T)) or [T - 1]
        shown = future if len(future) <= 6 else [future[int(round(i))] for i in np.linspace(0, len(future) - 1, 6)]
        tag = f"{scene.replace('/', '-')}_cams{cams}_camera{cam}"
        written.append(comparison_strip(gt, preds, shown, out / f"strip_{tag}.png", n_train))
        written.append(comparison_strip_video(gt, preds, n_train, out / f"strip_{tag}.mp4"))
        strips += 1
    return written

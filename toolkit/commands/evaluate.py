"""``projo4d evaluate RUN_DIR``: re-evaluate a fitted run folder.

Loads the fitted model (``physics/checkpoints/last.ckpt`` + ``physics_input.pt``), simulates
every frame with the estimated state (the frames after the training ones are the future
prediction), computes every metric (CD and EMD per frame against the ground-truth clouds; PSNR
and SSIM over all, fitted and held-out cameras, training and future frames; parameter errors),
and writes::

    RUN_DIR/evaluation/   evaluation.json (all numbers, per-frame lists included), prediction.npz,
                          renders.npz (unless --no-render)
    RUN_DIR/report/       trajectories.png, per_frame.png (+ evaluation_trajectories.png when the
                          fit recorded periodic evaluations; prediction_vs_truth.mp4 with renders)
    RUN_DIR/summary.json  refreshed headline numbers

and prints a table (or the JSON with ``--json``).

Examples::

    projo4d evaluate runs/torus
    projo4d evaluate runs/torus --no-render --json > eval.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

__all__ = ["configure", "run", "evaluate_run", "format_evaluation"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="a fitted run folder (projo4d run / benchmark)")
    parser.add_argument("--no-render", action="store_true", help="skip rendering: no PSNR/SSIM, no video (faster)")
    parser.add_argument("--no-report", action="store_true", help="do not redraw report/")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--json", action="store_true", help="print evaluation.json instead of the table")


def evaluate_run(run_dir: str | Path, render: bool = True, report: bool = True, device: str = "auto") -> dict:
    """Re-evaluate ``run_dir``; returns the evaluation dict (also written to ``evaluation/``)."""
    import numpy as np
    import torch

    from toolkit.evaluation import evaluate_module
    from toolkit.pipeline import _device, load_fitted_module
    from toolkit.run_summary import run_summary

    run = Path(run_dir)
    dev = _device(device)
    if dev == "cpu":
        torch.set_num_threads(max(1, min(4, torch.get_num_threads())))
    module = load_fitted_module(run, device=dev)
    import time

    t = time.perf_counter()
    out_dir = run / "evaluation"
    evaluation = evaluate_module(module, out_dir, render=render)
    if not render:
        stale = out_dir / "renders.npz"
        if stale.is_file():
            stale.unlink()  # renders of an earlier evaluation would not match this one
    elapsed = time.perf_counter() - t
    old = {}
    sp = run / "summary.json"
    if sp.is_file():
        old = json.loads(sp.read_text())
    grid = old.get("grid_check")  # the grid check belongs to the fit, not to the evaluation: kept
    files = []
    if report:
        from toolkit.report import write_report

        inp = module.input
        cams = inp.train_cameras[:2] + inp.held_out_cameras[:2]
        renders = None
        if render:
            renders = np.load(out_dir / "renders.npz")["renders"].transpose(1, 0, 2, 3, 4)
        files = write_report(run, module.history, module.curriculum.describe(module.material.registry_name or None),
                             evaluation, inp.ground_truth, inp.images.numpy() if render else None, renders, cams,
                             grid_check=grid)
    timings = {k: float(v) for k, v in (old.get("timings_s") or {}).items() if isinstance(v, (int, float))}
    timings["evaluation_s"] = elapsed
    summary = run_summary(module, evaluation, timings, files or [Path(f) for f in old.get("report", [])])
    for key in ("benchmark", "grid_check"):
        if key in old:
            summary[key] = old[key]
    from toolkit.atomic import write_json
    from toolkit.physics.grid_check import annotate_grid

    annotate_grid(summary["parameters"], grid, module.estimate()["params"])
    write_json(sp, summary)
    return evaluation


def _f(v, fmt: str = ".4g") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def format_evaluation(evaluation: dict, run_dir: str | Path = "") -> str:
    """A terminal table of an evaluation dict."""
    est = evaluation.get("estimate") or {}
    lines = [f"{run_dir}: material {est.get('material')}, frames {evaluation['n_train']} fitted + "
             f"{evaluation['n_frames'] - evaluation['n_train']} future", f"{'metric':<34}{'training':>12}{'future':>12}"]
    geo = evaluation.get("geometry")
    if geo:
        lines.append(f"{'Chamfer distance (x1e3)':<34}{_f(geo.get('cd_train'), '.4f'):>12}{_f(geo.get('cd_future'), '.4f'):>12}")
        lines.append(f"{'EMD (m)':<34}{_f(geo.get('emd_train'), '.5f'):>12}{_f(geo.get('emd_future'), '.5f'):>12}")
    else:
        lines.append("(no ground-truth point clouds: no CD/EMD)")
    for part, label in (("all_cameras", "all cameras"), ("fitted_cameras", "fitted cameras"), ("held_out_cameras", "held-out cameras")):
        im = (evaluation.get("images") or {}).get(part)
        if im:
            lines.append(f"{'PSNR (dB), ' + label:<34}{_f(im.get('psnr_train'), '.2f'):>12}{_f(im.get('psnr_future'), '.2f'):>12}")
            lines.append(f"{'SSIM, ' + label:<34}{_f(im.get('ssim_train'), '.4f'):>12}{_f(im.get('ssim_future'), '.4f'):>12}")
    if not evaluation.get("images"):
        lines.append("(not rendered: no PSNR/SSIM)")
    errors = {k.split("/", 1)[-1]: v for k, v in (evaluation.get("errors") or {}).items()}
    lines.append(f"{'parameter':<20}{'estimate':>14}{'error':>14}")
    for name, value in (est.get("params") or {}).items():
        lines.append(f"{name:<20}{_f(value):>14}{_f(errors.get(name)):>14}")
    v0 = est.get("v0")
    if v0 is not None:
        lines.append(f"{'v0 (m/s)':<20}{'(' + ', '.join(_f(x, '.3f') for x in v0) + ')':>14}{_f(errors.get('v0')):>14}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if not (args.run_dir / "physics" / "checkpoints" / "last.ckpt").is_file():
        raise SystemExit(f"projo4d evaluate: {args.run_dir} has no physics/checkpoints/last.ckpt (fit it first)")
    import contextlib
    import sys

    # with --json, stdout carries the JSON alone (kernel-cache messages go to stderr)
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        evaluation = evaluate_run(args.run_dir, render=not args.no_render, report=not args.no_report, device=args.device)
    if args.json:
        print(json.dumps(evaluation, indent=2))
    else:
        print(format_evaluation(evaluation, args.run_dir))
    return 0

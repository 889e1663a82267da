"""A run's summary: the ``summary.json`` record of a fitted module and its terminal table."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

__all__ = ["run_summary", "format_summary"]


def run_summary(module, evaluation: dict, timings: dict, files: Sequence[Path]) -> dict:
    """The ``summary.json`` of a fitted ``module``: estimate beside the truth with intervals and
    labels (material parameters, v0 and the strengths of fitted effects, ``<effect>.<param>``),
    future and training metrics, timings and report files (``evaluation``: the
    :func:`toolkit.evaluation.evaluate_module` record)."""
    est = module.estimate()
    gt = module.input.ground_truth or {}
    rows = []
    for name, value in est["params"].items():
        truth = (gt.get("params") or {}).get(name)
        rows.append({"parameter": name, "estimate": value, "truth": truth})
    for i, c in enumerate("xyz"):
        rows.append({"parameter": f"v0_{c}", "estimate": est["v0"][i], "truth": None if gt.get("v0") is None else gt["v0"][i]})
    true_effects = gt.get("effects") if isinstance(gt.get("effects"), dict) else {}
    for effect, values in (est.get("effects") or {}).items():  # fitted effects, named as the uncertainty names them
        truth = true_effects.get(effect) if isinstance(true_effects.get(effect), dict) else {}
        for param, value in values.items():
            rows.append({"parameter": f"{effect}.{param}", "estimate": float(value), "truth": truth.get(param)})
    from toolkit.physics.uncertainty import annotate_rows  # 90 % intervals and identifiability labels (issue #24)

    annotate_rows(rows, module.uncertainty_result)
    geo = evaluation.get("geometry") or {}
    img = (evaluation.get("images") or {}).get("all_cameras") or {}
    from toolkit.physics.world_checks import to_dataset_frame

    world = module.input.meta.get("world")
    return {
        "world": world,
        "dataset_frame": to_dataset_frame(est, world),  # v0 and gravity in the dataset's own axes
        "material": est["material"],
        "curriculum": module.curriculum.schedule_string(module.material.registry_name or None),
        "parameters": rows,
        "uncertainty": None if module.uncertainty_result is None else {
            k: module.uncertainty_result[k] for k in ("level", "noise_std", "dof", "frames", "rollouts", "seconds", "prior_step")},
        "errors": evaluation.get("errors", {}),
        "future": {"cd": geo.get("cd_future"), "emd": geo.get("emd_future"), "psnr": img.get("psnr_future"),
                   "ssim": img.get("ssim_future")},
        "train": {"cd": geo.get("cd_train"), "emd": geo.get("emd_train"), "psnr": img.get("psnr_train"),
                  "ssim": img.get("ssim_train")},
        "timings_s": {k: round(v, 1) for k, v in timings.items()},
        "report": [str(f) for f in files],
        "stage0_coverage": module.input.meta.get("stage0_coverage"),  # frames where stage 0 lost the object
        # the stage-0 ballistic estimate v0 started from: its free-flight frames and why it stopped there
        "v0_estimate": getattr(module, "v0_estimate", None),
        # where v0 started (estimate, given, zero, no estimate) and how a [S] stage resolved
        "v0_origin": getattr(module, "v0_origin", None),
        # does the body fall at g in the folder's frame times and units (None: too few free-flight frames)
        "time_scale": getattr(module, "time_scale", None),
    }


def format_summary(summary: dict) -> str:
    """A small table of the estimate next to the truth, for terminals."""
    lines = [f"material {summary['material']}, curriculum {summary['curriculum']}",
             f"{'parameter':<18}{'estimate':>14}{'truth':>14}  {'90 % interval':<24}label"]
    from toolkit.physics.uncertainty import format_interval

    for r in summary["parameters"]:
        est, tru = r["estimate"], r["truth"]
        fmt = (lambda v: "-" if v is None else (f"{v:.4g}"))  # noqa: E731
        label = r.get("label") or "-"
        label += f" ({r['note']})" if r.get("note") else ""
        lines.append(f"{r['parameter']:<18}{fmt(est):>14}{fmt(tru):>14}  {format_interval(r.get('low'), r.get('high')):<24}{label}")
    from toolkit.physics.starting_state import describe_start

    said = describe_start(summary.get("v0_origin"), summary.get("v0_estimate"))
    if said:
        lines.append(said)
    fut = summary["future"]
    if fut.get("cd") is not None:
        lines.append(f"future frames: CD {fut['cd']:.3f}  EMD {fut['emd']:.4f}  PSNR {fut['psnr'] or float('nan'):.2f}  "
                     f"SSIM {fut['ssim'] or float('nan'):.3f}")
    if summary.get("forecast_spread"):
        from toolkit.physics.forecast_spread import describe_spread

        lines.append(describe_spread(summary["forecast_spread"]))
    if summary.get("grid_check"):
        from toolkit.physics.grid_check import format_grid_check

        lines.append(format_grid_check(summary["grid_check"]))
    coverage = summary.get("stage0_coverage") or {}
    if coverage.get("lost_frames"):
        from toolkit.scene.coverage import lost_object_message

        lines.append("WARNING " + lost_object_message(coverage))
    time_scale = summary.get("time_scale") or {}
    if time_scale and not time_scale.get("agrees", True):
        lines.append("WARNING " + time_scale.get("message", "the body does not fall at g in the folder's frame times"))
    silhouettes = summary.get("silhouettes") or {}
    if silhouettes.get("disagree"):  # the warning before stage 0 has scrolled away by now
        lines.append("WARNING " + silhouettes.get("message", "the fitting cameras' silhouettes disagree"))
    lines.append("timings (s): " + ", ".join(f"{k} {v}" for k, v in summary["timings_s"].items()))
    refined = summary.get("refined")
    if refined and refined.get("failed"):
        lines.append(f"--- the refined fit on a grid of half the spacing failed ({refined['out']}); the estimate above "
                     f"stands: {refined['failed']}")
    elif refined:
        why = f"; {refined['reason']}" if refined.get("reason") else ""
        lines.append(f"--- refined on a grid of half the spacing ({refined['out']}{why}):")
        lines.append(format_summary(refined["summary"]))
    return "\n".join(lines)

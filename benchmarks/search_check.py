"""Where the coarse material search starts a fit, against the truth, by the fit's own score (issue #20).

For each finished run folder of a scene with ground truth, loads the fit as it stood at a kept
stage end (by default the one just before the first stage that optimizes ``M``, where
:func:`toolkit.physics.coarse_search.coarse_search` runs: the positions, appearance and v0 the
search saw), runs
the search again on the stage that optimizes ``M``, and scores the truth's material parameters
with the same loss on the same frames. Where the truth scores lower than the search's pick, the
search, not the loss, put the fit's start in the wrong place.

One JSON line per run::

    {"run", "pick": {name: value}, "pick_loss", "truth": {...}, "truth_loss", "truth_true_v0_loss",
     "pick_true_v0_loss", "window_frames", "pick_window_loss", "truth_window_loss", "v0", "true_v0",
     "start_error": {name: decades or absolute}, "rollouts", "seconds", "paths": [...]}

``*_loss`` are on the search's few frames, ``*_window_loss`` on every frame of the stage's window
(where the joint search weighs its product grid's paths against the default's pick).

``truth_true_v0_loss`` and ``pick_true_v0_loss`` score the truth's material and the pick with the
true initial velocity instead of the fitted one: where the truth wins only then, the initial
velocity fitted before the search, not the body or the appearance, biased the search's loss.

Usage::

    python benchmarks/search_check.py BENCH/runs/plasticine/*/cams3/progressive
    python benchmarks/search_check.py RUN --checkpoint stage_00_end.ckpt --device cuda
    python benchmarks/search_check.py BENCH/runs/plasticine/*/cams3/progressive --joint-yield

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _score(module, stage, frames: list[int], values: dict[str, float], v0=None) -> float:
    """:func:`~toolkit.physics.coarse_search.candidate_loss` with the material at ``values`` (the
    others as fitted) and the initial velocity ``v0`` (m/s; default as fitted)."""
    import torch

    from toolkit.physics.coarse_search import candidate_loss

    names = list(module.material.param_names)
    params = module.material_params().detach().clone()
    for n, v in values.items():
        params[names.index(n)] = v
    v = None if v0 is None else torch.as_tensor(v0, dtype=module.v0.dtype, device=module.v0.device)
    return candidate_loss(module, stage, params, frames, v)


def _error(module, name: str, value: float, truth: float) -> float:
    if module.material.param(name).transform == "log10":
        return math.log10(value / truth)
    return value - truth


def _checkpoint(run: Path, name: str) -> str:
    """``name``, or for ``auto`` the kept stage end saved at the iteration the run's search ran
    (``physics/material_search.json``'s ``iteration``).

    Raises:
        ValueError: the checkpoint is not there, naming the path and what is expected.
    """
    folder = run / "physics" / "checkpoints"
    if name != "auto":
        if not (folder / name).is_file():
            raise ValueError(f"{folder / name} does not exist (expected a kept checkpoint of a finished run)")
        return name
    import torch

    record = run / "physics" / "material_search.json"
    if not record.is_file():
        raise ValueError(f"{record} does not exist: the run never ran the coarse search (material_init='search')")
    iteration = json.loads(record.read_text())["iteration"]
    for ckpt in sorted(folder.glob("stage_*_end.ckpt")):
        state = torch.load(ckpt, map_location="cpu", weights_only=True).get("projo4d", {})
        if state.get("curriculum_step") == iteration:
            return ckpt.name
    raise ValueError(f"{folder}: no stage_*_end.ckpt saved at iteration {iteration}, where the search ran "
                     "(name one with --checkpoint)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="finished run folders (physics/checkpoints/) of scenes with ground truth")
    ap.add_argument("--checkpoint", default="auto",
                    help="kept checkpoint to start from (default: the stage end before the first stage fitting M)")
    ap.add_argument("--joint-yield", action="store_true",
                    help="search with coarse_search(joint_yield=True): the first parameter and the yield parameter on one grid")
    ap.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N (default cpu)")
    args = ap.parse_args(argv)
    from toolkit.run_validation import parse_device_option

    args.device = parse_device_option(ap, args.device)
    picks, problems = {}, []
    for run in args.runs:
        try:
            picks[run] = _checkpoint(Path(run), args.checkpoint)
        except ValueError as err:
            problems.append(str(err))
    if problems:
        ap.error(f"--checkpoint {args.checkpoint}: " + "; ".join(problems))

    from toolkit.verbosity import configure_output

    configure_output(False)
    from toolkit.physics.coarse_search import coarse_search, score_frames
    from toolkit.pipeline import load_fitted_module

    for run in args.runs:
        module = load_fitted_module(run, device=args.device, checkpoint=picks[run])
        gt = module.input.ground_truth or {}
        if not gt.get("params"):
            print(json.dumps({"run": run, "skipped": "no ground truth"}), flush=True)
            continue
        stage = next(s for s in module.stages if "M" in s.groups)
        result = coarse_search(module, stage, joint_yield=args.joint_yield)
        truth = {n: float(gt["params"][n]) for n in result["parameters"] if n in gt["params"]}
        truth_loss = _score(module, stage, result["frames"], truth)
        true_v0_loss = _score(module, stage, result["frames"], truth, gt["v0"])
        pick_true_v0_loss = _score(module, stage, result["frames"], result["best"], gt["v0"])
        window = stage.window(module.input.n_train)
        whole = score_frames(window, window)
        truth_window_loss = _score(module, stage, whole, truth)
        pick_window_loss = _score(module, stage, whole, result["best"])
        print(json.dumps({
            "run": run, "checkpoint": picks[run], "joint_yield": args.joint_yield, "stage": stage.name, "pick": result["best"], "pick_loss": result["best_loss"], "truth": truth,
            "truth_loss": truth_loss, "truth_true_v0_loss": true_v0_loss, "pick_true_v0_loss": pick_true_v0_loss,
            "window_frames": whole, "pick_window_loss": pick_window_loss, "truth_window_loss": truth_window_loss,
            "v0": module.v0.detach().tolist(), "true_v0": gt["v0"], "start": result["start"], "start_loss": result["start_loss"],
            "start_error": {n: round(_error(module, n, v, truth[n]), 3) for n, v in result["best"].items() if n in truth},
            "paths": result["paths"], "rollouts": result["rollouts"], "seconds": round(result["seconds"], 2),
        }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Discovery benchmark: scenes with a hidden effect, fitted with the base model, then ``discover``.

Suite (:func:`toolkit.discovery.hidden.hidden_suite`): every candidate of the library hidden at
medium and high strength, for two base materials (elastic ``neo_hookean``, ``plasticine``) and
two throws (``slide``, ``toss``), plus null scenes with nothing hidden. Per scene: generate the
truth, build the oracle physics input, fit the base model (``fit_physics``), run
:func:`toolkit.discovery.discover`. The null scenes run first: their statistics calibrate the
"no missing effect" thresholds (``--calibrate``; otherwise the shipped or ``--thresholds``
ones are used), and the false-positive rate is reported both with the thresholds used and with
2-fold cross-calibration (each half of the null scenes judged with thresholds calibrated on
the other half).

Reported: top-1 and top-3 identification accuracy (hidden physics effects and controls; the
expected answer for null and density scenes is "no missing effect"), the confusion matrix,
strength errors of identified effects, the median future-Chamfer gap shrink, the
false-positive rate on null scenes. Output: one JSON line per scene and a summary JSON line
on stdout, ``OUT/results.jsonl`` (resumable: finished scenes are skipped), ``OUT/summary.json``
and ``OUT/discovery_benchmark.md``; with ``--update-docs`` the table also replaces the
benchmark section of ``docs/tutorials/discovery.md`` for this run size.

Usage::

    python benchmarks/discovery.py --small --calibrate --out outputs/discovery_small      # CPU smoke run
    python benchmarks/discovery.py --calibrate --out outputs/discovery                  # full size (60 scenes)
    python benchmarks/discovery.py --null-only --shard 0/4 --out D                       # sharded: null scenes first,
    python benchmarks/discovery.py --report-only --calibrate --out D                    #   calibrate (writes D/thresholds.json),
    python benchmarks/discovery.py --shard 0/4 --out D                                  #   then the hidden scenes, 4 processes
    python benchmarks/discovery.py --report-only --out outputs/discovery --update-docs    # merge and tabulate
    python benchmarks/discovery.py --geometry stage0 --calibrate --out outputs/discovery_images   # from images
    python benchmarks/discovery.py --geometry stage0 --stage0-seed 1 --calibrate --out outputs/discovery_images_s1
    python benchmarks/discovery_runs.py s0=outputs/discovery_images s1=outputs/discovery_images_s1 --calibrate
                                                          # the same suite's decisions over two stage-0 runs

From images (``--geometry stage0``): each scene's geometry comes from stage 0 + the continuum
(:mod:`toolkit.discovery.from_images`; schedule ``--stage0``, default
``STAGE0_SCHEDULES[size]``; on ``--stage0-device``, default ``--device``), built once per
scene in ``OUT/runs/SCENE/images`` (resumable, shared by every candidate), the base fit holds
the positions still, and discovery carries stage 0's floor. Null scenes of the same geometry must calibrate the thresholds (``--calibrate``): the
shipped ones come from oracle scenes. Per scene the JSON line adds ``geometry``, the tied
candidates' ``separation`` (the observation that would separate them), ``joint`` and ``floors``.

Expected cost (measured): the CPU smoke run (22 tiny scenes) takes about 15 minutes on 2 cores.
A full-size scene (about 400 particles) is launch-bound, not compute-bound: with 16 processes
sharing 2 H200 GPUs and 32 cores, the base fit took 6-8 minutes and discovery 1-2 minutes per
scene, while one CPU process with 2 threads fits the same scene in 3.6 minutes and runs
discovery in 1.7. So on a GPU machine run the shards on its CPU cores (``--device cpu``, one
shard per core, one thread each): the default suite (40 hidden + 20 null scenes) on 60 shards
of a 64-core machine took 15 minutes (base fit 6-11 minutes, discovery 1.7-4.8 minutes per
scene, next to a strategy comparison on its GPUs). With fewer cores, ``--time-budget`` stops
starting scenes after that many seconds; rerun to continue.

From images the physics renders stage 0's Gaussians at every iteration. Without a cap stage 0
grew 27k-104k of them on these 96 px scenes and no base fit finished in 17 minutes on a core;
the full stage-0 schedule now caps them at one per observed object pixel (3.1k-8.5k in the scenes whose logs state it), and
``benchmarks/discovery_from_images.sh`` runs stage 0 on the GPUs and the physics on one core per
scene: stage 0 took 209-238 s, the base fit 411-1063 s and discovery 108-518 s per scene
(4 H200 GPUs and 64 cores, 2026-11-27).

Reported in addition: top-1/top-3 on the scenes whose effect the data show (refitting the true
effect halves the future gap); "no missing effect" is all the other scenes support.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the benchmarks' own modules, when loaded by path
from discovery_tables import decide_record, markdown, summarize  # noqa: E402
from discovery_tables import CONTROLS, truth_shrink  # noqa: E402,F401  (discovery_runs.py reads them from here)

ROOT = Path(__file__).resolve().parents[1]
DOCS_PAGE = ROOT / "docs" / "tutorials" / "discovery.md"
#: the docs page's benchmark sections, one per run size (``--small`` or not) and geometry
MARKS = {(True, "oracle"): ("<!-- benchmark-small:start -->", "<!-- benchmark-small:end -->"),
         (False, "oracle"): ("<!-- benchmark-full:start -->", "<!-- benchmark-full:end -->"),
         (True, "stage0"): ("<!-- benchmark-images-small:start -->", "<!-- benchmark-images-small:end -->"),
         (False, "stage0"): ("<!-- benchmark-images-full:start -->", "<!-- benchmark-images-full:end -->")}


def build_suite(args):
    from toolkit.discovery.hidden import HiddenScene, hidden_suite

    if args.small:
        effects = args.effects or ["ground_friction", "air_drag", "extra_acceleration", "wall", "internal_damping", "plastic_yield",
                                   "timing", "stiffness_gradient", "density", "camera_pose"]
        scenes = [HiddenScene(e, "high", "neo_hookean", "slide", "tiny") for e in effects]
        scenes += [HiddenScene("none", "none", "neo_hookean", ("slide", "toss")[i % 2], "tiny", seed=i) for i in range(args.null)]
        return scenes
    return hidden_suite(levels=tuple(args.levels), materials=tuple(args.materials), throws=tuple(args.throws), n_null=args.null,
                        size="full", effects=args.effects, combos=args.combos)


def run_scene(hs, args, thresholds) -> dict:
    import torch

    from toolkit.discovery import discover
    from toolkit.discovery.hidden import fit_base

    out = Path(args.out)
    t0 = time.time()
    root = hs.generate(out / "scenes" / hs.name, device=args.device)
    t_gen = time.time() - t0
    run = out / "runs" / hs.name
    accel = "gpu" if args.device.startswith("cuda") else "cpu"
    t0 = time.time()
    if args.geometry == "stage0":
        from toolkit.discovery.from_images import fit_base_from_images, stage0_physics_input

        # stage 0 + continuum in RUN/images (resumable, shared by every candidate); the input with
        # the scene's observation errors applied is RUN/physics_input.pt
        inp = stage0_physics_input(hs, root, run / "images", stage0=_stage0_arg(args.stage0) if args.stage0 else None,
                                   device=args.stage0_device or args.device, seed=args.stage0_seed,
                                   cameras=list(args.cameras) if args.cameras else "sparse")
    else:
        inp = hs.physics_input(root)
    t_stage0 = time.time() - t0
    inp.save(run / "physics_input.pt")
    t0 = time.time()
    if args.geometry == "stage0":
        module = fit_base_from_images(inp, run / "physics", hs, accelerator=accel)
    else:
        module = fit_base(inp, run / "physics", material=hs.material, size=hs.size, accelerator=accel)
    t_fit = time.time() - t0
    t0 = time.time()
    res = discover(module, run / "discovery", thresholds=thresholds, top_k=args.top_k, report=not args.no_reports)
    t_disc = time.time() - t0
    d = res.to_dict()
    final = res.final.strengths if res.final is not None else {}
    truth = hs.truth_strengths()
    errors = {k: abs(final[k] - v) for k, v in truth.items() if k in final} if res.decision == hs.expected else {}
    order = _order(d)
    rec = {
        "scene": hs.name, "geometry": args.geometry, "stage0_seed": args.stage0_seed if args.geometry == "stage0" else None,
        "effect": hs.effect, "level": hs.level, "material": hs.material, "throw": hs.throw, "size": hs.size,
        "expected": hs.expected, "decision": res.decision, "kind": res.decision_kind, "indistinguishable": res.indistinguishable,
        "separation": [{k: v for k, v in d.items() if k in ("candidates", "observation", "sentence", "camera")} for d in res.separation],
        "joint": res.joint, "floors": res.floors, "noise": res.noise, "motion": res.motion,
        "single_camera": res.localization.single_camera if res.localization.single_camera in inp.train_cameras else None,
        "silhouettes": res.silhouettes, "fitting_cameras": [int(c) for c in inp.train_cameras],
        "correct": res.decision == hs.expected, "top3": order[:3], "cd_before": res.gap.get("cd_future_before"),
        "cd_after": res.gap.get("cd_future_after"), "cd_truth_effect": res.gap.get("cd_future_truth_effect"),
        "cd_shrink": res.gap.get("cd_shrink"), "psnr_before": res.gap.get("psnr_future_before"),
        "psnr_after": res.gap.get("psnr_future_after"), "strengths": final, "truth_strengths": truth, "strength_errors": errors,
        "validation": d["validation"], "dofs": {s["name"]: s["dof"] for s in d["ranking"]["scores"]},
        "scores": {s["name"]: s["score"] for s in d["ranking"]["scores"]},
        "refits": _refit_summary(d["refits"]),
        "seconds": {"generate": t_gen, "stage0": t_stage0, "fit": t_fit, "discover": t_disc, **res.seconds},
    }
    del module, res
    if args.device.startswith("cuda"):
        torch.cuda.empty_cache()
    return _clean(rec)


def _refit_summary(refits: dict) -> dict:
    """Per confirmation refit: its objective, strengths and, for a candidate refitted from two
    starts (extra acceleration, air drag), the start kept and the other start's objective."""
    out = {}
    for name, r in refits.items():
        extra = r.get("extra") or {}
        out[name] = {"objective": r.get("objective"), "strengths": r.get("strengths") or {},
                     **{k: extra[k] for k in ("start", "other_start_objective") if k in extra}}
    return out


def _order(d: dict) -> list[str]:
    """Candidates best first: confirmed physics candidates by validation improvement, then the
    rest by ranking score (controls are listed like the others)."""
    val = {n: v["validation"] for n, v in d["validation"].items() if n != "base"}
    confirmed = sorted(val, key=lambda n: -val[n])
    rest = [s["name"] for s in d["ranking"]["scores"] if s["name"] not in val]
    order = confirmed + rest
    if d["decision"] is not None and d["decision"] in order:
        order.remove(d["decision"])
        order.insert(0, d["decision"])
    return order


def _clean(x):
    if isinstance(x, float):
        return None if (math.isnan(x) or math.isinf(x)) else x
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        return _clean(x.item())
    return x


def iter_records(out: Path):
    """``(file, record)`` for every line of ``out/results*.jsonl``, in file order (a later line of
    a scene replaces an earlier one where they are gathered); a line that is not JSON stops with
    its file and line number."""
    for f in sorted(Path(out).glob("results*.jsonl")):
        for k, line in enumerate(f.read_text().splitlines(), 1):
            if not line.strip():
                continue
            try:
                yield f, json.loads(line)
            except json.JSONDecodeError as err:
                raise SystemExit(f"{f}:{k}: not a JSON line ({err})") from None


def redecide(records: list[dict], thr) -> list[dict]:
    """Copies of stored records decided again under ``thr`` (:func:`discovery_tables.decide_record`); a changed decision
    drops the gap shrink, which belonged to another candidate's refit."""
    out = []
    for r in records:
        r = dict(r)
        runtime = r["decision"]
        r["decision"], r["kind"], r["indistinguishable"] = decide_record(r, thr)
        r["correct"] = r["decision"] == r["expected"]
        if r["decision"] != runtime:
            r["cd_shrink"] = None
        out.append(r)
    return out


def _stage0_arg(text: str):
    """``--stage0``: a preset name or JSON of Stage0Schedule fields."""
    return json.loads(text) if text.strip().startswith("{") else text


def _stage0_label(text: Optional[str]) -> str:
    """A short name of ``--stage0`` for the table's title (a JSON schedule by its preset and length)."""
    if not text:
        return "`STAGE0_SCHEDULES`"
    arg = _stage0_arg(text)
    if isinstance(arg, dict):
        extra = ", ".join(f"{k} {v}" for k, v in arg.items() if k in ("lambda_anchor", "gaussians_per_observed_pixel"))
        return f"`{arg.get('preset', 'full')}` compressed to {arg.get('iterations', '?')} iterations" + (f" ({extra})" if extra else "")
    return f"`{arg}`"


def update_docs(table: str, small: bool, geometry: str = "oracle") -> None:
    """Replace the page's section of this run size and geometry with ``table``."""
    start, end = MARKS[(small, geometry)]
    text = DOCS_PAGE.read_text()
    if start not in text or end not in text:
        raise SystemExit(f"{DOCS_PAGE} has no benchmark markers {start} ... {end}")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    DOCS_PAGE.write_text(head + start + "\n" + table + end + tail)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--small", action="store_true", help="CPU smoke run: tiny scenes, each effect once at high strength, 12 null scenes")
    p.add_argument("--out", default="outputs/discovery_benchmark")
    p.add_argument("--device", default="cpu")
    p.add_argument("--geometry", choices=["oracle", "stage0"], default="oracle",
                   help="oracle: the physics starts from the true body (positions fitted for tiny scenes, fixed for full); "
                        "stage0: from images, stage 0 + continuum per scene, positions held still")
    p.add_argument("--stage0", default=None,
                   help="stage-0 schedule with --geometry stage0: 'tiny', 'full' or JSON of Stage0Schedule fields "
                        "(default: toolkit.discovery.from_images.STAGE0_SCHEDULES of the scene size)")
    p.add_argument("--stage0-device", default=None,
                   help="device of stage 0 and the continuum with --geometry stage0 (default: --device); e.g. cuda with "
                        "--device cpu: the images' Gaussians on the GPU, the ~400-particle physics on the CPU cores")
    p.add_argument("--stage0-seed", type=int, default=0,
                   help="stage 0's seed with --geometry stage0 (its initial Gaussians, frame order and batches); another "
                        "seed is another run of the same scenes, for decisions measured over several runs "
                        "(benchmarks/discovery_runs.py); one OUT folder holds one seed")
    p.add_argument("--cameras", type=int, nargs="+", default=None,
                   help="fitting cameras with --geometry stage0: 0-based indices of the scene's cameras (default the sparse "
                        "three, 1 5 9); the others are held out and judge the candidates. E.g. 1 5 9 3: what one more "
                        "camera changes (benchmarks/visual_hull.py says which carves the most)")
    p.add_argument("--levels", nargs="+", default=["medium", "high"])
    p.add_argument("--materials", nargs="+", default=["neo_hookean", "plasticine"])
    p.add_argument("--throws", nargs="+", default=["slide", "toss"])
    p.add_argument("--effects", nargs="+", default=None)
    p.add_argument("--combos", choices=["paired", "cross"], default="paired",
                   help="material/throw combinations per effect and level (paired: 2, cross: 4)")
    p.add_argument("--null", type=int, default=None, help="null scenes (default 20, --small 12)")
    p.add_argument("--top-k", type=int, default=4)
    p.add_argument("--calibrate", action="store_true", help="calibrate the thresholds on this run's null scenes (they run first)")
    p.add_argument("--thresholds", default=None, help="JSON thresholds to use (default: the shipped ones)")
    p.add_argument("--shard", default="0/1", help="i/n: run every n-th scene starting at i")
    p.add_argument("--report-only", action="store_true", help="only merge OUT/results*.jsonl and write the tables")
    p.add_argument("--null-only", action="store_true",
                   help="run only the null scenes (first step of a sharded run; then --calibrate writes OUT/thresholds.json)")
    p.add_argument("--no-reports", action="store_true", help="skip the per-scene HTML reports")
    p.add_argument("--update-docs", action="store_true", help="write the table into docs/tutorials/discovery.md")
    p.add_argument("--time-budget", type=float, default=None,
                   help="seconds after which no new scene is started (rerun to continue: finished scenes are kept)")
    args = p.parse_args(argv)
    for name in ("device", "stage0_device"):
        value = getattr(args, name)
        if value is not None and not re.fullmatch(r"cpu|cuda(:\d+)?", value):
            p.error(f"--{name.replace('_', '-')} must be cpu, cuda or cuda:N; got {value!r}")
    if args.cameras is not None:
        if args.geometry != "stage0":
            p.error("--cameras chooses stage 0's fitting cameras: use it with --geometry stage0")
        from toolkit.discovery.hidden import SIZES

        n_cams = SIZES["tiny" if args.small else "full"]["scene"]["n_cameras"]
        if len(set(args.cameras)) != len(args.cameras) or len(args.cameras) < 2 or not all(0 <= c < n_cams for c in args.cameras):
            p.error(f"--cameras takes two or more distinct 0-based camera indices, got {args.cameras}; the scenes have "
                    f"{n_cams} cameras (0-{n_cams - 1})")
    if args.null is None:
        args.null = 12 if args.small else 20
    logging.basicConfig(level=logging.WARNING)
    for name in ("pytorch_lightning", "lightning", "lightning.pytorch"):
        logging.getLogger(name).setLevel(logging.WARNING)
    import torch

    if not args.device.startswith("cuda"):
        torch.set_num_threads(1)  # the CPU smoke run shares its machine
    from toolkit.discovery.calibration import DEFAULT_THRESHOLDS, Thresholds, calibrate, null_statistics

    t_start = time.time()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # a sharded run's hidden scenes use the thresholds its null step calibrated (OUT/thresholds.json)
    if args.thresholds:
        thresholds = Thresholds.load(args.thresholds)
    elif (out / "thresholds.json").is_file():
        thresholds = Thresholds.load(out / "thresholds.json")
    else:
        thresholds = DEFAULT_THRESHOLDS
    try:
        i, n = (int(x) for x in args.shard.split("/"))
        if not 0 <= i < n:
            raise ValueError
    except ValueError:
        p.error(f"--shard must be I/N with 0 <= I < N, such as 0/4; got {args.shard!r}")
    results_file = out / (f"results_{i}of{n}.jsonl" if n > 1 else "results.jsonl")
    suite = build_suite(args)
    done = {}
    for f, r in iter_records(out):
        seed = r.get("stage0_seed")
        if not args.report_only and seed is not None and args.geometry == "stage0" and seed != args.stage0_seed:
            p.error(f"{f}: scene {r['scene']} ran with --stage0-seed {seed}, not {args.stage0_seed}; "
                    "give each seed its own --out")
        done[r["scene"]] = r
    if not args.report_only:
        mine = [hs for k, hs in enumerate(sorted(suite, key=lambda h: h.effect != "none")) if k % n == i]
        nulls = [hs for hs in mine if hs.effect == "none"]
        others = [hs for hs in mine if hs.effect != "none"]
        for phase, scenes in (("null", nulls), ("hidden", [] if args.null_only else others)):
            if phase == "hidden" and args.calibrate:
                stats = [null_statistics({"validation": done[h.name]["validation"]}) for h in suite
                         if h.effect == "none" and h.name in done]
                if stats:
                    thresholds = calibrate(stats, source=f"calibrated on {len(stats)} null scenes of {out.name}")
                    thresholds.save(out / "thresholds.json")
                    print(json.dumps({"calibrated_thresholds": thresholds.to_dict()}), flush=True)
            for hs in scenes:
                if hs.name in done:
                    continue
                if args.time_budget is not None and time.time() - t_start > args.time_budget:
                    print(json.dumps({"stopped": "time budget reached", "remaining": [h.name for h in scenes if h.name not in done]}),
                          flush=True)
                    break
                try:
                    rec = run_scene(hs, args, thresholds)
                except Exception as exc:  # a failing scene is reported, not fatal
                    rec = {"scene": hs.name, "effect": hs.effect, "error": f"{type(exc).__name__}: {exc}"}
                    print(json.dumps(rec), flush=True)
                    continue
                rec["thresholds_used"] = thresholds.to_dict()
                done[hs.name] = rec
                with results_file.open("a") as fh:
                    fh.write(json.dumps(rec) + "\n")
                print(json.dumps({k: rec[k] for k in ("scene", "expected", "decision", "correct", "indistinguishable", "top3",
                                                      "cd_before", "cd_after", "cd_shrink", "strengths", "truth_strengths",
                                                      "seconds")}), flush=True)
    names = {h.name for h in suite}
    records = [r for name, r in done.items() if name in names and "error" not in r]
    if args.calibrate and not args.thresholds:
        stats = [null_statistics({"validation": done[h.name]["validation"]}) for h in suite
                 if h.effect == "none" and h.name in done and "error" not in done[h.name]]
        if stats:
            thresholds = calibrate(stats, source=f"calibrated on {len(stats)} null scenes of {out.name}")
            thresholds.save(out / "thresholds.json")
    if not records:
        return 0
    # decisions are re-derived with the final thresholds (the stored statistics do not depend on them)
    records = redecide(records, thresholds)
    summary = summarize(records, thresholds)
    title = "CPU smoke run (`--small`, tiny scenes)" if args.small else _full_size_title(args)
    if args.geometry == "stage0":
        title += f", from images (stage-0 geometry {_stage0_label(args.stage0)}, positions held still)"
    table = markdown(summary, title)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    (out / "discovery_benchmark.md").write_text(table)
    print(json.dumps({"summary": summary}), flush=True)
    print(table)
    if args.update_docs:
        update_docs(table, args.small, args.geometry)
    return 0


def _full_size_title(args) -> str:
    """The table's title for full-size scenes, naming where stage 0 and the fits ran (not known to
    ``--report-only``, which tabulates records made elsewhere)."""
    if args.report_only:
        return "Full-size scenes"
    fits = "GPU" if str(args.device).startswith("cuda") else "CPU"
    stage0 = args.stage0_device or args.device
    where = f"{fits} run" if str(stage0) == str(args.device) or args.geometry != "stage0" else \
        f"{fits} fits, stage 0 on {'GPU' if str(stage0).startswith('cuda') else 'CPU'}"
    return f"{where} (full-size scenes)"


if __name__ == "__main__":
    sys.exit(main())

"""``projo4d benchmark``: strategies x scenes (x camera counts), in parallel, resumable, tabulated.

Examples::

    # a generated suite, the paper's three strategies, 3 views, every visible GPU
    projo4d generate suite --out suites/s0 --families neo_hookean sand --per-family 3 --size full
    projo4d benchmark --suite suites/s0 --out bench/s0 --strategies sequential joint progressive

    # the benchmark writes the suite itself (one generation job per scene, in parallel)
    projo4d benchmark --suite suites/s0 --generate --families neo_hookean sand --per-family 3 --out bench/s0

    # chunks of at most 9 minutes (rerun the same command until it prints "complete": true)
    projo4d benchmark --suite suites/s0 --out bench/s0 --time-limit 540 --jobs-per-gpu 2

    # a public dataset on disk, the camera-count ablation (Table 8)
    projo4d benchmark --scenes data/pacnerf/elastic/* --material neo_hookean --dataset pacnerf --cameras 1 2 3 10

    # every scene also as two perturbed variants (own rows in the tables)
    projo4d benchmark --suite suites/s0 --out bench/s0v --variants noisy='{"mask_noise": 0.2, "gamma": 1.2}' \
        miscalibrated='{"calibration_deg": 0.5, "calibration_m": 0.005}'

    # tables (Markdown + JSON) and figures again from what is on disk
    projo4d benchmark --out bench/s0 --tables-only

Progress is printed as JSON lines. Exit status: 0 when every job is done (failed ones are
listed in the tables), 3 when the time limit stopped it first (rerun to continue), 2 for bad
arguments.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from toolkit.commands.arguments import add_refine_grid_argument, json_arg

__all__ = ["configure", "run", "spec_from_args"]


def _strategy_option(text: str) -> tuple[str, dict]:
    label, sep, value = text.partition("=")
    if not sep or not label:
        raise argparse.ArgumentTypeError(f"expected LABEL=JSON such as cyclic='{{\"cycles\": 2}}', got {text!r}")
    opts = json_arg(value)
    if not isinstance(opts, dict):
        raise argparse.ArgumentTypeError(f"the options of {label} must be a JSON object, got {value!r}")
    return label, opts


def _variant(text: str) -> tuple[str, dict]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=JSON such as noisy='{{\"mask_noise\": 0.2}}', got {text!r}")
    fields = json_arg(value)
    if not isinstance(fields, dict):
        raise argparse.ArgumentTypeError(f"the variant {name} must be a JSON object of VariantSpec fields, got {value!r}")
    return name.strip(), fields


def _gpus(text: str) -> list[str]:
    """``--gpus``: ids ``"0,2"`` (a trailing comma makes one id: ``"3,"`` is GPU 3 alone, as in
    Lightning's ``devices``) or a count ``"4"`` (GPUs 0-3)."""
    text = text.strip()
    if text.isdigit() and "," not in text:
        return [str(i) for i in range(int(text))]
    return [g.strip() for g in text.split(",") if g.strip()]


def configure(parser: argparse.ArgumentParser) -> None:
    from toolkit.synthetic.suite import SHAPE_SETS

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = __doc__.split("Examples::", 1)[1]
    src = parser.add_argument_group("scenes")
    src.add_argument("--suite", type=Path, help="a generated suite (suite.json; `projo4d generate suite`)")
    src.add_argument("--generate", action="store_true",
                     help="write the suite's missing scenes first (one job per scene; with --families, --per-family)")
    src.add_argument("--scenes", nargs="+", type=Path, metavar="DIR", help="scene folders of a dataset on disk")
    src.add_argument("--families", nargs="+", metavar="MATERIAL", help="suite families to use (or to generate)")
    src.add_argument("--per-family", type=int, help="scenes per family (to generate, or at most this many of the suite)")
    src.add_argument("--only", nargs="+", metavar="FAMILY/INDEX",
                     help="of those scenes, only these (e.g. sand/002 neo_hookean/003): a later round adds scenes "
                          "to a suite without redoing the rest")
    src.add_argument("--suite-size", choices=["small", "full"], help="size preset of generated scenes (default: --size)")
    src.add_argument("--suite-seed", type=int, default=0, help="seed of a generated suite (default 0)")
    src.add_argument("--suite-overrides", type=json_arg, help="JSON SceneSpec fields for every generated scene")
    src.add_argument("--shape-set", choices=list(SHAPE_SETS), default="pac_nerf",
                     help="shapes of generated scenes: pac_nerf (default, a random shape each) or spring_gaus "
                          f"({', '.join(SHAPE_SETS['spring_gaus'])} in turn)")
    src.add_argument("--material", help="material of --scenes (default: each scene's recorded ground truth)")
    src.add_argument("--dataset", help="config prefix: the material's configs/<dataset>_*.yaml (default synthetic for "
                                       "suites, pacnerf for --scenes)")
    src.add_argument("--config", type=Path, help="one YAML config for every scene (RunSettings fields or run:/model:)")

    what = parser.add_argument_group("what to compare")
    what.add_argument("--strategies", nargs="+", default=["sequential", "joint", "progressive"], metavar="STRATEGY",
                      help="registered names, schedule strings or LABEL=SPEC (default: sequential joint progressive)")
    what.add_argument("--strategy-options", action="append", type=_strategy_option, default=[], metavar="LABEL=JSON",
                      help="options of one strategy, e.g. cyclic='{\"pattern\": \"XA-(S-M-A)xN\"}' (repeatable)")
    what.add_argument("--cameras", nargs="+", type=int, default=[3], metavar="N",
                      help="camera counts (default 3; several make the Table-8 ablation)")
    what.add_argument("--variants", nargs="+", type=_variant, default=[], metavar="NAME=JSON",
                      help="also run every scene as each variant, e.g. noisy='{\"mask_noise\": 0.2, \"gamma\": 1.2}' "
                           "(VariantSpec fields, see `projo4d generate variant --help`; default: none)")

    size = parser.add_argument_group("sizes and settings (config, then --size, then these)")
    size.add_argument("--size", choices=["full", "small"], default="full",
                      help="full: the configs as they are (GIC's 40k stage 0, the paper's iterations); small: CPU-sized")
    size.add_argument("--stage0", help="'full', 'tiny' or JSON of Stage0Schedule fields")
    size.add_argument("--stage0-iterations", type=int, help="GIC's stage-0 schedule scaled to this many iterations")
    size.add_argument("--geometry", choices=["stage0", "oracle"], help="oracle: ground-truth geometry instead of stage 0")
    size.add_argument("--sim", type=json_arg, help='JSON SimConfig fields, e.g. \'{"substeps": 100}\' (merged)')
    size.add_argument("--continuum", type=json_arg,
                      help='JSON ContinuumConfig fields, e.g. \'{"centre_stamp": "ellipsoid"}\' (merged)')
    size.add_argument("--model-options", type=json_arg,
                      help='JSON module options merged into every job\'s, e.g. \'{"gaussian_shape": "deformed"}\'')
    size.add_argument("--downscale", type=int, help="integer image downscale factor")
    size.add_argument("--n-train", type=int, help="training frames (default: the scene's split)")
    size.add_argument("--seed", type=int)
    add_refine_grid_argument(size, "refit a fit whose estimate depends on the grid at half the grid spacing; the table "
                                   "then reports the refined result (default: on CUDA only; see `projo4d run --help`)")
    size.add_argument("--device", choices=["auto", "cpu", "cuda"], help="device of the jobs (default auto)")
    size.add_argument("--renderer", help="renderer name (default auto)")
    size.add_argument("--stage1-iterations", type=int, help="Stage-1 iterations of every strategy that has them (100)")
    size.add_argument("--stage2-iterations", type=int, help="Stage-2 iterations (default per material: 150-350)")
    size.add_argument("--appearance-iterations", type=int,
                      help="sequential's appearance stage (GIC's Stage 3: 40000 at --size full; 0 skips it)")
    size.add_argument("--periodic-eval", type=int, default=5, metavar="N",
                      help="evaluations of future EMD/PSNR per stage during each fit, for the trajectory plots (0: off)")
    size.add_argument("--periodic-eval-points", type=int, default=1024, metavar="N",
                      help="points per cloud in the periodic EMD (default 1024; the final evaluation uses 2048)")
    size.add_argument("--eval-every", type=int, help="evaluate every N iterations instead of --periodic-eval per stage")
    size.add_argument("--checkpoint-every", type=int, default=200, help="physics iterations between checkpoints")

    run = parser.add_argument_group("execution")
    run.add_argument("--out", type=Path, help="benchmark folder (default bench/<suite or first scene name>)")
    run.add_argument("--executor", choices=["local", "ray", "slurm", "inline"], default="local",
                     help="local processes (default), Ray tasks (--ray-address), SLURM jobs through submitit "
                          "(--slurm-*) or one at a time in this process")
    run.add_argument("--workers", type=int, help="worker processes (default: GPUs x --jobs-per-gpu; 1 on a CPU); "
                                                 "with --executor slurm: jobs queued at a time (default 32)")
    run.add_argument("--gpus", type=_gpus, help="GPU ids '0,1,2' or a count '4' (GPUs 0-3); one id needs a trailing comma: "
                     "'3,' is GPU 3 alone (default: every visible GPU)")
    run.add_argument("--jobs-per-gpu", type=int, default=1, help="jobs sharing one GPU (default 1)")
    run.add_argument("--threads", type=int, help="torch threads per worker (default: CPU cores / workers)")
    run.add_argument("--ray-address", help="Ray cluster address for --executor ray ('auto' = a running cluster)")
    slurm = parser.add_argument_group("SLURM (--executor slurm; pip install 'projo4d[slurm]')")
    slurm.add_argument("--slurm-partition", help="partition of the jobs (default: the cluster's default)")
    slurm.add_argument("--slurm-time", type=int, default=240, metavar="MINUTES",
                       help="time limit of each job; a job that reaches it is requeued and resumes (default 240)")
    slurm.add_argument("--slurm-gpus", type=int, default=1, metavar="N", help="GPUs per job (0: CPU jobs; default 1)")
    slurm.add_argument("--slurm-mem-gb", type=float, metavar="GB", help="memory per job (default: the partition's)")
    slurm.add_argument("--slurm-retries", type=int, default=2, metavar="N",
                       help="requeues of a preempted or timed-out job, resubmissions of one that died (default 2)")
    slurm.add_argument("--slurm-options", type=json_arg, default=None, metavar="JSON",
                       help='more submitit parameters, e.g. \'{"slurm_account": "proj", "slurm_qos": "normal"}\'')
    slurm.add_argument("--slurm-cluster", choices=["slurm", "local"], default="slurm",
                       help="'local' runs the jobs as local processes through submitit (a dry run without SLURM)")
    run.add_argument("--time-limit", type=float, metavar="SECONDS", help="return within this many seconds (jobs resume later)")
    run.add_argument("--start-limit", type=float, metavar="SECONDS",
                     help="start no job after this many seconds; running jobs go on until they finish or --time-limit")
    run.add_argument("--grace", type=float, default=45.0, help="seconds between asking jobs to stop and the limit")
    run.add_argument("--retry-failed", action="store_true", help="run failed jobs again")
    run.add_argument("--redo-changed", action="store_true", help="delete and redo results made with other settings")
    run.add_argument("--dry-run", action="store_true", help="print the plan and time estimates only")
    run.add_argument("--tables-only", action="store_true", help="only (re)write the tables and figures of --out")
    run.add_argument("--no-figures", action="store_true", help="tables without the comparison figures")
    run.add_argument("--export", type=Path, help="copy tables.md, tables.json, progress.jsonl and results.tar.gz here")
    run.add_argument("--heartbeat", type=float, default=60.0, help="seconds between heartbeat lines")
    run.add_argument("--estimate-for", choices=["cuda", "cpu"],
                     help="price the time estimates for this device (default: the one the jobs run on)")


def spec_from_args(args: argparse.Namespace):
    """The :class:`~toolkit.benchmark.plan.BenchmarkSpec` of the command line."""
    from toolkit.benchmark.plan import (
        BenchmarkError,
        BenchmarkSpec,
        parse_strategy,
        scaled_stage0,
    )
    from toolkit.benchmark.scenes import only_scenes, scenes_from_dirs, scenes_from_suite, scenes_to_generate

    if bool(args.suite) == bool(args.scenes):
        raise BenchmarkError("give either --suite DIR or --scenes DIR [DIR ...]")
    if args.scenes:
        scenes = scenes_from_dirs(args.scenes, args.material)
        dataset = args.dataset or "pacnerf"
    elif args.generate:
        if not args.families or not args.per_family:
            raise BenchmarkError("--generate needs --families and --per-family")
        device = "cpu" if args.device == "cpu" else _generation_device(args)
        scenes = scenes_to_generate(args.suite, args.families, args.per_family, args.suite_seed, args.suite_size or args.size,
                                    device, args.suite_overrides, shape_set=args.shape_set)
        dataset = args.dataset or "synthetic"
    else:
        scenes = scenes_from_suite(args.suite, args.families, args.per_family)
        dataset = args.dataset or "synthetic"
    if args.only:
        scenes = only_scenes(scenes, args.only)
    options = dict(args.strategy_options)
    strategies = [parse_strategy(s) for s in args.strategies]
    for st in strategies:
        st.options = dict(options.pop(st.label, {}))
    if options:
        raise BenchmarkError(f"--strategy-options for unknown strategies {sorted(options)}; strategies: "
                             f"{[s.label for s in strategies]}")
    if args.model_options is not None:  # checked here, before any scene is generated or fitted
        from toolkit.run_config import check_model_options

        check_model_options(args.model_options)
    if args.continuum is not None:
        from toolkit.scene.continuum import ContinuumConfig

        try:
            ContinuumConfig.from_dict(args.continuum)
        except (TypeError, ValueError) as err:
            raise BenchmarkError(f"--continuum {json.dumps(args.continuum)}: {err}") from None
    if args.refine_iterations is not None:
        from toolkit.run_validation import check_refine_iterations

        try:
            check_refine_iterations(args.refine_iterations, "--refine-iterations")
        except ValueError as err:
            raise BenchmarkError(str(err)) from None
    overrides = {}
    for key in ("geometry", "sim", "continuum", "model_options", "downscale", "n_train", "seed", "device", "renderer",
                "refine_grid", "refine_iterations"):
        v = getattr(args, key)
        if v is not None:
            overrides[key] = v
    if args.stage0 and args.stage0_iterations:
        raise BenchmarkError("give --stage0 or --stage0-iterations, not both")
    if args.stage0:
        overrides["stage0"] = args.stage0 if args.stage0 in ("full", "tiny") else json_arg(args.stage0)
    elif args.stage0_iterations:
        overrides["stage0"] = scaled_stage0(args.stage0_iterations)
    iterations = {k: getattr(args, k) for k in ("stage1_iterations", "stage2_iterations", "appearance_iterations")
                  if getattr(args, k) is not None}
    if args.eval_every:
        periodic = {"every_n_steps": args.eval_every, "emd_points": args.periodic_eval_points}
    elif args.periodic_eval and args.periodic_eval > 0:
        periodic = {"per_stage": args.periodic_eval, "emd_points": args.periodic_eval_points}
    else:
        periodic = None
    variants = dict(args.variants)
    if len(variants) != len(args.variants):
        raise BenchmarkError(f"--variants names must be unique, got {[n for n, _ in args.variants]}")
    return BenchmarkSpec(scenes=scenes, strategies=strategies, cameras=list(args.cameras), size=args.size, dataset=dataset,
                         config=str(args.config) if args.config else None, overrides=overrides, iterations=iterations,
                         periodic_eval=periodic, checkpoint_every=args.checkpoint_every, variants=variants)


def _generation_device(args: argparse.Namespace) -> str:
    """Warp device for generation jobs as a worker sees it: its own GPU is ``cuda:0``."""
    if args.executor == "inline":
        import warp as wp

        wp.init()
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if args.executor == "slurm":  # the jobs run on the cluster's nodes, each with its own GPU(s)
        return "cuda:0" if args.slurm_gpus > 0 else "cpu"
    from toolkit.benchmark.runner import _visible_gpus

    return "cuda:0" if (args.gpus or _visible_gpus()) else "cpu"


def _default_out(args: argparse.Namespace) -> Path:
    if args.out:
        return args.out
    name = args.suite.name if args.suite else (args.scenes[0].name if args.scenes else "benchmark")
    return Path("bench") / name


def run(args: argparse.Namespace) -> int:
    from toolkit.benchmark.plan import BenchmarkError

    if args.tables_only:
        return _tables_only(args)
    try:
        spec = spec_from_args(args)
        from toolkit.benchmark.runner import run_benchmark

        result = run_benchmark(spec, _default_out(args), executor=args.executor, workers=args.workers, gpus=args.gpus,
                               jobs_per_gpu=args.jobs_per_gpu, threads=args.threads, ray_address=args.ray_address,
                               time_limit=args.time_limit, grace=args.grace, retry_failed=args.retry_failed,
                               redo_changed=args.redo_changed, dry_run=args.dry_run,
                               export=str(args.export) if args.export else None, figures=not args.no_figures,
                               heartbeat=args.heartbeat, estimate_for=args.estimate_for, slurm=_slurm_args(args),
                               start_limit=args.start_limit)
    except BenchmarkError as err:
        raise SystemExit(f"projo4d benchmark: {err}") from None
    return 0 if result["complete"] or args.dry_run else 3


def _slurm_args(args: argparse.Namespace) -> dict:
    """:class:`~toolkit.benchmark.slurm.SubmititExecutor` arguments of the ``--slurm-*`` flags."""
    out = {"cluster": args.slurm_cluster, "time_min": args.slurm_time, "gpus_per_job": args.slurm_gpus,
           "max_retries": args.slurm_retries, "partition": args.slurm_partition, "mem_gb": args.slurm_mem_gb,
           "options": args.slurm_options}
    if args.workers:
        out["max_jobs"] = args.workers
    return out


def _tables_only(args: argparse.Namespace) -> int:
    from toolkit.benchmark.plots import write_figures
    from toolkit.benchmark.tables import collect_records, write_tables

    out = _default_out(args)
    meta_path = out / "benchmark.json"
    if not meta_path.is_file():
        raise SystemExit(f"projo4d benchmark: {meta_path} does not exist (run the benchmark first)")
    spec = json.loads(meta_path.read_text()).get("spec", {})
    strategies = [s["label"] for s in spec.get("strategies", [])]
    try:
        from toolkit.benchmark.plan import BenchmarkSpec, plan_benchmark
        from toolkit.benchmark.runner import _settings_summary

        full = BenchmarkSpec.from_dict(spec)
        settings = _settings_summary(full, [j.to_dict() for j in plan_benchmark(full, out)])
    except Exception:  # noqa: BLE001 - the scenes moved: the spec's own summary
        settings = {"size": spec.get("size"), "cameras": spec.get("cameras"), "overrides": spec.get("overrides"),
                    "iteration overrides": spec.get("iterations"), "periodic evaluation": spec.get("periodic_eval")}
    md, js, tables = write_tables(out, strategies=strategies, settings=settings)
    if not args.no_figures:
        records, _ = collect_records(out)
        write_figures(out, [r for r in records if not r.get("variant")], strategies=strategies)
    if args.export:
        from toolkit.benchmark.runner import _Events, _export

        _export(out.resolve(), args.export, _Events(None))
    print(json.dumps({"event": "tables", "markdown": str(md), "json": str(js),
                      "rows": sum(len(t["rows"]) for t in tables["tables"])}))
    return 0

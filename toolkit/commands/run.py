"""``projo4d run``: the whole pipeline for one scene (stage 0 -> continuum -> strategy -> prediction
-> metrics -> report). Rerunning the same command resumes where it stopped.

Examples::

    projo4d run scenes/torus --out runs/torus --material neo_hookean --curriculum progressive
    projo4d run scenes/sand0 --out runs/sand0 --material sand --curriculum sequential --stage0 tiny --device cpu
    projo4d run --config configs/pacnerf_sand.yaml --scene data/pacnerf/sand/0 --out runs/sand0
"""

from __future__ import annotations

import argparse
from pathlib import Path

from toolkit.commands.arguments import add_refine_grid_argument, json_arg
from toolkit.run_validation import SettingsError

__all__ = ["configure", "run"]


def _key_value(text: str) -> tuple[str, float]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    k, v = text.split("=", 1)
    try:
        return k.strip(), float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{k}: {v!r} is not a number") from None


def _threads_arg(text: str) -> int:
    from toolkit.threads import ThreadSettingError, parse_count

    try:
        return parse_count(text, "--threads")
    except ThreadSettingError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def configure(parser: argparse.ArgumentParser) -> None:
    from toolkit.run_settings import RunSettings

    d = {name: f.default for name, f in RunSettings.__dataclass_fields__.items()}  # shown as "(default: ...)"
    parser.add_argument("scene", nargs="?", help="scene folder (PAC-NeRF, Spring-Gaus, Vid2Sim GSO or generated)")
    parser.add_argument("--config", type=Path,
                        help="YAML file: RunSettings fields, or the run:/model:/trainer: sections of configs/ "
                             "(unknown keys are errors; flags given here override it)")
    parser.add_argument("--out", help="run folder (default: the config's run.out or trainer.default_root_dir, "
                                      "else runs/<scene name>)")
    parser.add_argument("--material", help=f"registered material (default: {d['material']})")
    parser.add_argument("--material-options", type=json_arg,
                        help='JSON options of the material, e.g. \'{"yield_rule": "pacnerf"}\' (default: none)')
    parser.add_argument("--param", action="append", type=_key_value, default=[],
                        help="starting guess NAME=VALUE, repeatable (default: the material's defaults)")
    parser.add_argument("--curriculum", help=f"strategy name, schedule string or package.module.Class "
                                             f"(default: {d['curriculum']})")
    parser.add_argument("--curriculum-options", type=json_arg, help="JSON options of a named strategy (default: none)")
    parser.add_argument("--cameras", help=f"fitting cameras: 'sparse' (1-based 2, 6, 10), 'all' or comma-separated "
                                          f"0-based indices (default: {d['cameras']})")
    parser.add_argument("--n-train", type=int, metavar="N",
                        help="training frames [0, N) (default: the scene's recorded split, else min(14, frames - 1))")
    parser.add_argument("--downscale", type=int, metavar="K",
                        help=f"integer image downscale factor (default: {d['downscale']})")
    parser.add_argument("--stage0", help=f"'full' (GIC, 40k iterations), 'tiny' or JSON of Stage0Schedule fields "
                                         f"(default: {d['stage0']})")
    parser.add_argument("--stage0-iterations", type=int, metavar="N",
                        help="GIC's stage-0 schedule with every iteration count scaled to N iterations in all "
                             "(Stage0Schedule.compressed; instead of --stage0; default: the --stage0 schedule)")
    parser.add_argument("--geometry", choices=["stage0", "oracle"],
                        help=f"where the particles come from: stage 0 (the method) or the ground truth "
                             f"(default: {d['geometry']})")
    parser.add_argument("--sim", type=json_arg,
                        help='JSON SimConfig fields, e.g. \'{"dx": 0.02, "substeps": 100}\' (default: SimConfig defaults)')
    parser.add_argument("--continuum", type=json_arg,
                        help='JSON ContinuumConfig fields, e.g. \'{"centre_stamp": "ellipsoid", "carve_depth": "opaque"}\' '
                             "(default: GIC's procedure on a lattice at sim.dx / 2)")
    parser.add_argument("--device", help=f"auto, cpu, cuda or cuda:N (default: {d['device']})")
    add_refine_grid_argument(parser, "when the estimate depends on the grid (the grid check fails, or a grid of half the "
                             "spacing moves a material parameter by more than its standard deviation), fit again at that "
                             "spacing in OUT/refined, starting from the estimate (default: on CUDA only, where it costs "
                             "1.4-3.4x the physics stage, more the fuller the card; about 8x on a CPU)")
    parser.add_argument("--seed", type=int, help=f"seed of stage 0 and of the batch sampling (default: {d['seed']})")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out with the settings it recorded (flags given must agree)")
    parser.add_argument("--overwrite", action="store_true", help="replace the run in --out instead of resuming it")
    parser.add_argument("--threads", type=_threads_arg,
                        help="CPU threads of this run (torch, OpenMP, BLAS), on CPU and CUDA alike (default: "
                             "$PROJO4D_THREADS, else the cores of this process's affinity mask divided by "
                             "$PROJO4D_CONCURRENT_RUNS, at most 8 on CUDA and 1 on CPU). Starting N runs on one machine yourself: "
                             "give --threads CORES/N or export PROJO4D_CONCURRENT_RUNS=N")


def settings_from_sections(cfg: dict, path) -> dict:
    """RunSettings fields from a config in the ``run:`` / ``model:`` / ``trainer:`` layout of ``configs/``
    (see :mod:`toolkit.run_config`: every key is carried or refused, none is dropped)."""
    from toolkit.run_config import settings_from_sections as from_sections

    return from_sections(cfg, path)


def settings_from_args(args: argparse.Namespace, command: str = "run"):
    """The :class:`~toolkit.run_settings.RunSettings` of ``projo4d run`` (or ``stage0``, which takes the
    same arguments: ``command`` names it in messages): the config file, then the flags over it."""
    from toolkit.run_settings import RunSettings

    base: dict = {}
    if args.config:
        import yaml

        if not args.config.is_file():
            raise SystemExit(f"projo4d {command}: config file {args.config} does not exist")
        base = yaml.safe_load(args.config.read_text()) or {}
        if not isinstance(base, dict):
            raise SystemExit(f"projo4d {command}: {args.config} must hold a mapping of RunSettings fields")
        if {"model", "run", "trainer"} & set(base):
            base = settings_from_sections(base, args.config)
        unknown = sorted(set(base) - set(RunSettings.__dataclass_fields__))
        if unknown:  # the flat layout: RunSettings fields at the top
            raise SettingsError(f"{args.config}: {unknown[0]}", base[unknown[0]],
                                f"unknown field; valid: {', '.join(sorted(RunSettings.__dataclass_fields__))} "
                                "(or the run:/model:/trainer: sections of configs/)")
    over = {
        "scene": args.scene, "out": args.out, "material": args.material, "material_options": args.material_options,
        "curriculum": args.curriculum, "curriculum_options": args.curriculum_options, "n_train": args.n_train,
        "downscale": args.downscale, "geometry": args.geometry, "sim": args.sim, "device": args.device, "seed": args.seed,
        "continuum": getattr(args, "continuum", None),
        "threads": args.threads, "refine_grid": getattr(args, "refine_grid", None),
        "refine_iterations": getattr(args, "refine_iterations", None),
    }
    if args.cameras:
        over["cameras"] = _cameras_arg(args.cameras)
    if args.stage0 and getattr(args, "stage0_iterations", None):
        raise SettingsError("--stage0-iterations", args.stage0_iterations, "give --stage0 or --stage0-iterations, not both")
    if args.stage0:
        over["stage0"] = _stage0_arg(args.stage0)
    elif getattr(args, "stage0_iterations", None) is not None:
        from toolkit.scene.stage0 import compressed_settings

        try:
            over["stage0"] = compressed_settings(args.stage0_iterations)
        except ValueError:
            raise SettingsError("--stage0-iterations", args.stage0_iterations, "an integer >= 100") from None
    if args.param:
        over["initial_params"] = {**(base.get("initial_params") or {}), **dict(args.param)}
    if getattr(args, "resume", False):
        base = {**_recorded(args.out), **base}
    merged = {**base, **{k: v for k, v in over.items() if v is not None}}
    if not merged.get("scene"):
        raise SettingsError("scene", None, "give a scene folder (argument, 'scene:' in --config, or --resume --out RUN)")
    merged.setdefault("out", str(Path("runs") / Path(merged["scene"]).name))
    return RunSettings(**merged)


def _cameras_arg(text: str):
    if text in ("sparse", "all"):
        return text
    try:
        return [int(c) for c in text.split(",")]
    except ValueError:
        raise SettingsError("cameras", text, "expected 'sparse', 'all' or comma-separated 0-based indices") from None


def _stage0_arg(text: str):
    if not text.lstrip().startswith("{"):
        return text  # a preset name; validation lists the valid ones
    try:
        return json_arg(text)
    except argparse.ArgumentTypeError as err:
        raise SettingsError("stage0", text, str(err)) from None


def _recorded(out) -> dict:
    """The settings a run folder recorded (for --resume)."""
    from toolkit.run_folder import recorded_settings

    if not out:
        raise SettingsError("out", out, "--resume needs the run folder: --resume --out RUN")
    recorded = recorded_settings(out)
    if recorded is None:
        raise SettingsError("out", out, "there is no run to resume in this folder (no readable settings.json)")
    return recorded


def run(args: argparse.Namespace) -> int:
    if args.resume and args.overwrite:
        raise SettingsError("--resume/--overwrite", True, "give one of them, not both")
    mode = "resume" if args.resume else "overwrite" if args.overwrite else "auto"
    settings = settings_from_args(args)
    settings.check_fields()  # a typo is reported before torch and Lightning load (seconds)
    from toolkit.pipeline import format_summary, run_pipeline

    summary = run_pipeline(settings, mode=mode)
    print(format_summary(summary))
    return 0

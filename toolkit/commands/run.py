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

from toolkit.commands.arguments import json_arg
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
    parser.add_argument("scene", nargs="?", help="scene folder (PAC-NeRF, Spring-Gaus, Vid2Sim GSO or generated)")
    parser.add_argument("--config", type=Path, help="YAML file with RunSettings fields (command-line flags override it)")
    parser.add_argument("--out", help="run folder (default runs/<scene name>)")
    parser.add_argument("--material", help="registered material (default neo_hookean)")
    parser.add_argument("--material-options", type=json_arg, help='JSON, e.g. \'{"yield_rule": "pacnerf"}\'')
    parser.add_argument("--param", action="append", type=_key_value, default=[], help="starting guess NAME=VALUE (repeatable)")
    parser.add_argument("--curriculum", help="strategy name or schedule string (default progressive)")
    parser.add_argument("--curriculum-options", type=json_arg, help='JSON options of a named strategy')
    parser.add_argument("--cameras", help="'sparse', 'all' or comma-separated 0-based indices")
    parser.add_argument("--n-train", type=int)
    parser.add_argument("--downscale", type=int)
    parser.add_argument("--stage0", help="'full', 'tiny' or JSON of Stage0Schedule fields")
    parser.add_argument("--geometry", choices=["stage0", "oracle"])
    parser.add_argument("--sim", type=json_arg, help='JSON SimConfig fields, e.g. \'{"dx": 0.02, "substeps": 100}\'')
    parser.add_argument("--device", help="auto, cpu or cuda")
    parser.add_argument("--seed", type=int)
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out with the settings it recorded (flags given must agree)")
    parser.add_argument("--overwrite", action="store_true", help="replace the run in --out instead of resuming it")
    parser.add_argument("--threads", type=_threads_arg,
                        help="CPU threads of this run (torch, OpenMP, BLAS), on CPU and CUDA alike (default: "
                             "$PROJO4D_THREADS, else the cores of this process's affinity mask divided by "
                             "$PROJO4D_CONCURRENT_RUNS, at most 8 on CUDA and 1 on CPU). Starting N runs on one machine yourself: "
                             "give --threads CORES/N or export PROJO4D_CONCURRENT_RUNS=N")


#: model-section keys (InversePhysicsModule arguments) that RunSettings carries
_MODEL_KEYS = ("material", "material_options", "initial_params", "optimize_params", "curriculum", "sim", "lambda_geometry",
               "learning_rates", "renderer", "seed", "optimize_gravity")


def settings_from_sections(cfg: dict, path) -> dict:
    """RunSettings fields from a config in the ``run:`` / ``model:`` / ``trainer:`` layout of ``configs/``."""
    from toolkit.pipeline import RunSettings

    run = dict(cfg.get("run") or {})
    model = dict(cfg.get("model") or {})
    unknown_run = set(run) - set(RunSettings.__dataclass_fields__)
    if unknown_run:
        raise SystemExit(f"projo4d run: {path}: unknown run field(s) {sorted(unknown_run)}")
    out = {**run, **{k: model[k] for k in _MODEL_KEYS if k in model}}
    curriculum = out.get("curriculum")
    if isinstance(curriculum, dict):  # class_path / init_args
        out["curriculum"] = curriculum["class_path"]
        out["curriculum_options"] = dict(curriculum.get("init_args") or {})
    accel = (cfg.get("trainer") or {}).get("accelerator")
    if accel in ("cpu",) and "device" not in out:
        out["device"] = "cpu"
    return out


def settings_from_args(args: argparse.Namespace):
    from toolkit.pipeline import RunSettings

    base: dict = {}
    if args.config:
        import yaml

        if not args.config.is_file():
            raise SystemExit(f"projo4d run: config file {args.config} does not exist")
        base = yaml.safe_load(args.config.read_text()) or {}
        if not isinstance(base, dict):
            raise SystemExit(f"projo4d run: {args.config} must hold a mapping of RunSettings fields")
        if "model" in base or "run" in base:
            base = settings_from_sections(base, args.config)
        unknown = set(base) - set(RunSettings.__dataclass_fields__)
        if unknown:
            raise SystemExit(f"projo4d run: {args.config} has unknown field(s) {sorted(unknown)}; "
                             f"known: {sorted(RunSettings.__dataclass_fields__)}")
    over = {
        "scene": args.scene, "out": args.out, "material": args.material, "material_options": args.material_options,
        "curriculum": args.curriculum, "curriculum_options": args.curriculum_options, "n_train": args.n_train,
        "downscale": args.downscale, "geometry": args.geometry, "sim": args.sim, "device": args.device, "seed": args.seed,
        "threads": args.threads,
    }
    if args.cameras:
        over["cameras"] = _cameras_arg(args.cameras)
    if args.stage0:
        over["stage0"] = _stage0_arg(args.stage0)
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
    from toolkit.pipeline import format_summary, run_pipeline

    if args.resume and args.overwrite:
        raise SettingsError("--resume/--overwrite", True, "give one of them, not both")
    mode = "resume" if args.resume else "overwrite" if args.overwrite else "auto"
    summary = run_pipeline(settings_from_args(args), mode=mode)
    print(format_summary(summary))
    return 0

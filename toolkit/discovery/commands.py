"""``projo4d discover RUN_DIR [RUN_DIR ...]``: find the missing effect of a fitted run.

RUN_DIR is a pipeline run folder (``physics_input.pt`` and ``physics/checkpoints/last.ckpt``).
Writes ``RUN_DIR/discovery/`` (or ``--out``): ``discovery.json``, ``report.md``,
``report.html`` and the figures; prints the verdict.

With several run folders of the same scene (fitted with other ``--seed`` values, say), each gets
its own ``RUN_DIR/discovery/``, and the decisions are compared
(:func:`toolkit.discovery.consensus.consensus`): ``consensus.json`` and ``consensus.md`` go to
``--out`` (default: the first run's ``discovery_consensus/``). Every folder is checked before any
work, and folders of different scenes (their ``run.json`` fingerprints) are refused.
"""

from __future__ import annotations

import argparse

__all__ = ["configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                        help="run folder with physics_input.pt and physics/checkpoints/last.ckpt; several runs of one scene "
                             "are each discovered and their decisions compared")
    parser.add_argument("--out", default=None,
                        help="output folder (default: RUN_DIR/discovery; with several runs, the consensus's folder, default "
                             "the first run's discovery_consensus/)")
    parser.add_argument("--candidates", nargs="+", default=None, metavar="NAME",
                        help="candidates to consider (default: the whole library; see toolkit.discovery.candidates)")
    parser.add_argument("--top-k", type=int, default=4, help="candidates confirmed by refits (default 4)")
    parser.add_argument("--holdout-frames", type=int, default=None,
                        help="training frames held out from the confirmation refits (default: a quarter)")
    parser.add_argument("--iterations", type=int, default=8, help="Levenberg-Marquardt iterations per confirmation refit")
    parser.add_argument("--final-iterations", type=int, default=12, help="iterations of the final refit")
    parser.add_argument("--thresholds", default=None, help="JSON file of calibrated thresholds (default: the shipped ones)")
    parser.add_argument("--no-emd", action="store_true", help="skip the EMD in the before/after metrics")
    parser.add_argument("--device", default="cpu", help="torch device of the module (cpu, cuda)")


def _check_run_dir(run_dir) -> None:
    from pathlib import Path

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise SystemExit(f"projo4d discover: {run_dir} is not a folder (expected a run folder of `projo4d run`)")
    for need, hint in (("physics_input.pt", "written after stage 0"), ("physics/checkpoints/last.ckpt", "fit it first")):
        if not (run_dir / need).is_file():
            raise SystemExit(f"projo4d discover: {run_dir} has no {need} ({hint})")


def _same_scene(run_dirs) -> None:
    """Refuse run folders whose ``run.json`` records different scenes (folders without one pass)."""
    from pathlib import Path

    from toolkit.run_folder import recorded_identity

    seen = {}
    for d in run_dirs:
        rec = recorded_identity(Path(d)) or {}
        fp = rec.get("scene_fingerprint")
        if fp is not None:
            seen.setdefault(fp, (d, rec.get("scene")))
    if len(seen) > 1:
        (a, sa), (b, sb) = list(seen.values())[:2]
        raise SystemExit(f"projo4d discover: {a} and {b} are runs of different scenes ({sa} and {sb}); several run folders "
                         "must be runs of one scene (other --seed values, say)")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from toolkit.atomic import write_json, write_text
    from toolkit.discovery.calibration import Thresholds
    from toolkit.discovery.candidates import library
    from toolkit.discovery.consensus import consensus, consensus_markdown
    from toolkit.discovery.workflow import discover

    for d in args.run_dirs:
        _check_run_dir(d)
    if len(set(Path(d).resolve() for d in args.run_dirs)) < len(args.run_dirs):
        raise SystemExit("projo4d discover: a run folder is given twice")
    _same_scene(args.run_dirs)
    if args.top_k < 1:
        raise SystemExit(f"projo4d discover: --top-k must be >= 1, got {args.top_k}")
    try:
        library(args.candidates)
    except ValueError as err:
        raise SystemExit(f"projo4d discover: --candidates: {err}") from None
    thresholds = None
    if args.thresholds is not None:
        try:
            thresholds = Thresholds.load(args.thresholds)
        except (ValueError, OSError, TypeError) as err:
            raise SystemExit(f"projo4d discover: --thresholds {args.thresholds}: {err} (expected the JSON written by "
                             "benchmarks/discovery.py --calibrate)") from None

    several = len(args.run_dirs) > 1
    results, verdicts = [], []
    for run_dir in args.run_dirs:
        out = Path(args.out) if args.out and not several else Path(run_dir) / "discovery"
        result = discover(run_dir, out, candidates=args.candidates, top_k=args.top_k, holdout_frames=args.holdout_frames,
                          refit_iterations=args.iterations, final_iterations=args.final_iterations, thresholds=thresholds,
                          emd=not args.no_emd, device=args.device)
        if several:
            print(f"{run_dir}: {result.verdict}")
        else:
            print(result.verdict)
        print(f"report: {out / 'report.html'}")
        results.append(result.to_dict())
        verdicts.append(result.verdict)
    if several:
        c = consensus(results, [str(d) for d in args.run_dirs])
        out = Path(args.out) if args.out else Path(args.run_dirs[0]) / "discovery_consensus"
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "consensus.json", c.to_dict())
        write_text(out / "consensus.md", consensus_markdown(c, verdicts))
        print(c.sentence)
        print(f"consensus: {out / 'consensus.md'}")
    return 0

"""``projo4d discover RUN_DIR``: find the missing effect of a fitted run.

RUN_DIR is a pipeline run folder (``physics_input.pt`` and ``physics/checkpoints/last.ckpt``).
Writes ``RUN_DIR/discovery/`` (or ``--out``): ``discovery.json``, ``report.md``,
``report.html`` and the figures; prints the verdict.
"""

from __future__ import annotations

import argparse

__all__ = ["configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", help="run folder with physics_input.pt and physics/checkpoints/last.ckpt")
    parser.add_argument("--out", default=None, help="output folder (default: RUN_DIR/discovery)")
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


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from toolkit.discovery.calibration import Thresholds
    from toolkit.discovery.candidates import library
    from toolkit.discovery.workflow import discover

    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        raise SystemExit(f"projo4d discover: {run_dir} is not a folder (expected a run folder of `projo4d run`)")
    for need, hint in (("physics_input.pt", "written after stage 0"), ("physics/checkpoints/last.ckpt", "fit it first")):
        if not (run_dir / need).is_file():
            raise SystemExit(f"projo4d discover: {run_dir} has no {need} ({hint})")
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

    out = Path(args.out) if args.out else run_dir / "discovery"
    result = discover(args.run_dir, out, candidates=args.candidates, top_k=args.top_k, holdout_frames=args.holdout_frames,
                      refit_iterations=args.iterations, final_iterations=args.final_iterations, thresholds=thresholds,
                      emd=not args.no_emd, device=args.device)
    print(result.verdict)
    print(f"report: {out / 'report.html'}")
    return 0

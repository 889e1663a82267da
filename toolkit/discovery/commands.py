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

    from toolkit.discovery.workflow import discover

    out = Path(args.out) if args.out else Path(args.run_dir) / "discovery"
    result = discover(args.run_dir, out, candidates=args.candidates, top_k=args.top_k, holdout_frames=args.holdout_frames,
                      refit_iterations=args.iterations, final_iterations=args.final_iterations, thresholds=args.thresholds,
                      emd=not args.no_emd, device=args.device)
    print(result.verdict)
    print(f"report: {out / 'report.html'}")
    return 0

"""The ``projo4d`` command line.

Each subcommand lives in its own module exposing ``configure(parser)`` (add arguments) and
``run(args) -> int``; this file only wires them up, importing a module when its command runs so
``projo4d --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

__all__ = ["main", "COMMANDS"]

#: command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "discover": ("toolkit.discovery.commands", "find where a fitted run and the measurements disagree and name the missing effect"),
    "demo": ("toolkit.commands.demo", "run the main job on an embedded synthetic scene (no download)"),
    "fit": ("toolkit.commands.fit", "run the physics stages from a YAML config (LightningCLI; see `projo4d fit --help`)"),
    "run": ("toolkit.commands.run", "the whole pipeline for one scene: stage 0, continuum, strategy, prediction, metrics, report"),
    "generate": ("toolkit.synthetic.commands", "write synthetic scenes (PAC-NeRF layout) with honest ground truth"),
    "materials": ("toolkit.commands.info", "list materials, renderers, strategies and effects with their parameters"),
    "evaluate": ("toolkit.commands.evaluate", "re-evaluate a fitted run folder: future prediction, all metrics, report"),
    "benchmark": ("toolkit.benchmark.commands", "compare strategies over a suite of scenes, in parallel; paper-style tables"),
    "view": ("toolkit.commands.view", "show predicted and ground-truth particles over time (window, or PNG/MP4 headless)"),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``projo4d`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "fit":  # LightningCLI parses its own arguments
        from toolkit.commands import fit

        return fit.main(argv[1:])
    parser = _build_parser_for(argv)
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    module = importlib.import_module(args._module)
    return int(module.run(args) or 0)


def _build_parser_for(argv: Sequence[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="projo4d",
        description="Inverse physics from sparse multi-view video: Gaussians, MPM, progressive joint optimization.",
    )
    from toolkit import __version__

    parser.add_argument("--version", action="version", version=f"projo4d {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = argv[0] if argv else None
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name == chosen:
            importlib.import_module(module).configure(p)
    return parser


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

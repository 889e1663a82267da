"""The ``projo4d`` command line.

Each subcommand lives in its own module exposing ``configure(parser)`` (add arguments) and
``run(args) -> int``; this file only wires them up, importing a module when its command runs so
``projo4d --help`` stays fast.

Every command runs inside one error boundary (:mod:`toolkit.errors`): a mistake in the input prints
one line ``projo4d <command>: <message>`` and exits with status 2, an unexpected failure prints
one line and exits with 1, Ctrl-C exits with 130; ``--debug`` shows the traceback instead. Output
is quiet by default (:mod:`toolkit.verbosity`); ``--verbose`` shows Warp's and Lightning's
messages. Both flags are accepted anywhere on the line (``projo4d run SCENE --debug``).

Option values that start with a minus sign parse as values (``--v0 -0.5,0,0.4``,
``--cameras -1,2``): :func:`join_negative_values` writes them as ``--v0=-0.5,0,0.4`` first.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from typing import Sequence

__all__ = ["main", "COMMANDS", "GLOBAL_FLAGS", "split_global_flags", "join_negative_values"]

#: flags of every command, accepted before or after the subcommand
GLOBAL_FLAGS = {"--debug": "show the full traceback of an error", "--verbose": "show Warp's and Lightning's messages"}

#: command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "discover": ("toolkit.discovery.commands", "find where a fitted run and the measurements disagree and name the missing effect"),
    "demo": ("toolkit.commands.demo", "run the main job on an embedded synthetic scene (no download)"),
    "fit": ("toolkit.commands.fit", "run the physics stages from a YAML config (LightningCLI; see `projo4d fit --help`)"),
    "run": ("toolkit.commands.run", "the whole pipeline for one scene: stage 0, continuum, strategy, prediction, metrics, report"),
    "stage0": ("toolkit.commands.stage0", "only stage 0 (4D Gaussians) of a scene into a run folder; a later `run` reuses it"),
    "generate": ("toolkit.synthetic.commands", "write synthetic scenes (PAC-NeRF layout) with honest ground truth"),
    "materials": ("toolkit.commands.info", "list materials, renderers, strategies and effects with their parameters"),
    "evaluate": ("toolkit.commands.evaluate", "re-evaluate a fitted run folder: future prediction, all metrics, report"),
    "benchmark": ("toolkit.benchmark.commands", "compare strategies over a suite of scenes, in parallel; paper-style tables"),
    "view": ("toolkit.commands.view", "show predicted and ground-truth particles over time (browser viewer, or PNG/MP4 files)"),
    "export": ("toolkit.commands.export", "export a fitted run: refined Gaussians (3DGS PLY), per-frame PLY sequence, digital twin"),
    "simulate": ("toolkit.commands.simulate", "re-simulate a digital twin with new v0, parameters, effects or frames; render video"),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``projo4d`` console script; returns the exit status.

    A handled error (see :mod:`toolkit.errors`) is printed as one line on stderr and raised as a
    ``SystemExit`` carrying its status (2: a mistake in the input, 1: a failure, 130: interrupted),
    so ``sys.exit(main())`` exits with it and in-process callers can catch it.
    """
    from toolkit.errors import error_boundary

    argv, flags = split_global_flags(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and not argv[0].startswith("-") else ""
    if command in COMMANDS:
        from toolkit.verbosity import configure_output

        configure_output(verbose="--verbose" in flags)
    with error_boundary(command, debug="--debug" in flags):
        if command == "fit":  # LightningCLI parses its own arguments
            from toolkit.commands import fit

            return fit.main(argv[1:])
        parser = _build_parser_for(argv)
        args = parser.parse_args(join_negative_values(argv, _value_options(parser)))
        if not getattr(args, "command", None):
            parser.print_help()
            return 2
        module = importlib.import_module(args._module)
        return int(module.run(args) or 0)


def split_global_flags(argv: Sequence[str]) -> tuple[list[str], set[str]]:
    """``argv`` without the :data:`GLOBAL_FLAGS` (wherever they stand before a ``--``), and the set of those given."""
    rest: list[str] = []
    flags: set[str] = set()
    for i, arg in enumerate(argv):
        if arg == "--":
            rest.extend(argv[i:])
            break
        if arg in GLOBAL_FLAGS:
            flags.add(arg)
        else:
            rest.append(arg)
    return rest, flags


_NEGATIVE_VALUE = re.compile(r"^-[0-9.]")


def join_negative_values(argv: Sequence[str], value_options: set[str]) -> list[str]:
    """Write ``--opt -0.5,0,1`` as ``--opt=-0.5,0,1`` for the options in ``value_options``.

    argparse reads a word starting with ``-`` as an option unless it is a plain negative number,
    so ``--v0 -0.5,0,0.4`` failed with "expected one argument". Only a word starting with ``-``
    followed by a digit or ``.`` is joined, and only after an option that takes one value.
    """
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg == "--":
            out.extend(argv[i:])
            break
        if arg in value_options and i + 1 < len(argv) and _NEGATIVE_VALUE.match(argv[i + 1]):
            out.append(f"{arg}={argv[i + 1]}")
            i += 2
            continue
        out.append(arg)
        i += 1
    return out


def _value_options(parser: argparse.ArgumentParser) -> set[str]:
    """Long option strings that take exactly one value, in ``parser`` and its subparsers."""
    out: set[str] = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in set(action.choices.values()):
                out |= _value_options(sub)
        elif action.option_strings and action.nargs in (None, "?", 1):
            out.update(s for s in action.option_strings if s.startswith("--"))
    return out


class _Parser(argparse.ArgumentParser):
    """argparse, with a mistake reported on one line (no usage block) through the error boundary."""

    def error(self, message: str):  # noqa: D102
        raise SystemExit(f"{self.prog}: {message} (see `{self.prog} --help`)")


def _build_parser_for(argv: Sequence[str]) -> argparse.ArgumentParser:
    parser = _Parser(
        prog="projo4d",
        description="Inverse physics from sparse multi-view video: Gaussians, MPM, progressive joint optimization.",
        epilog="Every command also takes --debug (the traceback of an error) and --verbose (Warp's and Lightning's messages).",
    )
    from toolkit import __version__

    parser.add_argument("--version", action="version", version=f"projo4d {__version__}")
    for flag, help_text in GLOBAL_FLAGS.items():  # documented here; split_global_flags removes them before parsing
        parser.add_argument(flag, action="store_true", help=help_text)
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

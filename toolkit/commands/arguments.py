"""Argument types shared by the ``projo4d`` subcommands."""

from __future__ import annotations

import argparse
import json

__all__ = ["json_arg", "add_refine_grid_argument"]


def json_arg(text: str):
    """An argparse type: the option's value parsed as JSON (a clear error naming the text)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise argparse.ArgumentTypeError(f"not valid JSON: {text!r} ({err.msg})") from None


def add_refine_grid_argument(parser, help: str) -> None:
    """``--refine-grid`` (True), ``--refine-grid-always`` (``"always"``) and ``--no-refine-grid``
    (False) into ``args.refine_grid``, and ``--refine-iterations`` into ``args.refine_iterations``;
    None when none is given (the settings' default)."""
    parser.add_argument("--refine-grid", dest="refine_grid", action="store_const", const=True, default=None, help=help)
    parser.add_argument("--refine-grid-always", dest="refine_grid", action="store_const", const="always",
                        help="fit every run again at half the grid spacing, whatever its grid check found, on any "
                             "device (default: only a run whose estimate depends on the grid)")
    parser.add_argument("--no-refine-grid", dest="refine_grid", action="store_const", const=False,
                        help="never fit again at a finer grid (default: refit a grid-dependent estimate on CUDA only)")
    parser.add_argument("--refine-iterations", dest="refine_iterations", type=float, default=None, metavar="FRACTION",
                        help="the refit runs each stage of the curriculum for this fraction of its iterations, in "
                             "(0, 1]; it starts at the first fit's estimate (default: the settings')")

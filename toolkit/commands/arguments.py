"""Argument types shared by the ``projo4d`` subcommands."""

from __future__ import annotations

import argparse
import json

__all__ = ["json_arg"]


def json_arg(text: str):
    """An argparse type: the option's value parsed as JSON (a clear error naming the text)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise argparse.ArgumentTypeError(f"not valid JSON: {text!r} ({err.msg})") from None

"""The command-line reference, generated from the parsers at every build.

A page holding the line ``<!-- cli-reference -->`` gets, in its place, one section per
``projo4d`` command with the ``--help`` text its parser prints (``toolkit.cli`` builds the
argparse parser of each command; ``projo4d fit`` is LightningCLI, whose own ``--help`` is long:
the page shows its ``--model.*`` section, the part projo4d defines). The page is re-read at every
build, so the reference cannot drift from the code.

Unlike the API reference (static analysis), this imports ``toolkit`` and the command modules:
the docs build needs the package installed (``make docs`` installs it).
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from typing import Any

MARKER = "<!-- cli-reference -->"
WIDTH = "100"  # columns of the help text (argparse and jsonargparse read COLUMNS)


@contextlib.contextmanager
def _help_environment():
    old_columns, old_argv = os.environ.get("COLUMNS"), sys.argv
    os.environ["COLUMNS"] = WIDTH
    sys.argv = ["projo4d"]
    try:
        yield
    finally:
        sys.argv = old_argv
        if old_columns is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old_columns


def _fence(text: str) -> str:
    return "````text\n" + text.rstrip() + "\n````\n"


def fit_model_section(help_text: str) -> str:
    """The ``--model.*`` block of ``projo4d fit --help``: from the line before ``--model CONFIG``
    (the group's title, the module's description) to the next unindented line (another group)."""
    lines = help_text.splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.strip().startswith("--model CONFIG")), None)
    if start is None:
        raise RuntimeError("`projo4d fit --help` has no `--model CONFIG` option: update docs/_ext/cli_reference.py")
    end = start + 1
    while end < len(lines) and (not lines[end].strip() or lines[end].startswith(" ")):
        end += 1
    return "\n".join(lines[start - 1:end]).rstrip()


def _fit_help() -> str:
    from toolkit.commands import fit

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        fit.main(["--help"])
    return out.getvalue()


def generate() -> str:
    """Markdown: ``projo4d --help``, then one section per command."""
    from toolkit import cli

    parts = []
    with _help_environment():
        top = cli._build_parser_for([])
        parts.append("## `projo4d`\n\n" + _fence(top.format_help()))
        for name, (_module, summary) in cli.COMMANDS.items():
            parts.append(f"## `projo4d {name}`\n\n{summary[0].upper()}{summary[1:]}.\n")
            if name == "fit":
                parts.append(
                    "`projo4d fit` is a LightningCLI: besides the options below it takes every argument of "
                    "Lightning's `Trainer` as `--trainer.*`, `--config FILE` (YAML), `--print_config` and "
                    "`--ckpt_path`; `projo4d fit --help` prints them all. The model's own options "
                    "(`--model.*`, {py:class}`toolkit.physics.module.InversePhysicsModule`):\n")
                parts.append(_fence(fit_model_section(_fit_help())))
                continue
            parser = cli._build_parser_for([name])
            sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
            parts.append(_fence(sub.choices[name].format_help()))
    return "\n".join(parts)


def _source_read(app: Any, docname: str, source: list[str]) -> None:
    if MARKER in source[0]:
        source[0] = source[0].replace(MARKER, generate())


def _always_outdated(app: Any, env: Any, added: set, changed: set, removed: set) -> list[str]:
    # the page's text depends on the code, not only on its own file
    return [doc for doc in env.found_docs if doc == app.config.cli_reference_page]


def setup(app: Any) -> dict:
    app.add_config_value("cli_reference_page", "reference/cli", "env")
    app.connect("source-read", _source_read)
    app.connect("env-get-outdated", _always_outdated)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}

"""The error boundary of the ``projo4d`` commands: one line per mistake, the traceback on request.

Every command runs inside :func:`error_boundary`. What it does with an exception:

* a mistake in the input, exit status 2, one line ``projo4d <command>: <message>``:
  :class:`UserError` and every ``ValueError`` (the registries', readers' and validators'
  errors), ``OSError`` about a path (missing, unreadable, unwritable), the registries'
  ``UnknownNameError``, a ``SystemExit`` carrying a message, an argparse mistake, and
  LightningCLI's ``ArgumentError`` (``projo4d fit``);
* an interruption, exit status 130, ``projo4d <command>: interrupted ...; rerun the same command
  to resume``: ``KeyboardInterrupt`` and any exception with ``exit_code = 130``
  (:class:`toolkit.checkpointing.RunInterrupted`, raised after the checkpoint is saved);
* anything else (a bug, a simulation that blew up), exit status 1: one line with the exception's
  type and message and ``(run with --debug for the traceback)``; a GPU out-of-memory error gets a
  second line saying who holds the card's memory (:mod:`toolkit.device_memory`).

With ``--debug`` the exception propagates unchanged, so Python prints the whole traceback.

Every handled error leaves the boundary as a :class:`CommandExit` (a ``SystemExit`` whose
``code`` is the status and whose ``str()`` is the message), so the console script exits with
that status and an in-process caller (tests, notebooks) can inspect both::

    with pytest.raises(SystemExit) as exc:
        main(["run", "missing/scene"])
    assert exc.value.code == 2 and "does not exist" in str(exc.value)
"""

from __future__ import annotations

import contextlib
import sys
from typing import Iterator, TextIO

__all__ = ["UserError", "CommandExit", "error_boundary", "describe_error", "EXIT_FAILURE", "EXIT_USAGE", "EXIT_INTERRUPTED"]

#: exit status of an unexpected failure (a bug, a diverged simulation)
EXIT_FAILURE = 1
#: exit status of a mistake in the input (settings, flags, files)
EXIT_USAGE = 2
#: exit status after Ctrl-C / SIGTERM (128 + SIGINT, as shells report it)
EXIT_INTERRUPTED = 130

_DEBUG_HINT = "(run with --debug for the traceback)"
_RESUME_HINT = "rerun the same command to resume"


class UserError(ValueError):
    """A mistake in the user's input (a setting, a flag, a file): the CLI prints its message on one
    line and exits with status 2. Name the field, the value and what is valid in the message."""

    exit_code = EXIT_USAGE


class CommandExit(SystemExit):
    """How a handled error leaves :func:`error_boundary`: ``code`` is the exit status, ``str()`` the
    line that was printed (without the ``projo4d <command>:`` prefix when it had none)."""

    def __init__(self, code: int, message: str = ""):
        super().__init__(code)
        self.message = message

    def __str__(self) -> str:
        return self.message


def _first_line(err: BaseException) -> str:
    text = err.args[0] if isinstance(err, KeyError) and len(err.args) == 1 and isinstance(err.args[0], str) else str(err)
    text = text.strip()
    return text or type(err).__name__


def describe_error(err: BaseException) -> tuple[int, str]:
    """``(exit status, message)`` for an exception escaping a command (the rules of the module docstring).

    The message is the exception's own text (a mistake's message keeps all its lines, such as a
    list of invalid fields); an unexpected exception gives its type and the first line of its
    message (at most 300 characters). A ``SystemExit`` raised while a ``KeyboardInterrupt`` was
    handled (Lightning's ``sys.exit(1)`` on Ctrl-C) counts as the interruption.
    """
    code = getattr(err, "exit_code", None)
    if isinstance(err, SystemExit) and isinstance(err.__context__, KeyboardInterrupt):
        err = err.__context__  # Lightning turns Ctrl-C into sys.exit(1) while handling it
    if isinstance(err, KeyboardInterrupt) or code == EXIT_INTERRUPTED:
        detail = "" if isinstance(err, KeyboardInterrupt) else _first_line(err)
        return EXIT_INTERRUPTED, f"interrupted{f' ({detail})' if detail else ''}; {_RESUME_HINT}"
    if isinstance(err, SystemExit):
        if isinstance(err.code, str):
            return EXIT_USAGE, err.code.strip()
        return (0 if err.code is None else int(err.code)), ""
    if isinstance(code, int):
        return code, _first_line(err)
    import argparse

    if isinstance(err, argparse.ArgumentError):  # LightningCLI's parser (jsonargparse) with exit_on_error=False
        return EXIT_USAGE, f"{_first_line(err)} (see `projo4d fit --help`)" if "--help" not in str(err) else _first_line(err)
    if isinstance(err, (ValueError, OSError, KeyError)):
        from toolkit.registry import UnknownNameError

        if isinstance(err, (ValueError, UnknownNameError)) or isinstance(err, OSError) and _is_file_problem(err):
            return EXIT_USAGE, _first_line(err)
    first = _first_line(err).splitlines()[0]
    if len(first) > 300:
        first = first[:297] + "..."
    from toolkit.device_memory import oom_note

    note = oom_note(err)  # a GPU out of memory: who holds it
    return EXIT_FAILURE, f"{type(err).__name__}: {first} {_DEBUG_HINT}" + (f"\n  {note}" if note else "")


def _is_file_problem(err: OSError) -> bool:
    """Missing, unreadable or unwritable paths are the user's to fix; other OS errors are not."""
    return isinstance(err, (FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError)) or (
        getattr(err, "filename", None) is not None)


def _with_prefix(command: str, message: str) -> str:
    prefix = f"projo4d {command}".strip()
    if not message or message.startswith("projo4d"):
        return message
    return f"{prefix}: {message}"


@contextlib.contextmanager
def error_boundary(command: str, debug: bool = False, stream: TextIO | None = None) -> Iterator[None]:
    """Run a command's body; turn what escapes it into one line on ``stream`` (stderr) and a
    :class:`CommandExit` with the status of :func:`describe_error`.

    Args:
        command: the subcommand's name, used as the prefix ``projo4d <command>:``.
        debug: let every exception propagate unchanged (the full traceback).
        stream: where the line goes (default ``sys.stderr`` at the time of the error).
    """
    try:
        yield
    except CommandExit:
        raise  # already printed (a nested boundary)
    except BaseException as err:  # noqa: BLE001 - this is the boundary
        if debug or isinstance(err, (GeneratorExit,)):
            raise
        code, message = describe_error(err)
        if isinstance(err, SystemExit) and not message:
            raise  # a plain exit status (argparse --help, a command's own `return 1`)
        line = _with_prefix(command, message)
        print(line, file=stream or sys.stderr, flush=True)
        raise CommandExit(code, line) from None

"""Quiet by default: what the ``projo4d`` commands print besides their results.

:func:`configure_output` is called once per command by :mod:`toolkit.cli`. By default it hides

* Warp's ``Module ... load on device ... took ... ms`` lines and its start-up banner
  (``warp.config.log_level = warp.LOG_WARNING``; Warp's own warnings still show);
* Lightning's INFO chatter: "GPU available: ...", the "Tip: ..." advertisements, "`weights_only`
  was not set" on every checkpoint save, "Restoring states from the checkpoint path ...";
* Lightning's ``PossibleUserWarning`` (few dataloader workers, ...), LightningCLI's warnings
  that ``args`` and ``sys.argv`` were both given (``projo4d fit`` passes its own arguments), that
  no seed was given and that ``tensorboardX`` is not a dependency (``projo4d fit`` sets its own
  loggers), and torch's deprecation of ``LeafSpec`` seen through Lightning;

and leaves warnings and errors (ours and everyone's) alone. ``verbose=True`` (``projo4d
--verbose``) shows all of the above and the toolkit's own INFO log lines. The choice is also
exported as ``PROJO4D_VERBOSE=1|0`` for worker processes, which call :func:`configure_output`
with :func:`verbose_from_environment`.
"""

from __future__ import annotations

import logging
import os
import sys
import warnings

__all__ = ["configure_output", "verbose_from_environment", "THIRD_PARTY_LOGGERS"]

#: loggers whose records below WARNING are hidden unless verbose
THIRD_PARTY_LOGGERS = ("pytorch_lightning", "lightning_fabric", "lightning", "lightning_utilities", "torch", "jsonargparse")

_ENV = "PROJO4D_VERBOSE"


class _HideChatter(logging.Filter):
    """Drop third-party records below WARNING (the root handler's filter)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            return True
        name = record.name
        return not any(name == p or name.startswith(p + ".") for p in THIRD_PARTY_LOGGERS)


class _Handler(logging.StreamHandler):
    """The handler :func:`configure_output` installs: writes to the ``sys.stderr`` of the moment (so
    a redirected or captured stderr is honoured), and is told apart from other handlers so a second
    call replaces it instead of stacking another."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # noqa: D102
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it
        pass


def verbose_from_environment() -> bool:
    """The verbosity a parent ``projo4d`` process chose (``PROJO4D_VERBOSE``), default quiet."""
    return os.environ.get(_ENV, "0").strip().lower() in ("1", "true", "yes", "on")


def configure_output(verbose: bool = False) -> None:
    """Set what the current process prints besides results (see the module docstring).

    Safe to call more than once (each call replaces the previous choice).

    Args:
        verbose: show Warp's module-load lines, Lightning's INFO messages and warnings of the
            kinds listed above, and the toolkit's INFO log lines.
    """
    os.environ[_ENV] = "1" if verbose else "0"
    root = logging.getLogger()
    for h in [h for h in root.handlers if isinstance(h, _Handler)]:
        root.removeHandler(h)
    handler = _Handler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    if not verbose:
        handler.addFilter(_HideChatter())
    # Lightning adds a handler of its own (and stops propagating) only where the root has none
    root.addHandler(handler)
    root.setLevel(logging.INFO if verbose else logging.WARNING)
    for name in ("pytorch_lightning", "lightning_fabric", "lightning.pytorch", "lightning.fabric"):
        if name.split(".")[0] in sys.modules:  # imported before us: its own handler may be in place
            lg = logging.getLogger(name)
            lg.setLevel(logging.INFO if verbose else logging.WARNING)
    action = "default" if verbose else "ignore"
    warnings.filterwarnings(action, message=r"LightningCLI's args parameter is intended")
    warnings.filterwarnings(action, message=r".*does not have many workers")
    warnings.filterwarnings(action, message=r".*`training_step` returned `None`")
    warnings.filterwarnings(action, message=r"`isinstance\(treespec, LeafSpec\)` is deprecated")  # torch vs Lightning
    # LightningCLI's own defaults, before `projo4d fit` installs its loggers and seed
    warnings.filterwarnings(action, message=r"No seed found, seed set to")
    warnings.filterwarnings(action, message=r"Starting from v1\.9\.0, `tensorboardX` has been removed")
    if "lightning_fabric" in sys.modules:  # else the message filters above cover what our runs meet
        from lightning_fabric.utilities.warnings import PossibleUserWarning

        warnings.filterwarnings(action, category=PossibleUserWarning)
    _quiet_warp(not verbose)


def _quiet_warp(quiet: bool) -> None:
    try:
        import warp as wp
    except ImportError:  # pragma: no cover - warp is a dependency
        return
    if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.19: a log level
        wp.config.log_level = wp.LOG_WARNING if quiet else wp.LOG_INFO
    else:  # pragma: no cover - older Warp
        wp.config.quiet = quiet

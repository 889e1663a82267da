"""Checkpoints that survive kills: atomic saves, saves by wall time and on Ctrl-C / SIGTERM, and
resuming from the newest intact checkpoint.

* :func:`save_checkpoint` writes through a temporary file, so a checkpoint on disk is always whole.
* :class:`WallClock` says when ``every_s`` seconds of work have passed since the last save, so at
  most about that much work is lost to a kill that gives no warning (SIGKILL, power loss).
* :func:`graceful_interrupts` turns the first Ctrl-C or SIGTERM into a request that the training
  callbacks honour at the end of the current iteration (a consistent state): they save, then raise
  :class:`RunInterrupted`. A second Ctrl-C interrupts at once.
* :func:`newest_intact_checkpoint` picks the checkpoint with the most progress that loads, and sets
  aside (``<name>.corrupt``) every newer one that does not, naming it in the log.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Optional

from toolkit.atomic import atomic_path, load_error_reason, set_aside

__all__ = [
    "RunInterrupted",
    "WallClock",
    "graceful_interrupts",
    "interrupt_requested",
    "newest_intact_checkpoint",
    "save_checkpoint",
    "DEFAULT_CHECKPOINT_SECONDS",
]

log = logging.getLogger(__name__)

#: seconds of work between wall-time checkpoints (the most a SIGKILL can cost)
DEFAULT_CHECKPOINT_SECONDS = 120.0

_requested: Optional[str] = None


class RunInterrupted(Exception):
    """The user asked the run to stop (Ctrl-C or SIGTERM); a checkpoint was written first.

    Not a ``KeyboardInterrupt``: Lightning turns those into ``sys.exit(1)``.
    """

    exit_code = 130


def interrupt_requested() -> Optional[str]:
    """The name of the signal that asked the run to stop (``"SIGINT"``, ``"SIGTERM"``), or None."""
    return _requested


def request_interrupt(name: str = "SIGINT") -> None:
    """Ask the running fit to stop at the end of its current iteration (what a signal does)."""
    global _requested
    _requested = name


@contextlib.contextmanager
def graceful_interrupts() -> Iterator[None]:
    """Within the block the first SIGINT/SIGTERM only sets :func:`interrupt_requested`; a second
    SIGINT raises ``KeyboardInterrupt`` at once. Outside the main thread this does nothing."""
    global _requested
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _requested = None
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum, frame):  # noqa: ARG001
        global _requested
        if _requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        _requested = signal.Signals(signum).name
        log.warning("%s received: saving a checkpoint at the end of this iteration (Ctrl-C again to stop at once)",
                    _requested)

    for s in previous:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _requested = None


class WallClock:
    """``due()`` is True once ``every_s`` seconds have passed since the last ``reset()``."""

    def __init__(self, every_s: Optional[float] = DEFAULT_CHECKPOINT_SECONDS, clock: Callable[[], float] = time.monotonic):
        if every_s is not None and not every_s > 0:
            raise ValueError(f"checkpoint interval must be > 0 seconds or None, got {every_s!r}")
        self.every_s = every_s
        self.clock = clock
        self.last = clock()

    def due(self) -> bool:
        return self.every_s is not None and self.clock() - self.last >= self.every_s

    def reset(self) -> None:
        self.last = self.clock()


def save_checkpoint(trainer, path: str | Path) -> Path:
    """``trainer.save_checkpoint(path)`` through a temporary file (a kill never truncates ``path``)."""
    with atomic_path(path) as tmp:
        trainer.save_checkpoint(tmp)
    return Path(path)


def _progress(ckpt: dict) -> int:
    own = ckpt.get("projo4d") or {}
    for key in ("curriculum_step", "step"):
        if key in own:
            return int(own[key])
    return int(ckpt.get("global_step", 0))


def checkpoint_progress(path: str | Path) -> int:
    """The iteration a checkpoint file was written at; raises if the file does not load."""
    import torch

    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise ValueError("not a Lightning checkpoint (no state_dict)")
    return _progress(ckpt)


def newest_intact_checkpoint(folder: str | Path, pattern: str = "*.ckpt") -> Optional[Path]:
    """The checkpoint in ``folder`` with the most progress that loads, or None.

    ``last.ckpt`` is the newest by construction, so it is returned when it loads; otherwise every
    other checkpoint is tried and the one with the most progress wins. Unreadable files are set
    aside as ``<name>.corrupt`` (and named in the log), so a rerun never trips over them again.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return None

    def intact(path: Path) -> Optional[int]:
        try:
            return checkpoint_progress(path)
        except Exception as err:  # noqa: BLE001 - any load failure means the file is unusable
            set_aside(path, load_error_reason(err))
            return None

    last = folder / "last.ckpt"
    if last.is_file() and intact(last) is not None:
        return last
    best: tuple[int, Path] | None = None
    for path in sorted(folder.glob(pattern)):
        if path.name.startswith(".") or path.name == "last.ckpt":
            continue
        step = intact(path)
        if step is not None and (best is None or step > best[0]):
            best = (step, path)
    if best is not None:
        log.warning("resuming from %s (iteration %d)", best[1], best[0])
    return None if best is None else best[1]

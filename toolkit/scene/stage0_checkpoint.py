"""Stage-0 checkpoints: every N iterations, every few minutes of work, on Ctrl-C/SIGTERM and at the end."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import pytorch_lightning as pl

from toolkit.checkpointing import DEFAULT_CHECKPOINT_SECONDS, RunInterrupted, WallClock, interrupt_requested, save_checkpoint

__all__ = ["Stage0Checkpoint"]


class Stage0Checkpoint(pl.Callback):
    """Save ``step_XXXXXX.ckpt`` every ``every_n`` iterations (the module's own counter, not
    ``trainer.global_step``), once ``every_s`` seconds of work have passed since the last save, and
    when Ctrl-C or SIGTERM asked the run to stop (then :class:`RunInterrupted` is raised); write
    ``last.ckpt`` at the end of training. Every file is written atomically; a wall-time save
    replaces the previous wall-time save (the periodic ones are kept).
    """

    def __init__(self, dirpath: str | Path, every_n: Optional[int] = None, save_last: bool = True,
                 every_s: Optional[float] = DEFAULT_CHECKPOINT_SECONDS):
        self.dirpath = Path(dirpath)
        self.every_n = every_n
        self.save_last = save_last
        self.clock = WallClock(every_s)
        self._timed: Optional[Path] = None

    def on_train_start(self, trainer: pl.Trainer, pl_module) -> None:
        self.clock.reset()

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = int(pl_module.step)
        interrupted = interrupt_requested() is not None or getattr(trainer, "received_sigterm", False)
        finished = step >= pl_module.schedule.iterations
        periodic = bool(self.every_n) and step % self.every_n == 0
        if periodic or self.clock.due() or (interrupted and not finished):
            path = save_checkpoint(trainer, self.dirpath / f"step_{step:06d}.ckpt")
            self.clock.reset()
            if self._timed is not None and self._timed != path:
                self._timed.unlink(missing_ok=True)
            self._timed = None if periodic else path
        if interrupted and not finished:
            raise RunInterrupted(f"stage 0 stopped at iteration {step} of {pl_module.schedule.iterations}; "
                                 f"saved {self.dirpath / f'step_{step:06d}.ckpt'}")

    def on_train_end(self, trainer: pl.Trainer, pl_module) -> None:
        if self.save_last:
            save_checkpoint(trainer, self.dirpath / "last.ckpt")

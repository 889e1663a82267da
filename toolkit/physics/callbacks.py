"""Lightning callbacks of the physics stages: curriculum checkpoints and a stage-aware progress bar."""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
from pytorch_lightning.callbacks import Callback

from toolkit.atomic import write_json
from toolkit.checkpointing import DEFAULT_CHECKPOINT_SECONDS, RunInterrupted, WallClock, interrupt_requested, save_checkpoint

__all__ = ["CurriculumCheckpoint", "EstimateWriter", "curriculum_progress_bar"]


#: curricula with more stages than this get no per-stage checkpoints
MAX_STAGE_SAVES = 50


class CurriculumCheckpoint(Callback):
    """Save ``step_XXXXXX.ckpt`` every ``every_n_steps`` iterations and at each stage end, and keep
    ``last.ckpt`` current, so a killed run resumes where it stopped (``trainer.fit(ckpt_path=...)``).

    Every file is written atomically. ``last.ckpt`` is also written once ``every_s`` seconds of work
    have passed since the last save (at most that much is lost to a SIGKILL) and when Ctrl-C or
    SIGTERM asked the run to stop (see :func:`toolkit.checkpointing.graceful_interrupts`); after
    that save the fit raises :class:`~toolkit.checkpointing.RunInterrupted`.

    Args:
        dirpath: folder of the checkpoints (default: ``<trainer.default_root_dir>/checkpoints``).
        every_n_steps: curriculum iterations between checkpoints (0: only stage ends and last).
        keep_stage_ends: keep a copy at every stage end (``stage_XX_end.ckpt``).
        every_s: seconds of work between wall-time saves of ``last.ckpt`` (None: off).
        max_stage_saves: curricula with more stages than this save at stage ends only through
            the periodic and wall-time rules (``(XAS:1)x100000`` must not write 100000 files;
            default :data:`MAX_STAGE_SAVES`).
    """

    def __init__(self, dirpath: str | None = None, every_n_steps: int = 50, keep_stage_ends: bool = True,
                 every_s: float | None = DEFAULT_CHECKPOINT_SECONDS, max_stage_saves: int | None = None):
        super().__init__()
        self.dirpath = Path(dirpath) if dirpath else None
        self.every_n_steps = every_n_steps
        self.keep_stage_ends = keep_stage_ends
        self.clock = WallClock(every_s)
        self.max_stage_saves = MAX_STAGE_SAVES if max_stage_saves is None else max_stage_saves

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        if self.dirpath is None:
            self.dirpath = Path(trainer.default_root_dir) / "checkpoints"
        self.clock.reset()

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = getattr(pl_module, "curriculum_step", None)
        if step is None or outputs is None:
            return
        self.dirpath.mkdir(parents=True, exist_ok=True)
        boundaries = pl_module.curriculum.boundaries(pl_module.material.registry_name or None)
        few_stages = len(boundaries) - 1 <= self.max_stage_saves
        at_stage_end = step in boundaries[1:] and (few_stages or step == boundaries[-1])
        periodic = bool(self.every_n_steps) and step % self.every_n_steps == 0
        interrupted = interrupt_requested() is not None or getattr(trainer, "received_sigterm", False)
        if periodic:
            save_checkpoint(trainer, self.dirpath / f"step_{step:06d}.ckpt")
        if at_stage_end and self.keep_stage_ends and few_stages:
            save_checkpoint(trainer, self.dirpath / f"stage_{boundaries.index(step) - 1:02d}_end.ckpt")
        if periodic or at_stage_end or interrupted or self.clock.due():
            save_checkpoint(trainer, self.dirpath / "last.ckpt")
            self.clock.reset()
        if interrupted and step < boundaries[-1]:
            raise RunInterrupted(f"physics fit stopped at iteration {step} of {boundaries[-1]}; "
                                 f"saved {self.dirpath / 'last.ckpt'}")


class EstimateWriter(Callback):
    """Write ``estimate.json`` (parameters, v0, curriculum, errors when known, and the uncertainty:
    90 % intervals and identifiability labels, :mod:`toolkit.physics.uncertainty`) and
    ``history.json`` (one record per iteration) to ``<trainer.default_root_dir>`` when training ends.

    With ``uncertainty`` (default) the Laplace posterior is computed first, after a finished
    curriculum only; its MAP step may move undetermined parameters back toward their initial guess,
    so ``last.ckpt`` of a :class:`CurriculumCheckpoint` is written again afterwards.
    """

    def __init__(self, uncertainty: bool = True):
        super().__init__()
        self.uncertainty = uncertainty

    def on_train_end(self, trainer: pl.Trainer, pl_module) -> None:
        out = Path(trainer.default_root_dir)
        out.mkdir(parents=True, exist_ok=True)
        key = pl_module.material.registry_name or None
        if self.uncertainty and pl_module.curriculum_step >= pl_module.total_iterations and hasattr(pl_module, "uncertainty"):
            _add_uncertainty(trainer, pl_module)
        est = pl_module.estimate()
        est["uncertainty"] = getattr(pl_module, "uncertainty_result", None)
        est["iterations"] = pl_module.curriculum_step
        est["curriculum"] = pl_module.curriculum.describe(key)
        est["errors"] = pl_module.parameter_errors()
        write_json(out / "history.json", pl_module.history, indent=None)
        write_json(out / "estimate.json", est)


def _add_uncertainty(trainer: pl.Trainer, module) -> None:
    """``module.uncertainty()``, then ``last.ckpt`` again; a failure is logged, never fatal."""
    import logging

    try:
        module.uncertainty()
    except Exception as err:  # the estimate is still worth writing
        logging.getLogger(__name__).warning("uncertainty of the estimate could not be computed: %s", err)
        return
    for cb in getattr(trainer, "callbacks", None) or []:  # (benchmark jobs pass a bare namespace)
        if isinstance(cb, CurriculumCheckpoint) and cb.dirpath is not None and (cb.dirpath / "last.ckpt").is_file():
            save_checkpoint(trainer, cb.dirpath / "last.ckpt")


def _physics_position(trainer, module) -> tuple[str, int, int]:
    """``("physics 2/3 XAS@3", iterations done, total)`` from the module's own curriculum counter."""
    total = int(getattr(module, "total_iterations", 0))
    done = min(int(getattr(module, "curriculum_step", 0)), total)
    if not total:
        return "physics", 0, 0
    at = module.curriculum.stage_at(min(done, total - 1), module.material.registry_name or None)
    return f"physics {at.index + 1}/{len(module.stages)} {at.stage.name}", done, total


def curriculum_progress_bar(enabled: bool | None = None, console=None) -> Callback:
    """The bar of the physics stages: ``physics <stage>/<stages> <name>``, iteration/total over the
    whole curriculum, elapsed time, ETA and the loss (see :class:`toolkit.progress.IterationBar`;
    off when stdout/stderr is not a terminal unless ``enabled``)."""
    from toolkit.progress import IterationBar

    return IterationBar(_physics_position, metric_keys=("loss/total",), enabled=enabled, console=console)

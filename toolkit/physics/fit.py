"""Run the physics stages with a Lightning Trainer: loggers, checkpoints, progress, resume."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Optional

import pytorch_lightning as pl
from pytorch_lightning.loggers import CSVLogger, TensorBoardLogger
from pytorch_lightning.utilities.exceptions import SIGTERMException

from toolkit.checkpointing import RunInterrupted

from toolkit.physics.callbacks import CurriculumCheckpoint, EstimateWriter, curriculum_progress_bar
from toolkit.physics.module import InversePhysicsModule

__all__ = ["build_trainer", "fit_physics", "default_loggers", "default_callbacks", "TRAINER_DEFAULTS"]

#: Trainer settings of the physics stages (a curriculum, not epochs, decides when to stop).
TRAINER_DEFAULTS = dict(
    devices=1,
    max_epochs=1,
    enable_checkpointing=False,
    enable_model_summary=False,
    log_every_n_steps=1,
    num_sanity_val_steps=0,
    limit_val_batches=0,
)


def default_loggers(out_dir: str | Path) -> list:
    """CSV logs under ``out_dir/logs/version_K`` (and TensorBoard next to them when installed).

    A resumed run writes a new version folder, so no earlier log is overwritten; ``history.json``
    (written at the end of training) holds the whole run in one file.
    """
    csv = CSVLogger(out_dir, name="logs")
    loggers = [csv]
    if importlib.util.find_spec("tensorboard") is not None:
        loggers.append(TensorBoardLogger(out_dir, name="logs", version=f"{csv.version}_tensorboard" if isinstance(csv.version, str) else f"version_{csv.version}_tensorboard"))
    return loggers


def default_callbacks(checkpoint_every: int = 50, progress: bool = True) -> list:
    callbacks = [CurriculumCheckpoint(every_n_steps=checkpoint_every), EstimateWriter()]
    if progress:
        callbacks.append(curriculum_progress_bar())
    return callbacks


def build_trainer(out_dir: str | Path, checkpoint_every: int = 50, accelerator: str = "auto", progress: bool = True,
                  **trainer_kwargs) -> pl.Trainer:
    """A Trainer for :class:`InversePhysicsModule`: CSV logs (and TensorBoard when installed) under
    ``out_dir/logs``, curriculum checkpoints under ``out_dir/checkpoints``, a stage-aware progress bar.
    """
    out_dir = Path(out_dir)
    kwargs = dict(TRAINER_DEFAULTS, accelerator=accelerator, default_root_dir=str(out_dir), logger=default_loggers(out_dir),
                  callbacks=default_callbacks(checkpoint_every, progress), enable_progress_bar=progress)
    kwargs.update(trainer_kwargs)
    return pl.Trainer(**kwargs)


def fit_physics(module: InversePhysicsModule, out_dir: str | Path, resume: Optional[str | Path] = None,
                checkpoint_every: int = 50, accelerator: str = "auto", progress: bool = True,
                **trainer_kwargs) -> InversePhysicsModule:
    """Fit ``module``, writing logs, checkpoints and ``estimate.json`` to ``out_dir``.

    Args:
        resume: a checkpoint to continue from (e.g. ``out_dir/checkpoints/last.ckpt``), or
            ``"last"`` for that file when it exists.
    """
    out_dir = Path(out_dir)
    if resume == "last":
        last = out_dir / "checkpoints" / "last.ckpt"
        resume = last if last.is_file() else None
    trainer = build_trainer(out_dir, checkpoint_every, accelerator, progress, **trainer_kwargs)
    try:
        trainer.fit(module, ckpt_path=str(resume) if resume else None)
    except SIGTERMException as err:
        # a SIGTERM in the fit's last iteration gets past CurriculumCheckpoint (which raises only before
        # the last one); Lightning then ends the epoch with SystemExit(None), exit status 0, before
        # on_train_end. That callback saved last.ckpt at the last iteration: report the interruption.
        raise RunInterrupted(f"physics fit stopped by SIGTERM at iteration {module.curriculum_step} of "
                             f"{module.total_iterations}; saved {out_dir / 'checkpoints' / 'last.ckpt'}") from err
    return module

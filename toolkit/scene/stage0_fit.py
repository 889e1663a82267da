"""Train stage 0 in one call: :func:`fit_stage0` sets up a Lightning ``Trainer`` (checkpoints,
progress bar, loggers) for a :class:`~toolkit.scene.stage0.Gaussians4DModule`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import pytorch_lightning as pl

from toolkit.scene.stage0_checkpoint import Stage0Checkpoint
from toolkit.scene.stage0_data import Stage0DataModule

if TYPE_CHECKING:  # stage0 re-exports fit_stage0, so it is imported where needed
    from toolkit.scene.stage0 import Gaussians4DModule

__all__ = ["fit_stage0"]


def fit_stage0(
    data: Stage0DataModule,
    module: Optional["Gaussians4DModule"] = None,
    *,
    out_dir: Optional[str | Path] = None,
    checkpoint_every: Optional[int] = None,
    ckpt_path: Optional[str | Path] = None,
    stop_at: Optional[int] = None,
    accelerator: str = "auto",
    progress_bar: bool = False,
    logger: Any = None,
    **module_kwargs: Any,
) -> "Gaussians4DModule":
    """Train stage 0 with a ready-configured Lightning ``Trainer``.

    Args:
        data: The training views.
        module: A module to train (default: ``Gaussians4DModule(**module_kwargs)``).
        out_dir: Where checkpoints go (``step_XXXXXX.ckpt``, ``last.ckpt``); None: no checkpoints.
        checkpoint_every: Iterations between checkpoints.
        ckpt_path: Resume from this checkpoint.
        stop_at: Stop after this iteration (the schedule is unchanged, so a later resume
            continues it).
        accelerator: Lightning accelerator (``"cpu"``, ``"gpu"``, ``"auto"``).
        progress_bar: Show the stage-0 progress bar (``stage 0``, iteration/total, ETA, loss;
            drawn only on a terminal, see :func:`toolkit.progress.stage0_progress_bar`).
        logger: Lightning logger(s) for the ``train/*`` metrics (loss, L1, SSIM, PSNR in dB,
            Gaussian count, iteration; every ``schedule.log_every`` iterations). Default: with
            ``out_dir``, CSV under ``out_dir/logs/version_K`` (and TensorBoard when installed, as
            the physics stages do); without, none. ``False`` turns logging off.

    Returns:
        The trained module.
    """
    if module is None:
        from toolkit.scene.stage0 import Gaussians4DModule

        module = Gaussians4DModule(**module_kwargs)
    module.stop_at = stop_at
    callbacks: list[pl.Callback] = []
    if out_dir is not None:
        callbacks.append(Stage0Checkpoint(out_dir, checkpoint_every))
    if progress_bar:
        from toolkit.progress import stage0_progress_bar

        callbacks.append(stage0_progress_bar())
    if logger is None:
        from toolkit.physics.fit import default_loggers

        logger = default_loggers(out_dir) if out_dir is not None else False
    trainer = pl.Trainer(
        accelerator=accelerator,
        devices=1,
        max_epochs=1,
        max_steps=-1,
        logger=logger,
        log_every_n_steps=1,  # the module logs every schedule.log_every iterations itself
        enable_checkpointing=False,
        enable_model_summary=False,
        enable_progress_bar=progress_bar,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        callbacks=callbacks,
    )
    trainer.fit(module, datamodule=data, ckpt_path=None if ckpt_path is None else str(ckpt_path))
    return module

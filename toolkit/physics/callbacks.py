"""Lightning callbacks of the physics stages: curriculum checkpoints and a stage-aware progress bar."""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
from pytorch_lightning.callbacks import Callback, RichProgressBar, TQDMProgressBar

__all__ = ["CurriculumCheckpoint", "EstimateWriter", "curriculum_progress_bar"]


class CurriculumCheckpoint(Callback):
    """Save ``step_XXXXXX.ckpt`` every ``every_n_steps`` iterations and at each stage end, and keep
    ``last.ckpt`` current, so a killed run resumes where it stopped (``trainer.fit(ckpt_path=...)``).

    Args:
        dirpath: folder of the checkpoints (default: ``<trainer.default_root_dir>/checkpoints``).
        every_n_steps: curriculum iterations between checkpoints (0: only stage ends and last).
        keep_stage_ends: keep a copy at every stage end (``stage_XX_end.ckpt``).
    """

    def __init__(self, dirpath: str | None = None, every_n_steps: int = 50, keep_stage_ends: bool = True):
        super().__init__()
        self.dirpath = Path(dirpath) if dirpath else None
        self.every_n_steps = every_n_steps
        self.keep_stage_ends = keep_stage_ends

    def setup(self, trainer: pl.Trainer, pl_module, stage: str) -> None:
        if self.dirpath is None:
            self.dirpath = Path(trainer.default_root_dir) / "checkpoints"

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = getattr(pl_module, "curriculum_step", None)
        if step is None or outputs is None:
            return
        self.dirpath.mkdir(parents=True, exist_ok=True)
        boundaries = pl_module.curriculum.boundaries(pl_module.material.registry_name or None)
        at_stage_end = step in boundaries[1:]
        periodic = self.every_n_steps and step % self.every_n_steps == 0
        if periodic:
            trainer.save_checkpoint(self.dirpath / f"step_{step:06d}.ckpt")
        if at_stage_end and self.keep_stage_ends:
            trainer.save_checkpoint(self.dirpath / f"stage_{boundaries.index(step) - 1:02d}_end.ckpt")
        if periodic or at_stage_end:
            trainer.save_checkpoint(self.dirpath / "last.ckpt")


class EstimateWriter(Callback):
    """Write ``estimate.json`` (parameters, v0, curriculum, errors when known) and ``history.json``
    (one record per iteration) to ``<trainer.default_root_dir>`` when training ends."""

    def on_train_end(self, trainer: pl.Trainer, pl_module) -> None:
        import json

        out = Path(trainer.default_root_dir)
        out.mkdir(parents=True, exist_ok=True)
        key = pl_module.material.registry_name or None
        est = pl_module.estimate()
        est["iterations"] = pl_module.curriculum_step
        est["curriculum"] = pl_module.curriculum.describe(key)
        est["errors"] = pl_module.parameter_errors()
        (out / "estimate.json").write_text(json.dumps(est, indent=2))
        (out / "history.json").write_text(json.dumps(pl_module.history))


class _StageMetrics:
    def get_metrics(self, trainer, pl_module):  # noqa: D102
        items = super().get_metrics(trainer, pl_module)
        items.pop("v_num", None)
        step = getattr(pl_module, "curriculum_step", 0)
        total = getattr(pl_module, "total_iterations", 0)
        if total and step:
            at = pl_module.curriculum.stage_at(min(step, total) - 1, pl_module.material.registry_name or None)
            items["stage"] = f"{at.index + 1}/{len(pl_module.stages)} {at.stage.name}"
            items["iteration"] = f"{step}/{total}"
        return items


class _RichStageBar(_StageMetrics, RichProgressBar):
    pass


class _TqdmStageBar(_StageMetrics, TQDMProgressBar):
    pass


def curriculum_progress_bar() -> Callback:
    """A rich progress bar showing the stage and iteration (tqdm when rich is unavailable)."""
    try:
        import rich  # noqa: F401

        return _RichStageBar()
    except ImportError:  # pragma: no cover
        return _TqdmStageBar()

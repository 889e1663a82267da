"""Lightning callbacks of the benchmark's physics fits: stop cleanly when asked to, and when a fit diverges."""

from __future__ import annotations

import os
import signal
from pathlib import Path

from pytorch_lightning.callbacks import Callback

__all__ = ["CheckpointOnStop", "SigtermAtStep", "DivergenceGuard"]


class CheckpointOnStop(Callback):
    """Save ``last.ckpt`` at the iteration where SIGTERM arrived; Lightning stops right after it
    (raising ``SIGTERMException``), and a rerun resumes from that iteration.

    Args:
        dirpath: the checkpoint folder of the fit (``physics/checkpoints``).
    """

    def __init__(self, dirpath: str | Path):
        super().__init__()
        self.dirpath = Path(dirpath)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if outputs is not None and trainer.received_sigterm:
            self.dirpath.mkdir(parents=True, exist_ok=True)
            trainer.save_checkpoint(self.dirpath / "last.ckpt")
            print(f"stop requested: saved {self.dirpath / 'last.ckpt'} at iteration {pl_module.curriculum_step}", flush=True)


class SigtermAtStep(Callback):
    """Testing aid: send this process SIGTERM after iteration ``step``, as the runner does when its
    time limit comes.

    Args:
        step: the iteration count after which to stop.
    """

    def __init__(self, step: int):
        super().__init__()
        self.step = step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if outputs is not None and pl_module.curriculum_step == self.step:
            os.kill(os.getpid(), signal.SIGTERM)


class DivergenceGuard(Callback):
    """Stop a fit whose parameters left the valid set, and put back the last valid ones.

    After every iteration it checks that every parameter is finite and that the material
    parameters are in their material's ranges (a linear friction angle can be pushed below 0, a
    NaN gradient makes E NaN). When they are not, it restores the parameters from the start of
    that iteration, records ``diverged`` (``{"step", "reason"}``) here and in the history's last
    record, and stops training, so the benchmark evaluates the estimate the strategy reached
    instead of losing the run. List it before the checkpoint and periodic-evaluation callbacks.
    A simulation that fails inside an iteration raises out of the fit instead; :meth:`restore`
    then puts back the parameters from the start of that iteration.
    """

    def __init__(self):
        super().__init__()
        self.diverged = None
        self._snapshot = None
        self._step = 0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._snapshot = {n: p.detach().clone() for n, p in pl_module.named_parameters()}
        self._step = pl_module.curriculum_step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if outputs is None:
            return
        reason = self.check(pl_module)
        if reason:
            self.restore(pl_module, reason)
            trainer.should_stop = True

    @staticmethod
    def check(pl_module) -> "str | None":
        """Why the module's parameters are invalid, or ``None``."""
        import torch

        from materials import MaterialError

        params = dict(pl_module.named_parameters())
        finite = torch.stack([torch.isfinite(p).all() for p in params.values()])
        if not bool(finite.all()):
            bad = [n for n, ok in zip(params, finite.tolist()) if not ok]
            return f"non-finite parameters: {', '.join(bad)}"
        try:
            pl_module.material.check_tensor(pl_module.material_params().detach())
        except MaterialError as err:
            return str(err)
        return None

    def restore(self, pl_module, reason: str) -> None:
        """Put back the parameters of the start of the current iteration and record why."""
        import torch

        if self._snapshot is None:
            return
        with torch.no_grad():
            for n, p in pl_module.named_parameters():
                p.copy_(self._snapshot[n])
        self.diverged = {"step": self._step + 1, "reason": reason}
        if pl_module.history and pl_module.history[-1].get("step") == self._step + 1:
            pl_module.history[-1]["diverged"] = reason
        pl_module._cached_positions = None
        print(f"fit diverged at iteration {self._step + 1} ({reason}); kept the parameters of iteration {self._step}", flush=True)

"""Opacity resets that cannot wipe out stage 0's model.

3DGS (and GIC) cap every opacity at 0.01 at regular intervals and let the Gaussians that matter
earn their opacity back; the next densification rounds prune those that fall below
``min_opacity``. That assumes the model already explains most of the images. In a 4D model whose
deformation does not yet follow the motion (a fast throw early in a short schedule), every
Gaussian is in the wrong place in most frames, so the loss lowers every opacity at once, and the
optimizer moments the reset zeroed make the first steps large: on a generated banana thrown at
1.3 m/s, with GIC's schedule compressed to 2500 iterations, 3611 of 4127 Gaussians fell below
``min_opacity`` eight iterations after the first reset and stage 0 ended with 24 Gaussians and no
body to fill (the same run without resets: 33k Gaussians, 43.8 dB).

:class:`OpacityResetGuard` keeps a copy of the Gaussians and their optimizer state at each reset.
If, before the next reset, more than ``max_fade`` of the Gaussians sit below ``min_opacity`` at a
densification round, the reset is undone (the copy is restored: parameters, Adam moments and step,
the densification statistics zeroed) and no further reset happens in the run. The deformation
network keeps what it learned meanwhile. A healthy reset fades a few percent of the Gaussians
(floaters), far below the default ``max_fade`` of one half. The copy lives in memory only: a run
resumed between a reset and the next densification round cannot undo that reset (whether resets
are still allowed is kept in the checkpoint).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Optional

import torch

from toolkit.scene.gaussian_model import PER_GAUSSIAN_BUFFERS, PER_GAUSSIAN_PARAMS, GaussianModel, _unwrap_optimizers

__all__ = ["OpacityResetGuard"]

log = logging.getLogger(__name__)


@dataclass
class OpacityResetGuard:
    """Resets opacities (:meth:`reset`) and undoes a reset that fades most of the model (:meth:`check`).

    Attributes:
        max_fade: Fraction of the Gaussians below ``min_opacity`` at a densification round after a
            reset above which the reset is undone (default one half).
        disabled: True once a reset was undone: later :meth:`reset` calls do nothing. Kept in
            stage 0's checkpoints.
        reverted: One record per undone reset (``reset_iteration``, ``iteration``, ``faded``, ``n``,
            ``restored_n``), for the stage-0 summary.
    """

    max_fade: float = 0.5
    disabled: bool = False
    reverted: list = field(default_factory=list)
    _snapshot: Optional[dict] = field(default=None, repr=False)
    _reset_iteration: int = field(default=0, repr=False)

    def reset(self, g: GaussianModel, optimizers: Any, value: float, iteration: int) -> bool:
        """Cap every opacity at ``value`` (:meth:`GaussianModel.reset_opacity`) after keeping a copy
        of the Gaussians and their optimizer state; returns False (and does nothing) when disabled."""
        if self.disabled:
            return False
        self._snapshot = _snapshot(g, optimizers)
        self._reset_iteration = int(iteration)
        g.reset_opacity(value, optimizers)
        return True

    def release(self) -> None:
        """Drop the copy (the densification window is over: nothing is pruned any more)."""
        self._snapshot = None

    @torch.no_grad()
    def check(self, g: GaussianModel, optimizers: Any, min_opacity: float, iteration: int) -> Optional[dict]:
        """Before a densification round: undo the last reset if more than ``max_fade`` of the
        Gaussians are below ``min_opacity``. Returns the record of an undone reset, else None."""
        if self._snapshot is None or g.n == 0:
            return None
        faded = int((g.opacity < min_opacity).sum())
        if faded <= self.max_fade * g.n:
            return None
        record = {"reset_iteration": self._reset_iteration, "iteration": int(iteration), "faded": faded, "n": int(g.n)}
        _restore(g, optimizers, self._snapshot)
        self._snapshot, self.disabled = None, True
        record["restored_n"] = int(g.n)
        self.reverted.append(record)
        log.warning(
            "stage 0: the opacity reset at iteration %d faded %d of %d Gaussians below opacity %g by iteration %d "
            "(the 4D model does not follow the motion yet); restored the %d Gaussians of before the reset, "
            "and no further opacity resets in this run",
            record["reset_iteration"], faded, record["n"], min_opacity, record["iteration"], record["restored_n"])
        return record


def _snapshot(g: GaussianModel, optimizers: Any) -> dict:
    params = {name: getattr(g, name).data.clone() for name in PER_GAUSSIAN_PARAMS}
    states = []
    for opt in _unwrap_optimizers(optimizers):
        states.append({name: {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in opt.state[getattr(g, name)].items()}
                       for name in PER_GAUSSIAN_PARAMS if opt.state.get(getattr(g, name))})
    return {"params": params, "states": states}


def _restore(g: GaussianModel, optimizers: Any, snap: dict) -> None:
    for name, data in snap["params"].items():
        p = getattr(g, name)
        p.data = data
        p.grad = None
    for opt, saved in zip(_unwrap_optimizers(optimizers), snap["states"]):
        for name in PER_GAUSSIAN_PARAMS:
            p = getattr(g, name)
            if name in saved:
                opt.state[p] = saved[name]
            else:
                opt.state.pop(p, None)
    n = g.n
    for name in PER_GAUSSIAN_BUFFERS:
        b = getattr(g, name)
        setattr(g, name, torch.zeros(n, dtype=b.dtype, device=b.device))

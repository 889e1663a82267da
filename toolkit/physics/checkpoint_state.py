"""What an :class:`~toolkit.physics.InversePhysicsModule` keeps in a checkpoint besides its
parameters, and how a checkpoint written by an older version is read (a mixin of the module).

Saved under ``checkpoint["projo4d"]``: the module's own iteration counter (``curriculum_step``),
the curriculum it ran, the per-step history, the simulator's grid (its origin enters
``(x - origin) / dx``, so a resumed run must use the same one), the substeps floor left by a
dt halving, the last uncertainty result and the coarse material search's record.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import torch

from strategies import Stage

__all__ = ["CheckpointStateMixin"]

log = logging.getLogger(__name__)


class CheckpointStateMixin:
    """Lightning's checkpoint hooks and the state-dict compatibility of the module."""

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a run saved before Gaussians could deform (no deform buffers) was fitted with rigid shapes: it keeps them
        if prefix + "embed_index" in state_dict and prefix + "deform_index" not in state_dict:
            state_dict[prefix + "deform_index"] = torch.zeros(0, 0, dtype=torch.int64)
            state_dict[prefix + "deform_gradient"] = torch.zeros(0, 0, 3)
        # a run saved with another embedding (neighbour count or mode, rigid or deformed shapes)
        # keeps its own: the buffers take its shape
        for name in ("embed_index", "embed_weight", "deform_index", "deform_gradient"):
            saved = state_dict.get(prefix + name)
            if saved is not None and saved.shape != getattr(self, name).shape:
                setattr(self, name, torch.empty_like(saved, device=getattr(self, name).device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        if not self.deform_index.numel():
            self.gaussian_shape = "rigid"

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["projo4d"] = {
            "curriculum_step": self.curriculum_step,
            "curriculum": self.curriculum.describe(self.material.registry_name or None),
            "history": self.history,
            "grid": None if self._sim is None or self._sim.grid is None else self._sim.grid.__dict__,
            "substeps_floor": self._restored_substeps_floor if self._sim is None else self._sim.substeps_floor,
            "uncertainty": self.uncertainty_result,
            "material_search": self.material_search,
        }

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        state = checkpoint.get("projo4d", {})
        self.curriculum_step = int(state.get("curriculum_step", 0))
        self.history = list(state.get("history", []))
        self._restored_grid = state.get("grid")
        self._restored_substeps_floor = int(state.get("substeps_floor", 0))
        self.uncertainty_result = state.get("uncertainty")
        self.material_search = state.get("material_search")
        self._sim = None
        saved = state.get("curriculum")
        # as Stages (a field a checkpoint predates takes its default), names aside
        unnamed = lambda stages: [  # noqa: E731
            (replace(Stage.from_dict({k: v for k, v in d.items() if k not in ("start", "end")}), name=""), d.get("start"), d.get("end"))
            for d in stages]
        if saved is not None and unnamed(saved) != unnamed(self.curriculum.describe(self.material.registry_name or None)):
            log.warning("the checkpoint was written with a different curriculum; continuing with the current one")

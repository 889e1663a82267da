"""Periodic evaluation during the physics fit: future-state error and image quality against the iteration.

The paper's appendix figure plots EMD and PSNR of the *future* frames, and the parameter errors,
against the optimization iteration with the stages shaded. The parameter errors are already in
every record of :attr:`InversePhysicsModule.history` (``error/...``); this callback adds the
future-state metrics at a few iterations per stage:

* ``eval/cd_future``, ``eval/emd_future``: Chamfer distance (x1e3) and EMD (m) between the
  predicted particles and the ground-truth clouds, averaged over the future frames
  ``[n_train, T)`` (computed as :mod:`toolkit.metrics` does; a scene without future frames uses
  its last frame);
* ``eval/cd_x0``, ``eval/emd_x0``: the same at frame 0 (the canonical state, the paper's
  ``EMD_x0``);
* ``eval/psnr_future``: PSNR (dB) of the future frames rendered from one held-out camera
  (``eval/camera``) against its ground-truth images masked on black;
* ``eval/error``: set instead when the prediction's simulation fails (CFL, NaN, out of the grid,
  parameters out of their range); the fit itself goes on.

Each prediction simulates every frame without gradients; the CD/EMD part needs the ground-truth
point clouds (synthetic scenes), the PSNR part a held-out camera (else the first fitted one).

It is **off by default** (not among :func:`toolkit.physics.fit.default_callbacks`);
``projo4d benchmark`` turns it on. Use it with :func:`~toolkit.physics.fit.fit_physics`::

    from toolkit.physics.fit import default_callbacks, fit_physics
    from toolkit.physics.periodic_eval import PeriodicEvaluation

    callbacks = [PeriodicEvaluation(per_stage=8)] + default_callbacks()
    fit_physics(module, "runs/x/physics", callbacks=callbacks)

List it *before* the checkpoint callback so that the checkpoint written at the same iteration
holds the new values (the history is part of the checkpoint, so a resumed fit keeps them).
:func:`toolkit.report.plot_evaluation_trajectories` draws the series.
"""

from __future__ import annotations

import logging
import math
from typing import Optional, Sequence, Union

import numpy as np
import torch
from pytorch_lightning.callbacks import Callback

__all__ = ["PeriodicEvaluation", "EVAL_KEYS", "evaluation_steps"]

log = logging.getLogger(__name__)

#: the keys this callback adds to history records
EVAL_KEYS = ("eval/cd_future", "eval/emd_future", "eval/cd_x0", "eval/emd_x0", "eval/psnr_future")


def evaluation_steps(boundaries: Sequence[int], every_n_steps: Optional[int] = None, per_stage: int = 8) -> list[int]:
    """The iterations (1-based counts of finished iterations) at which the callback evaluates.

    Always the first iteration, every stage end and the last iteration; in between either every
    ``every_n_steps`` iterations or, when that is ``None``, ``per_stage`` evenly spaced points in
    each stage (so a 40k-iteration appearance stage costs as much as a 100-iteration one).

    Args:
        boundaries: cumulative stage boundaries ``[0, b1, ..., total]``
            (:meth:`strategies.Strategy.boundaries`).
        every_n_steps: a fixed interval instead of ``per_stage``.
        per_stage: evaluations inside each stage.

    Returns:
        Sorted iteration counts.
    """
    total = boundaries[-1]
    steps = {1, total} | {b for b in boundaries[1:]}
    if every_n_steps:
        steps |= set(range(every_n_steps, total + 1, every_n_steps))
    elif per_stage > 0:
        for start, end in zip(boundaries[:-1], boundaries[1:]):
            interval = max(1, math.ceil((end - start) / per_stage))
            steps |= set(range(start + interval, end + 1, interval))
    return sorted(s for s in steps if 1 <= s <= total)


class PeriodicEvaluation(Callback):
    """Evaluate the current estimate every few iterations and record it in the module's history.

    Args:
        every_n_steps: evaluate every this many iterations (``None``: ``per_stage`` per stage).
        per_stage: evaluations spread evenly over each stage (see :func:`evaluation_steps`).
        camera: camera rendered for the PSNR: an index, ``"held_out"`` (the first held-out
            camera, else the first fitted one) or ``None`` (no rendering).
        geometry: compute CD/EMD against the ground-truth clouds when the scene has them.
        emd_points: points per cloud in the EMD (the evaluator's 2048).
        cd_points: points per cloud in the Chamfer distance (the evaluator's 8192).
    """

    def __init__(self, every_n_steps: Optional[int] = None, per_stage: int = 8,
                 camera: Union[int, str, None] = "held_out", geometry: bool = True, emd_points: int = 2048,
                 cd_points: int = 8192):
        super().__init__()
        if every_n_steps is not None and every_n_steps < 1:
            raise ValueError(f"every_n_steps must be >= 1 or None, got {every_n_steps}")
        if per_stage < 0:
            raise ValueError(f"per_stage must be >= 0, got {per_stage}")
        self.every_n_steps = every_n_steps
        self.per_stage = per_stage
        self.camera = camera
        self.geometry = geometry
        self.emd_points = emd_points
        self.cd_points = cd_points
        self._clouds: Optional[list] = None
        self._clouds_loaded = False
        self._steps: Optional[set[int]] = None
        self._geometry_cache: Optional[tuple[bytes, dict]] = None

    # ------------------------------------------------------------------ Lightning hooks
    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if outputs is None or not pl_module.history:
            return
        step = pl_module.curriculum_step
        if pl_module.history[-1].get("step") != step:
            return
        if self._steps is None:
            key = pl_module.material.registry_name or None
            self._steps = set(evaluation_steps(pl_module.curriculum.boundaries(key), self.every_n_steps, self.per_stage))
        if step not in self._steps:
            return
        record = self.evaluate(pl_module)
        pl_module.history[-1].update(record)
        for k, v in record.items():
            if isinstance(v, float) and math.isfinite(v):
                pl_module.log(k, v, on_step=True, on_epoch=False, batch_size=1)

    # ------------------------------------------------------------------ evaluation
    def _ground_truth_clouds(self, module) -> Optional[list]:
        if not self._clouds_loaded:
            from toolkit.evaluation import load_ground_truth_clouds

            self._clouds = load_ground_truth_clouds(module.input.ground_truth, module.input.n_frames) if self.geometry else None
            self._clouds_loaded = True
        return self._clouds

    def _camera(self, module) -> Optional[int]:
        if self.camera is None:
            return None
        if isinstance(self.camera, int):
            return self.camera
        held = module.input.held_out_cameras
        return held[0] if held else module.input.train_cameras[0]

    def _state_key(self, module) -> bytes:
        """Bytes of everything that moves the particles (:func:`toolkit.physics.grid_check.state_key`)."""
        from toolkit.physics.grid_check import state_key

        return state_key(module)

    @torch.no_grad()
    def evaluate(self, module) -> dict:
        """The ``eval/...`` values for the module's current estimate (see the module docstring)."""
        from materials import MaterialError
        from toolkit.metrics import chamfer_sequence, emd_sequence, psnr
        from toolkit.mpm.config import SimulationError

        inp = module.input
        T, n_train = inp.n_frames, inp.n_train
        future = list(range(n_train, T)) or [T - 1]
        out: dict = {}
        try:
            traj = module.predict_trajectory(T)
        except (SimulationError, MaterialError) as err:
            log.warning("periodic evaluation at iteration %d: the prediction failed: %s", module.curriculum_step, err)
            return {"eval/error": f"{type(err).__name__}: {err}"}
        positions = traj["positions"]
        clouds = self._ground_truth_clouds(module)
        if clouds is not None:
            key = self._state_key(module)
            if self._geometry_cache is not None and self._geometry_cache[0] == key:
                out.update(self._geometry_cache[1])  # only the appearance changed since the last evaluation
            else:
                pos = positions.detach().cpu().numpy()
                geo = {}
                cd, _ = chamfer_sequence([pos[t] for t in future], [clouds[t] for t in future], max_points=self.cd_points)
                emd, _ = emd_sequence([pos[t] for t in future], [clouds[t] for t in future], n_points=self.emd_points)
                cd0, _ = chamfer_sequence([pos[0]], [clouds[0]], max_points=self.cd_points)
                emd0, _ = emd_sequence([pos[0]], [clouds[0]], n_points=self.emd_points)
                geo.update({"eval/cd_future": float(cd), "eval/emd_future": float(emd), "eval/cd_x0": float(cd0),
                            "eval/emd_x0": float(emd0)})
                self._geometry_cache = (key, geo)
                out.update(geo)
        cam = self._camera(module)
        if cam is not None:
            deform = traj.get("deformations")
            renders = module.render_frames(traj["means"][future], [cam], None if deform is None else deform[future])
            renders = renders[:, 0].detach().cpu().numpy()  # (F, H, W, 3)
            gt = inp.images[cam, future].numpy().astype(np.float32) / 255.0
            mask = inp.masks[cam, future].numpy().astype(np.float32)[..., None] / 255.0
            values = [psnr(r, g * m) for r, g, m in zip(renders, gt, mask)]
            finite = [v for v in values if math.isfinite(v)]
            out["eval/psnr_future"] = float(np.mean(finite)) if finite else float("nan")
            out["eval/camera"] = int(cam)
        return out

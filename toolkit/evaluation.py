"""Future prediction and the paper's metrics for a fitted physics model.

:func:`evaluate_module` simulates every frame (training and future) with the estimated state,
renders every camera, and computes, exactly as ProJo4D's evaluator (DESIGN section 7,
:mod:`toolkit.metrics`):

* Chamfer distance and EMD between the predicted particles and the ground-truth clouds, per
  frame, averaged over training frames and over future frames;
* PSNR and SSIM against the ground-truth images masked on black, over all cameras, training and
  future frames separately (and for the fitted and the held-out cameras separately);
* parameter errors (log10 for moduli, absolute for nu, friction angle and v0).

Files written to ``out_dir``: ``evaluation.json`` (all numbers, per-frame lists included) and
``prediction.npz`` (``positions`` (T, N, 3), ``means`` (T, G, 3)).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from toolkit.metrics import chamfer_sequence, emd_sequence, image_metrics, split_mean

__all__ = ["evaluate_module", "load_ground_truth_clouds"]


def load_ground_truth_clouds(ground_truth: dict | None, n_frames: int) -> Optional[list[np.ndarray]]:
    """Ground-truth clouds (one (M, 3) array per frame) from a physics input's ground truth."""
    if not ground_truth or not ground_truth.get("point_clouds"):
        return None
    from toolkit.data.ply import read_ply_points

    paths = ground_truth["point_clouds"][:n_frames]
    if len(paths) < n_frames:
        return None
    return [read_ply_points(p) for p in paths]


def _nan_to_none(x):
    if isinstance(x, float) and (math.isnan(x) or math.isinf(x)):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


@torch.no_grad()
def evaluate_module(module, out_dir: str | Path, render: bool = True) -> dict:
    """Predict all frames with ``module`` (a fitted InversePhysicsModule) and compute the metrics.

    Args:
        module: the fitted :class:`~toolkit.physics.InversePhysicsModule`.
        out_dir: where ``evaluation.json`` and ``prediction.npz`` go.
        render: also render every camera and compute PSNR/SSIM (skip for speed).

    Returns:
        The evaluation dict (``None`` for metrics that need a ground truth the scene lacks).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    inp = module.input
    T, n_train = inp.n_frames, inp.n_train
    traj = module.predict_trajectory(T)
    positions = traj["positions"].cpu().numpy()
    means = traj["means"].cpu().numpy()
    np.savez_compressed(out_dir / "prediction.npz", positions=positions, means=means, times=inp.times.numpy())
    result: dict = {"n_frames": T, "n_train": n_train, "estimate": module.estimate(), "errors": module.parameter_errors()}

    clouds = load_ground_truth_clouds(inp.ground_truth, T)
    if clouds is not None:
        cd, cd_frames = chamfer_sequence(list(positions), clouds)
        emd, emd_frames = emd_sequence(list(positions), clouds)
        (cd_tr, cd_fu), (emd_tr, emd_fu) = split_mean(cd_frames, n_train), split_mean(emd_frames, n_train)
        result["geometry"] = {"cd": cd, "cd_train": cd_tr, "cd_future": cd_fu, "cd_per_frame": cd_frames,
                              "emd": emd, "emd_train": emd_tr, "emd_future": emd_fu, "emd_per_frame": emd_frames}
    if render:
        cams = list(range(len(inp.cameras)))
        renders = module.render_frames(traj["means"], cams).cpu().numpy()  # (T, C, H, W, 3)
        preds = np.transpose(renders, (1, 0, 2, 3, 4))
        gts = inp.images.numpy().astype(np.float32) / 255.0
        masks = inp.masks.numpy().astype(np.float32) / 255.0
        result["images"] = {
            "all_cameras": image_metrics(preds, gts, masks, n_train),
            "fitted_cameras": image_metrics(preds[inp.train_cameras], gts[inp.train_cameras], masks[inp.train_cameras], n_train),
        }
        held = inp.held_out_cameras
        if held:
            result["images"]["held_out_cameras"] = image_metrics(preds[held], gts[held], masks[held], n_train)
        np.savez_compressed(out_dir / "renders.npz", renders=(np.clip(renders, 0, 1) * 255).astype(np.uint8))
    result = _nan_to_none(result)
    (out_dir / "evaluation.json").write_text(json.dumps(result, indent=2))
    return result

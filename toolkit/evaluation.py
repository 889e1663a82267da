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

import math
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from toolkit.atomic import write_json, write_with
from toolkit.metrics import CD_MAX_POINTS, EMD_POINTS, chamfer_sequence, emd_per_frame, image_metrics, split_mean

__all__ = ["evaluate_module", "geometry_per_frame", "load_ground_truth_clouds"]


def load_ground_truth_clouds(ground_truth: dict | None, n_frames: int) -> Optional[list[np.ndarray]]:
    """Ground-truth clouds (one (M, 3) array per frame) from a physics input's ground truth."""
    if not ground_truth or not ground_truth.get("point_clouds"):
        return None
    from toolkit.data.ply import read_ply_points

    paths = ground_truth["point_clouds"][:n_frames]
    if len(paths) < n_frames:
        return None
    clouds = [read_ply_points(p) for p in paths]
    if ground_truth.get("to_canonical"):  # stored in the dataset's frame; the fit is in the canonical one
        from toolkit.data.world import RigidTransform

        T = RigidTransform.from_dict(ground_truth["to_canonical"])
        clouds = clouds if T.is_identity else [T.apply_points(c) for c in clouds]
    return clouds


def _nan_to_none(x):
    if isinstance(x, float) and (math.isnan(x) or math.isinf(x)):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


@torch.no_grad()
def geometry_per_frame(positions: Sequence[np.ndarray], clouds: Sequence[np.ndarray],
                       on_frame: Optional[Callable[[int], None]] = None) -> tuple[list[float], list[float]]:
    """Chamfer distance (x1e3) and EMD (m) of every frame: :func:`chamfer_sequence` and
    :func:`emd_per_frame` (one random stream per metric, seeded 0, as the evaluator draws them);
    ``on_frame(t)`` reports progress once frame ``t``'s EMD, the slow part, is known.

    Args:
        positions: T predicted clouds, each (N, 3) metres.
        clouds: T ground-truth clouds, each (M_t, 3) metres.
    """
    if len(positions) != len(clouds):
        raise ValueError(f"{len(positions)} predicted frames but {len(clouds)} ground-truth clouds")
    _, cd = chamfer_sequence(positions, clouds, max_points=CD_MAX_POINTS, seed=0)
    # the EMD's assignments dominate: they run on this run's share of the cores (emd_per_frame)
    emd = emd_per_frame(positions, clouds, n_points=EMD_POINTS, seed=0, fewer="shrink", on_frame=on_frame)
    return cd, emd


def evaluate_module(module, out_dir: str | Path, render: bool = True, progress: bool = True) -> dict:
    """Predict all frames with ``module`` (a fitted InversePhysicsModule) and compute the metrics.

    Args:
        module: the fitted :class:`~toolkit.physics.InversePhysicsModule`.
        out_dir: where ``evaluation.json`` and ``prediction.npz`` go.
        render: also render every camera and compute PSNR/SSIM (skip for speed).
        progress: show a progress bar over the steps (prediction, CD/EMD per frame, rendering per
            frame, image metrics) when stdout is a terminal (:func:`toolkit.progress.bars_enabled`).

    Returns:
        The evaluation dict (``None`` for metrics that need a ground truth the scene lacks).
    """
    from toolkit.progress import step_progress

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    inp = module.input
    T, n_train = inp.n_frames, inp.n_train
    clouds = load_ground_truth_clouds(inp.ground_truth, T)
    steps = 1 + (T if clouds is not None else 0) + (T + 1 if render else 0)
    with step_progress("evaluation", steps, progress) as bar:
        bar.describe(f"predicting {T} frames")
        traj = module.predict_trajectory(T)
        positions = traj["positions"].cpu().numpy()
        means = traj["means"].cpu().numpy()
        write_with(out_dir / "prediction.npz", lambda p: np.savez_compressed(p, positions=positions, means=means, times=inp.times.numpy()))
        result: dict = {"n_frames": T, "n_train": n_train, "estimate": module.estimate(), "errors": module.parameter_errors()}
        bar.advance("CD and EMD, frame 1" if clouds is not None else ("rendering frame 1" if render else None))

        if clouds is not None:
            cd_frames, emd_frames = geometry_per_frame(
                list(positions), clouds, on_frame=lambda t: bar.advance(f"CD and EMD, frame {t + 2}" if t + 1 < T else None))
            cd, emd = float(np.mean(cd_frames)), float(np.mean(emd_frames))
            (cd_tr, cd_fu), (emd_tr, emd_fu) = split_mean(cd_frames, n_train), split_mean(emd_frames, n_train)
            result["geometry"] = {"cd": cd, "cd_train": cd_tr, "cd_future": cd_fu, "cd_per_frame": cd_frames,
                                  "emd": emd, "emd_train": emd_tr, "emd_future": emd_fu, "emd_per_frame": emd_frames}
        if render:
            cams = list(range(len(inp.cameras)))
            frames = []
            for t in range(T):
                bar.describe(f"rendering frame {t + 1}/{T}")
                deform = traj.get("deformations")
                frames.append(module.render_frames(traj["means"][t:t + 1], cams,
                                                   None if deform is None else deform[t:t + 1]).cpu().numpy())
                bar.advance()
            renders = np.concatenate(frames)  # (T, C, H, W, 3)
            bar.describe("PSNR and SSIM")
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
            frames8 = (np.clip(renders, 0, 1) * 255).astype(np.uint8)
            write_with(out_dir / "renders.npz", lambda p: np.savez_compressed(p, renders=frames8))
            bar.advance("done")
    result = _nan_to_none(result)
    write_json(out_dir / "evaluation.json", result)
    return result

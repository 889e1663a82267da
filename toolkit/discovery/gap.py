"""The gap between a model and the measurements: future-frame metrics of a library-model state.

:func:`evaluate_state` predicts every frame (training and future) from a
:class:`~toolkit.discovery.library.LibraryModel` state and computes what
:func:`toolkit.evaluation.evaluate_module` computes (same metric functions, DESIGN section 7):
Chamfer distance and EMD against the ground-truth clouds (when the scene has them), PSNR and
SSIM of every camera against the masked images, split into training and future frames, plus
the fit's image loss on the held-out cameras. "The gap" of the discovery report is the
future-frame Chamfer distance (and EMD, PSNR) before and after adding the discovered effect.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch

from toolkit.discovery.library import LibraryModel
from toolkit.metrics import chamfer_sequence, emd_sequence, image_metrics, split_mean

__all__ = ["evaluate_state", "gap_shrink", "ground_truth_clouds"]


def ground_truth_clouds(lib: LibraryModel) -> Optional[list[np.ndarray]]:
    """The scene's ground-truth clouds (one (M, 3) array per frame), or ``None``."""
    from toolkit.evaluation import load_ground_truth_clouds

    return load_ground_truth_clouds(lib.input.ground_truth, lib.input.n_frames)


@torch.no_grad()
def evaluate_state(lib: LibraryModel, q: np.ndarray, clouds: Optional[Sequence[np.ndarray]] = None,
                   emd: bool = True) -> dict:
    """Metrics of the state ``q`` over every frame.

    Args:
        lib: the library model.
        q: library parameters.
        clouds: ground-truth clouds per frame (:func:`ground_truth_clouds`), or ``None``.
        emd: also compute the EMD (exact assignment; the slowest metric).

    Returns:
        ``cd_future``, ``cd_train``, ``cd_per_frame`` (x 1e3, as the evaluator),
        ``emd_future``, ``emd_per_frame`` (m), ``psnr_future``, ``ssim_future``,
        ``psnr_per_frame`` (all cameras), ``psnr_future_held_out``, ``held_out_loss_train``,
        ``held_out_loss_future`` and ``held_out_loss_per_frame`` (the fit's image loss on the
        held-out cameras); geometric entries are ``None`` without ground truth.
    """
    inp = lib.input
    T, n_train = inp.n_frames, inp.n_train
    pred = lib.predict(q, T)
    positions = pred["positions"].cpu().numpy()
    out: dict = {}
    if clouds is not None:
        cd, per = chamfer_sequence(list(positions), list(clouds))
        _, cd_fu = split_mean(per, n_train)
        out.update(cd_future=cd_fu, cd_train=split_mean(per, n_train)[0], cd_per_frame=per)
        if emd:
            _, eper = emd_sequence(list(positions), list(clouds))
            out.update(emd_future=split_mean(eper, n_train)[1], emd_per_frame=eper)
    else:
        out.update(cd_future=None, cd_train=None, cd_per_frame=None, emd_future=None, emd_per_frame=None)
    cams = list(range(len(inp.cameras)))
    renders = lib.render(q, pred["means"], cams, pred.get("deformations")).clamp(0, 1).cpu().numpy()  # (T, C, H, W, 3)
    preds = np.transpose(renders, (1, 0, 2, 3, 4))
    gts = inp.images.numpy().astype(np.float32) / 255.0
    masks = inp.masks.numpy().astype(np.float32) / 255.0
    im = image_metrics(preds, gts, masks, n_train)
    out.update(psnr_future=im["psnr_future"], ssim_future=im["ssim_future"], psnr_train=im["psnr_train"],
               psnr_per_frame=im["psnr_per_frame"])
    held = inp.held_out_cameras
    if held:
        hm = image_metrics(preds[held], gts[held], masks[held], n_train)
        out["psnr_future_held_out"] = hm["psnr_future"]
        losses = lib.image_losses(q, list(range(T)), held).numpy()  # (T, C)
        per_frame = losses.mean(1)
        out["held_out_loss_per_frame"] = per_frame.tolist()
        out["held_out_loss_train"] = float(per_frame[:n_train].mean())
        out["held_out_loss_future"] = float(per_frame[n_train:].mean()) if T > n_train else float("nan")
    return out


def gap_shrink(before: Optional[float], after: Optional[float], floor: Optional[float] = None) -> Optional[float]:
    """Fraction of the gap removed: ``1 - after / before`` (or ``1 - (after - floor) / (before - floor)``
    with a floor); ``None`` when undefined."""
    if before is None or after is None or not np.isfinite(before) or not np.isfinite(after):
        return None
    f = 0.0 if floor is None else float(floor)
    if before - f <= 0:
        return None
    return float(1.0 - (after - f) / (before - f))

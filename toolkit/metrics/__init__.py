"""Evaluation metrics computed as ProJo4D's evaluator does, so numbers compare with the paper.

* geometry: :func:`chamfer_distance`, :func:`earth_movers_distance` (+ sequence versions) and the
  differentiable :func:`chamfer_loss` used as the geometric training loss;
* image: :func:`psnr`, :func:`ssim` (3DGS definition), the differentiable :func:`ssim_torch`,
  :func:`mask_on_black` and :func:`image_metrics` (training vs future frames);
* parameters: :func:`parameter_errors` (log10 errors for moduli, absolute otherwise).
"""

from toolkit.metrics.geometry import (
    CD_MAX_POINTS,
    EMD_POINTS,
    chamfer_distance,
    chamfer_loss,
    chamfer_sequence,
    earth_movers_distance,
    emd_per_frame,
    mean_nearest_distance,
    emd_sequence,
    split_mean,
)
from toolkit.metrics.image import gaussian_window, image_metrics, mask_on_black, psnr, ssim, ssim_torch
from toolkit.metrics.parameters import (
    LOG_PARAMS,
    PARAM_ALIASES,
    canonical_param_name,
    parameter_errors,
)

__all__ = [
    "CD_MAX_POINTS",
    "EMD_POINTS",
    "LOG_PARAMS",
    "PARAM_ALIASES",
    "canonical_param_name",
    "chamfer_distance",
    "chamfer_loss",
    "chamfer_sequence",
    "earth_movers_distance",
    "emd_per_frame",
    "mean_nearest_distance",
    "emd_sequence",
    "gaussian_window",
    "image_metrics",
    "mask_on_black",
    "parameter_errors",
    "psnr",
    "split_mean",
    "ssim",
    "ssim_torch",
]

"""Image metrics: PSNR and SSIM as ProJo4D's evaluator computes them, and a differentiable SSIM.

Conventions: images are channel-last, (H, W, C) or (B, H, W, C), float values in [0, 1], numpy
arrays or torch tensors. Ground truth is the masked image composited on black
(:func:`mask_on_black`); predictions are rendered on black.

* **SSIM** is the 3D Gaussian Splatting definition (``utils/loss_utils.py::ssim``): 11 x 11
  Gaussian window with sigma = 1.5, per-channel (depthwise) filtering with *zero* padding of 5
  (``F.conv2d(padding=5)``), C1 = 0.01^2, C2 = 0.03^2 (data range 1), population statistics,
  mean over all pixels and channels. scikit-image (reflect padding, crops the border) and kornia
  (reflect padding) agree with it exactly away from the 5-pixel border and differ near it.
* **PSNR** per image is ``-10 log10(MSE)``. ProJo4D's evaluator calls the 3DGS ``psnr`` on a
  (C, H, W) tensor, whose ``view(C, -1)`` makes the MSE *per channel*; it then averages the
  per-channel PSNRs. That is the default here (``per_channel=True``) so numbers compare with the
  paper; ``per_channel=False`` gives the textbook whole-image PSNR. Both agree when the three
  channels have the same MSE.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["psnr", "ssim", "ssim_torch", "mask_on_black", "image_metrics", "gaussian_window"]

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def _as_bhwc(x, name: str, numpy_dtype=np.float32) -> torch.Tensor:
    """(H, W, C) or (B, H, W, C) numpy/torch -> (B, H, W, C) float tensor (numpy -> numpy_dtype)."""
    if not isinstance(x, torch.Tensor):
        x = torch.from_numpy(np.asarray(x, dtype=numpy_dtype))
    elif not x.is_floating_point():
        x = x.double()
    if x.ndim == 3:
        x = x.unsqueeze(0)
    if x.ndim != 4:
        raise ValueError(f"{name} must be (H, W, C) or (B, H, W, C), got shape {tuple(x.shape)}")
    return x


def _pair(img, gt, numpy_dtype=np.float32) -> tuple[torch.Tensor, torch.Tensor]:
    x, y = _as_bhwc(img, "img", numpy_dtype), _as_bhwc(gt, "gt", numpy_dtype)
    if x.shape != y.shape:
        raise ValueError(f"img and gt shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
    dtype = torch.promote_types(x.dtype, y.dtype)
    return x.to(dtype), y.to(device=x.device, dtype=dtype)


def gaussian_window(
    window_size: int = 11, sigma: float = 1.5, *, dtype=torch.float32, device=None
) -> torch.Tensor:
    """Normalised 2D Gaussian window (window_size, window_size), the outer product of 1D ones."""
    x = torch.arange(window_size, dtype=torch.float64) - window_size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return torch.outer(g, g).to(dtype=dtype, device=device)


def ssim_torch(
    img: torch.Tensor,
    gt: torch.Tensor,
    *,
    window_size: int = 11,
    sigma: float = 1.5,
    reduction: Literal["mean", "none"] = "mean",
) -> torch.Tensor:
    """Differentiable SSIM, 3DGS definition (see the module docstring).

    Args:
        img: (H, W, C) or (B, H, W, C) tensor in [0, 1]; usable as a loss via ``1 - ssim``.
        gt: Same shape as ``img``.
        window_size: Side of the Gaussian window (odd); zero padding of ``window_size // 2``.
        sigma: Standard deviation of the window, pixels.
        reduction: ``"mean"`` -> scalar mean over all pixels, channels and images;
            ``"none"`` -> the SSIM map, (B, H, W, C) (a batch of one for (H, W, C) input).

    Returns:
        Scalar tensor or SSIM map.
    """
    x, y = _pair(img, gt)
    x = x.permute(0, 3, 1, 2)
    y = y.permute(0, 3, 1, 2)
    channels = x.shape[1]
    w = gaussian_window(window_size, sigma, dtype=x.dtype, device=x.device)
    w = w.expand(5 * channels, 1, window_size, window_size).contiguous()
    # one depthwise convolution filters all five maps: x, y, x^2, y^2, xy
    stats = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    blurred = F.conv2d(stats, w, padding=window_size // 2, groups=5 * channels)
    mu_x, mu_y, e_xx, e_yy, e_xy = blurred.split(channels, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x = e_xx - mu_xx
    var_y = e_yy - mu_yy
    cov = e_xy - mu_xy
    ssim_map = ((2 * mu_xy + SSIM_C1) * (2 * cov + SSIM_C2)) / (
        (mu_xx + mu_yy + SSIM_C1) * (var_x + var_y + SSIM_C2)
    )
    if reduction == "none":
        return ssim_map.permute(0, 2, 3, 1)
    if reduction == "mean":
        return ssim_map.mean()
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


def ssim(img, gt) -> float:
    """SSIM (3DGS definition) of one image or the mean over a batch of equally sized images.

    Args:
        img: (H, W, C) or (B, H, W, C) numpy array or tensor in [0, 1].
        gt: Same shape.

    Returns:
        Mean SSIM over pixels, channels and images. Numpy input is evaluated in float32 (as the
        evaluator does on the GPU; float64 convolutions are ~50x slower on CPU); pass float64
        tensors for a float64 evaluation.
    """
    with torch.no_grad():
        return float(ssim_torch(img, gt))


def psnr(img, gt, *, per_channel: bool = True) -> float:
    """PSNR in dB for images in [0, 1] (peak 1), averaged over the batch.

    Args:
        img: (H, W, C) or (B, H, W, C) numpy array or tensor.
        gt: Same shape.
        per_channel: ``True`` (default, ProJo4D's evaluator): MSE per image and channel, the
            PSNRs averaged over channels and images. ``False``: MSE over the whole image.

    Returns:
        PSNR in dB; ``inf`` for identical images.
    """
    with torch.no_grad():
        x, y = _pair(img, gt, np.float64)
        err = (x.double() - y.double()) ** 2
        mse = err.mean(dim=(1, 2)) if per_channel else err.mean(dim=(1, 2, 3))
        values = [-10.0 * math.log10(m) if m > 0 else math.inf for m in mse.flatten().tolist()]
    return float(np.mean(values))


def mask_on_black(image, mask):
    """Composite an image on black: ``image * mask``.

    Args:
        image: (..., H, W, C) numpy array or tensor.
        mask: (..., H, W) or (..., H, W, 1) in [0, 1] (soft masks blend towards black).

    Returns:
        Masked image of the same type and shape as ``image``.
    """
    if isinstance(image, torch.Tensor) and not isinstance(mask, torch.Tensor):
        mask = torch.as_tensor(np.asarray(mask), dtype=image.dtype, device=image.device)
    elif not isinstance(image, torch.Tensor) and isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    if mask.shape == image.shape[:-1]:
        mask = mask[..., None]
    if mask.shape[:-1] != image.shape[:-1] or mask.shape[-1] != 1:
        raise ValueError(
            f"mask shape {tuple(mask.shape)} does not fit image shape {tuple(image.shape)}"
        )
    return image * mask


def image_metrics(
    preds: Sequence,
    gts: Sequence,
    masks: Sequence | None,
    frame_split: int,
    *,
    per_channel_psnr: bool = True,
) -> dict[str, float | list[float]]:
    """PSNR and SSIM over every (camera, frame) image, split into training and future frames.

    Args:
        preds: Rendered images indexed ``[camera][frame]``, each (H, W, 3) on black; a
            (C, T, H, W, 3) array works too.
        gts: Ground-truth images, same indexing.
        masks: Object masks ``[camera][frame]``, each (H, W), applied to ``gts`` with
            :func:`mask_on_black`; ``None`` if ``gts`` are already on black.
        frame_split: ``n_train``: frames ``[0, n_train)`` are training frames, the rest future.
        per_channel_psnr: See :func:`psnr`.

    Returns:
        ``psnr_train``, ``psnr_future``, ``ssim_train``, ``ssim_future`` (means over all cameras
        and the frames of the part; ``nan`` for a part without frames), ``psnr``/``ssim`` (over
        all frames), and ``psnr_per_frame``/``ssim_per_frame`` (lists of T means over cameras).
    """
    n_cams = len(preds)
    if len(gts) != n_cams or (masks is not None and len(masks) != n_cams):
        raise ValueError("preds, gts and masks must have the same number of cameras")
    if n_cams == 0:
        raise ValueError("no cameras to evaluate")
    n_frames = len(preds[0])
    psnrs = np.full((n_cams, n_frames), np.nan)
    ssims = np.full((n_cams, n_frames), np.nan)
    for c in range(n_cams):
        lengths = {len(preds[c]), len(gts[c])} | ({len(masks[c])} if masks is not None else set())
        if lengths != {n_frames}:
            raise ValueError(f"camera {c} has frame counts {sorted(lengths)}, expected {n_frames}")
        for t in range(n_frames):
            gt = gts[c][t] if masks is None else mask_on_black(gts[c][t], masks[c][t])
            psnrs[c, t] = psnr(preds[c][t], gt, per_channel=per_channel_psnr)
            ssims[c, t] = ssim(preds[c][t], gt)

    def part(values: np.ndarray) -> float:
        return float(values.mean()) if values.size else float("nan")

    return {
        "psnr_train": part(psnrs[:, :frame_split]),
        "psnr_future": part(psnrs[:, frame_split:]),
        "ssim_train": part(ssims[:, :frame_split]),
        "ssim_future": part(ssims[:, frame_split:]),
        "psnr": part(psnrs),
        "ssim": part(ssims),
        "psnr_per_frame": psnrs.mean(axis=0).tolist(),
        "ssim_per_frame": ssims.mean(axis=0).tolist(),
    }

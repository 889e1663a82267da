"""Reading images and masks from disk as float arrays in [0, 1]."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from toolkit.data.errors import DatasetError, require_file

__all__ = ["image_size", "read_raw", "to_unit", "rgb_of", "alpha_of", "mask_of"]


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file, from its header only."""
    require_file(path, "an image")
    try:
        with Image.open(path) as im:
            return im.size
    except OSError as exc:
        raise DatasetError(f"cannot read image {path}: {exc}") from None


def read_raw(path: Path) -> np.ndarray:
    """Decoded pixels, (H, W) or (H, W, C), in the file's integer dtype."""
    require_file(path, "an image")
    try:
        with Image.open(path) as im:
            if im.mode in ("P", "PA"):
                im = im.convert("RGBA")
            elif im.mode == "I;16":
                return np.asarray(im, dtype=np.uint16)
            return np.asarray(im)
    except OSError as exc:
        raise DatasetError(f"cannot read image {path}: {exc}") from None


def to_unit(arr: np.ndarray) -> np.ndarray:
    """Integer pixels -> float32 in [0, 1] (divided by the dtype's maximum); floats unchanged."""
    if np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.float32) / np.float32(np.iinfo(arr.dtype).max)
    if arr.dtype == bool:
        return arr.astype(np.float32)
    return arr.astype(np.float32)


def rgb_of(arr: np.ndarray) -> np.ndarray:
    """(H, W, 3) colour channels of a gray, gray+alpha, RGB or RGBA array (alpha dropped)."""
    if arr.ndim == 2:
        return np.repeat(arr[..., None], 3, axis=-1)
    if arr.shape[-1] in (1, 2):
        return np.repeat(arr[..., :1], 3, axis=-1)
    return arr[..., :3]


def alpha_of(arr: np.ndarray) -> np.ndarray | None:
    """(H, W) alpha channel of a gray+alpha or RGBA array, None if there is none."""
    if arr.ndim == 3 and arr.shape[-1] in (2, 4):
        return arr[..., -1]
    return None


def mask_of(arr: np.ndarray) -> np.ndarray:
    """(H, W) float32 mask in [0, 1] from a mask file's pixels: its alpha channel if any, else
    its value (the mean of the colour channels for an RGB file)."""
    a = alpha_of(arr)
    if a is not None:
        return to_unit(a)
    unit = to_unit(arr)
    if unit.ndim == 2:
        return unit
    return unit[..., :3].mean(axis=-1) if unit.shape[-1] >= 3 else unit[..., 0]

"""Files of the PAC-NeRF layout as this generator writes them.

::

    <scene>/all_data.json              list of {"file_path": "./data/r_{cam}_{frame}.png", "time": s,
                                        "c2w": 4x4 OpenGL camera-to-world, "intrinsic": 3x3}
    <scene>/data/r_{cam}_{frame}.png   RGBA, straight alpha = object coverage (frames 0..T-1)
    <scene>/data/r_{cam}_-1.png        RGB background plate (the scene without the object)
    <scene>/gt_points/frame_{t:03d}.ply  ground-truth particles of frame t (binary float32)
    <scene>/ground_truth.json          see toolkit.data.ground_truth (written last: its presence
                                        marks a complete scene)

PNG files are written with Pillow without metadata, so identical pixels give identical bytes.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from PIL import Image

from toolkit.cameras import Cameras

__all__ = ["image_name", "write_png", "all_data_entries", "write_json", "clear_scene_outputs"]


def image_name(cam: int, frame: int) -> str:
    """``r_{cam}_{frame}.png`` (frame -1 is the background plate)."""
    return f"r_{cam}_{frame}.png"


def write_png(path: Path, pixels: np.ndarray) -> Path:
    """Write (H, W, 3) or (H, W, 4) uint8 pixels as PNG (no metadata, deterministic bytes)."""
    arr = np.ascontiguousarray(pixels)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ValueError(f"expected (H, W, 3|4) uint8 pixels, got {arr.dtype} {arr.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr, "RGBA" if arr.shape[2] == 4 else "RGB").save(path, format="PNG", optimize=False, compress_level=6)
    return path


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """float [0, 1] -> uint8 (rounded)."""
    return np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def all_data_entries(cameras: Cameras, times: np.ndarray, with_plates: bool = True) -> list[dict]:
    """``all_data.json`` entries: per camera, the plate (frame -1) then frames 0..T-1.

    Args:
        cameras: B cameras.
        times: (T,) frame times, seconds.
        with_plates: list the background plates (time ``-1 / fps``).
    """
    c2w = cameras.c2w_opengl().detach().cpu().double().numpy()
    K = cameras.K.detach().cpu().double().numpy()
    dt = float(times[1] - times[0]) if len(times) > 1 else 0.0
    entries = []
    for c in range(len(cameras)):
        frames = ([-1] if with_plates else []) + list(range(len(times)))
        for f in frames:
            entries.append(
                {
                    "file_path": f"./data/{image_name(c, f)}",
                    "time": float(times[f]) if f >= 0 else -dt,
                    "c2w": c2w[c].tolist(),
                    "intrinsic": K[c].tolist(),
                }
            )
    return entries


def write_json(path: Path, data) -> Path:
    """Write JSON atomically (indent 2, trailing newline)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def clear_scene_outputs(root: Path) -> None:
    """Remove files a previous generation wrote into ``root`` (only this layout's names), so a
    scene regenerated with fewer cameras or frames leaves nothing stale behind."""
    for name in ("ground_truth.json", "all_data.json"):
        (root / name).unlink(missing_ok=True)
    for folder, pattern in (("data", "r_*_*.png"), ("gt_points", "frame_*.ply")):
        for p in sorted((root / folder).glob(pattern)):
            p.unlink()

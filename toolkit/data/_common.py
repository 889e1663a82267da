"""Helpers shared by the dataset readers."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from toolkit.data.errors import DatasetError
from toolkit.metrics.parameters import canonical_param_name

# Numeric entries of the public parameter files that describe the setup, not the material.
_SETUP_KEYS = {
    "rho", "density", "hit_frame", "n_frames", "dt", "frame_dt", "fps", "id", "world_scale", "yms_sim",
}

_NUMBERED_PLY = re.compile(r"^(\d+)\.ply$")


def matrix(value, path: Path, where: str, shapes: tuple[tuple[int, ...], ...]) -> np.ndarray:
    """A numeric matrix field of one of ``shapes``, or a :class:`DatasetError` naming it."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {where} must be a numeric matrix, got {value!r:.80}") from None
    if arr.shape not in shapes:
        want = " or ".join("x".join(map(str, s)) for s in shapes)
        raise DatasetError(f"{path}: {where} must be {want}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise DatasetError(f"{path}: {where} has non-finite values")
    return arr


def matrix_field(mapping, key: str, path: Path, where: str, shapes: tuple[tuple[int, ...], ...]) -> np.ndarray:
    """``matrix(mapping[key])`` with errors naming the file, the entry and the field."""
    from toolkit.data.errors import field

    return matrix(field(mapping, key, path, where), path, f"{where} field {key!r}", shapes)


def frame_grid(
    found: dict[int, dict[int, Path]], names: dict[int, str], expected: callable, source: Path
) -> list[list[Path]]:
    """``[camera][frame]`` paths for frames ``0..T-1`` (T = 1 + the largest frame of any camera).

    Args:
        found: camera id -> frame -> path, as discovered.
        names: camera id -> the dataset's name of the camera (for messages).
        expected: ``(camera id, frame) -> Path`` of a frame that should exist (for messages).
        source: The file or folder the frames were discovered in.

    Raises:
        DatasetError: naming the camera and frame of the first gap.
    """
    if not any(found.values()):
        raise DatasetError(f"{source}: no frames found")
    n_frames = 1 + max(max(frames) for frames in found.values() if frames)
    grid = []
    for cam in sorted(found):
        row = []
        for t in range(n_frames):
            if t not in found[cam]:
                raise DatasetError(
                    f"{source}: camera {names[cam]} has no frame {t} (the scene has frames "
                    f"0..{n_frames - 1}); expected {expected(cam, t)}"
                )
            row.append(found[cam][t])
        grid.append(row)
    return grid


def numbered_plys(folder: Path) -> list[Path]:
    """``NNN.ply`` files of a folder in numeric order (empty if the folder does not exist)."""
    if not folder.is_dir():
        return []
    hits = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _NUMBERED_PLY.match(p.name))]
    return [p for _, p in sorted(hits)]


def fps_from_times(times: np.ndarray, default: float) -> float:
    """Frames per second from frame times (median spacing), ``default`` if undetermined."""
    if len(times) > 1:
        dt = float(np.median(np.diff(times)))
        if dt > 0:
            return 1.0 / dt
    return default


def ground_truth_from_flat(values: dict, *, material: str | None, point_clouds: list[Path]):
    """A :class:`GroundTruth` from a public dataset's flat parameter dict.

    Keys are mapped with :func:`canonical_param_name`; ``v0``/``gravity`` vectors go to their
    fields, numeric material parameters to ``params``, everything else to ``extra``.
    """
    from toolkit.data.scene import GroundTruth

    gt = GroundTruth(material=material, point_clouds=list(point_clouds))
    for key, value in values.items():
        name = canonical_param_name(key)
        if name in ("v0", "gravity") and isinstance(value, (list, tuple)) and len(value) == 3:
            setattr(gt, name, [float(v) for v in value])
        elif (
            name not in _SETUP_KEYS
            and isinstance(value, (int, float))
            and not isinstance(value, bool)
        ):
            gt.params[name] = float(value)
        else:
            gt.extra[key] = value
    return gt

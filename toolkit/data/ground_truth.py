"""``ground_truth.json``: the ground truth this project's synthetic generator writes.

The file sits next to ``all_data.json`` (PAC-NeRF layout). Schema, version 1::

    {
      "format": "projo4d-ground-truth",     # required, exactly this string
      "version": 1,                          # required; readers reject newer versions
      "material": "neo_hookean",             # material registry name, or null
      "params": {"E": 1e5, "nu": 0.3},       # toolkit parameter names, SI units, angles in degrees
      "v0": [0.0, -1.0, 0.0],                # initial velocity, m/s, or null
      "gravity": [0.0, -9.8, 0.0],           # m/s^2, or null
      "effects": {"ground_friction": {"mu": 0.3}},   # effect name -> parameters ({} if none)
      "density": 1000,                       # kg/m^3 (optional)
      "point_clouds": ["gt_points/frame_000.ply", ...],  # per frame, relative to this file
      "simulation": {...}                    # optional, free-form (dx, substeps, ...)
    }

Any further top-level key is kept in :attr:`GroundTruth.extra` and written back unchanged
(``density`` and ``simulation`` land there too).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from toolkit.data.errors import DatasetError, load_json
from toolkit.data.scene import GroundTruth

__all__ = ["GROUND_TRUTH_FORMAT", "GROUND_TRUTH_VERSION", "read_ground_truth", "write_ground_truth"]

GROUND_TRUTH_FORMAT = "projo4d-ground-truth"
GROUND_TRUTH_VERSION = 1
_RESERVED = {"format", "version", "material", "params", "v0", "gravity", "effects", "point_clouds"}


def _vector(value, path: Path, name: str) -> list[float] | None:
    if value is None:
        return None
    try:
        vec = [float(v) for v in value]
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: field {name!r} must be a list of 3 numbers or null, got {value!r}") from None
    if len(vec) != 3:
        raise DatasetError(f"{path}: field {name!r} must have 3 entries, got {len(vec)}")
    return vec


def read_ground_truth(path: str | Path) -> GroundTruth:
    """Read a ``ground_truth.json`` (schema in the module docstring).

    Point-cloud paths are resolved relative to the file's folder; files are not opened.

    Raises:
        DatasetError: Missing file, malformed JSON, wrong format/version, or a malformed field.
    """
    path = Path(path)
    data = load_json(path, "the synthetic ground truth (ground_truth.json)")
    if not isinstance(data, dict) or data.get("format") != GROUND_TRUTH_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise DatasetError(f"{path}: field 'format' must be {GROUND_TRUTH_FORMAT!r}, got {got!r}")
    version = data.get("version")
    if not isinstance(version, int) or not 1 <= version <= GROUND_TRUTH_VERSION:
        raise DatasetError(
            f"{path}: field 'version' must be an integer 1..{GROUND_TRUTH_VERSION}, got {version!r}"
        )
    params = data.get("params") or {}
    if not isinstance(params, dict):
        raise DatasetError(f"{path}: field 'params' must be an object, got {type(params).__name__}")
    for key, value in params.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise DatasetError(f"{path}: field 'params.{key}' must be a number, got {value!r}")
    effects = data.get("effects") or {}
    if not isinstance(effects, dict) or not all(isinstance(v, dict) for v in effects.values()):
        raise DatasetError(f"{path}: field 'effects' must map effect names to objects")
    clouds = data.get("point_clouds") or []
    if not isinstance(clouds, list) or not all(isinstance(p, str) for p in clouds):
        raise DatasetError(f"{path}: field 'point_clouds' must be a list of file paths")
    material = data.get("material")
    if material is not None and not isinstance(material, str):
        raise DatasetError(f"{path}: field 'material' must be a string or null, got {material!r}")
    return GroundTruth(
        material=material,
        params={k: float(v) for k, v in params.items()},
        v0=_vector(data.get("v0"), path, "v0"),
        gravity=_vector(data.get("gravity"), path, "gravity"),
        effects={k: dict(v) for k, v in effects.items()},
        point_clouds=[path.parent / p for p in clouds],
        extra={k: v for k, v in data.items() if k not in _RESERVED},
    )


def _plain(value):
    """numpy scalars/arrays and Paths -> JSON types; non-finite floats are rejected."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return _plain(value.item())
    if isinstance(value, Path):
        return value.as_posix()
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"ground truth holds a non-finite number {value}")
    return value


def write_ground_truth(path: str | Path, gt: GroundTruth) -> Path:
    """Write ``gt`` as ``ground_truth.json`` (schema in the module docstring); returns the path.

    Point-cloud paths inside the file's folder are stored relative to it (POSIX separators),
    others absolute. ``gt.extra`` keys become top-level keys and must not shadow schema fields.
    """
    path = Path(path)
    clash = _RESERVED & set(gt.extra)
    if clash:
        raise ValueError(f"GroundTruth.extra must not contain schema fields {sorted(clash)}")
    base = path.parent.resolve()
    clouds = []
    for p in gt.point_clouds:
        full = (path.parent / p).resolve() if not Path(p).is_absolute() else Path(p).resolve()
        try:
            clouds.append(full.relative_to(base).as_posix())
        except ValueError:
            clouds.append(full.as_posix())
    doc = {
        "format": GROUND_TRUTH_FORMAT,
        "version": GROUND_TRUTH_VERSION,
        "material": gt.material,
        "params": _plain(gt.params),
        "v0": _plain(gt.v0),
        "gravity": _plain(gt.gravity),
        "effects": _plain(gt.effects),
        "point_clouds": clouds,
        **_plain(gt.extra),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)
    return path

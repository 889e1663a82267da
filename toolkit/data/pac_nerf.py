"""Reader for the PAC-NeRF layout (also what this project's synthetic generator writes).

Layout (facts from xuan-li/PAC-NeRF ``train.py::load_data`` and the GIC/ProJo4D readers
``scene/dataset_readers.py::readCamerasFromAllData``, ``prepare_pacnerf_data.py``,
``train_projo4d.py::load_gt_params``, ``utils/data_utils.py::load_gt_pcds``)::

    <scene>/all_data.json        list of {"file_path": "data/r_{cam}_{frame}.png", "time": s,
                                  "c2w": 3x4 or 4x4 OpenGL camera-to-world, "intrinsic": 3x3}
    <scene>/data/r_{cam}_{frame}.png   frames 0..T-1 of camera cam
    <scene>/data/r_{cam}_-1.png        background plate of camera cam (no object)
    <scene>/data/r_{cam}_-2.png        optional loss-exclusion mask: PAC-NeRF drops the pixels
                                       whose alpha > 50 from the image loss
    <scene>/data/a_{cam}_{frame}.png   optional RGBA with the object alpha (written by GIC's
                                       matting preprocessing, with m_{cam}_{frame}.png on white)
    <scene>/ground_truth.json          this project's synthetic ground truth (optional)
    <scene>/world.json                 optional world of the scene (gravity, ground plane, fps;
                                       :func:`toolkit.data.world.load_world`); default below
    <scene>/../<material>.json         public PAC-NeRF ground truth, keyed by scene folder name
                                       ("0", "1", ...); keys E, nu, mu, kappa, ys, eta, fa, v
    <root>/simulation_data/<material>/<scene>/NNN.ply   public ground-truth particles, found by
                                       replacing the path component "pacnerf" by "simulation_data"

World: PAC-NeRF's own, which is the canonical one: gravity (0, -9.8, 0) m/s^2, ground plane
y = 0 with normal +y, frames 1/24 s apart (xuan-li/PAC-NeRF ``configs/default.py``: ``gravity``,
``BC = {"ground": [[0, 0, 0], [0, 1, 0]]}``, ``frame_dt = 1/24``). The frame times themselves come
from ``all_data.json``.

Masks: the ``a_`` files when every frame has one; else the images' alpha channel when the first
image has a non-constant one; else the difference to the background plate (PAC-NeRF itself
mattes against that plate with a neural network; the threshold rule here is a plain fallback).
"""

from __future__ import annotations

import re
from pathlib import Path, PurePosixPath

import numpy as np

from toolkit.cameras import Cameras
from toolkit.data._common import frame_grid, fps_from_times, ground_truth_from_flat, matrix, numbered_plys
from toolkit.data.errors import DatasetError, field, load_json, require_file
from toolkit.data.ground_truth import read_ground_truth
from toolkit.data.images import alpha_of, image_size, read_raw
from toolkit.data.scene import GroundTruth, MultiViewScene
from toolkit.data.world import World, check_frame_rate, into_canonical_world, load_world

__all__ = ["PAC_NERF_WORLD", "read_pac_nerf", "camera_and_frame"]

_FILE = re.compile(r"^r_(\d+)_(-?\d+)(\.png)?$")
_MATERIALS = {
    "elastic": "neo_hookean",
    "newtonian": "newtonian",
    "non_newtonian": "non_newtonian",
    "plasticine": "plasticine",
    "sand": "sand",
}
_TIME_TOL = 1e-4  # seconds; frame times of different cameras must agree to this

#: PAC-NeRF's world (xuan-li/PAC-NeRF configs/default.py: gravity, BC "ground", frame_dt = 1/24).
PAC_NERF_WORLD = World(
    gravity=(0.0, -9.8, 0.0), ground_point=(0.0, 0.0, 0.0), ground_normal=(0.0, 1.0, 0.0), fps=None,
    source="PAC-NeRF (xuan-li/PAC-NeRF configs/default.py: gravity [0,-9.8,0], ground [[0,0,0],[0,1,0]])",
)


def camera_and_frame(file_path: str) -> tuple[int, int] | None:
    """``(camera, frame)`` of an ``all_data.json`` ``file_path`` (``data/r_<camera>_<frame>[.png]``),
    or ``None`` when its name does not follow that pattern."""
    match = _FILE.match(PurePosixPath(str(file_path)).name)
    return None if match is None else (int(match.group(1)), int(match.group(2)))


def read_pac_nerf(root: str | Path, *, verify_sizes: bool = True) -> MultiViewScene:
    """Read a PAC-NeRF-layout scene (see the module docstring).

    Args:
        root: Scene folder holding ``all_data.json``.
        verify_sizes: Check every image's size from its header (cheap; catches mixed sizes).

    Raises:
        DatasetError: Missing or malformed files, gaps in the frames, moving cameras, mixed
            image sizes.
    """
    root = Path(root)
    index = root / "all_data.json"
    entries = load_json(index, "the PAC-NeRF frame list (all_data.json)")
    if not isinstance(entries, list):
        raise DatasetError(f"{index}: expected a JSON list of frames, got {type(entries).__name__}")

    frames: dict[int, dict[int, Path]] = {}
    times: dict[int, dict[int, float]] = {}
    c2w: dict[int, np.ndarray] = {}
    intrinsics: dict[int, np.ndarray] = {}
    plates: dict[int, Path] = {}
    exclusions: dict[int, Path] = {}
    for i, entry in enumerate(entries):
        file_path = field(entry, "file_path", index, f"entry {i}")
        match = _FILE.match(PurePosixPath(str(file_path)).name)
        if match is None:
            raise DatasetError(
                f"{index}: entry {i} field 'file_path' is {file_path!r}, expected data/r_{{camera}}_{{frame}}.png"
            )
        cam, frame = int(match.group(1)), int(match.group(2))
        rel = str(file_path) if match.group(3) else f"{file_path}.png"
        path = root / rel
        where = f"entry {i} ({file_path})"
        if frame == -1:
            plates[cam] = path
            continue
        if frame == -2:
            exclusions[cam] = path
            continue
        if frame < 0:
            raise DatasetError(f"{index}: {where}: frame {frame} is not a frame, a plate (-1) or a mask (-2)")
        if frame in frames.get(cam, {}):
            raise DatasetError(f"{index}: {where}: camera {cam}, frame {frame} is listed twice")
        pose = matrix(field(entry, "c2w", index, where), index, f"{where} field 'c2w'", ((3, 4), (4, 4)))[:3]
        K = matrix(field(entry, "intrinsic", index, where), index, f"{where} field 'intrinsic'", ((3, 3),))
        try:
            t = float(field(entry, "time", index, where))
        except (TypeError, ValueError):
            raise DatasetError(f"{index}: {where} field 'time' must be a number") from None
        if cam in c2w and (np.abs(c2w[cam] - pose).max() > 1e-5 or np.abs(intrinsics[cam] - K).max() > 1e-5):
            raise DatasetError(f"{index}: {where}: camera {cam} moves or changes intrinsics; cameras must be static")
        c2w.setdefault(cam, pose)
        intrinsics.setdefault(cam, K)
        frames.setdefault(cam, {})[frame] = path
        times.setdefault(cam, {})[frame] = t

    cams = sorted(frames)
    names = {c: str(c) for c in cams}
    grid = frame_grid(frames, names, lambda c, t: f"an entry for data/r_{c}_{t}.png", index)
    for cam, row in zip(cams, grid):
        for t, path in enumerate(row):
            require_file(path, f"the image of camera {cam}, frame {t} listed in {index.name}")
    frame_times = _frame_times(times, cams, len(grid[0]), index)

    width, height = image_size(grid[0][0])
    cameras = Cameras.from_opengl_c2w(
        np.stack([c2w[c] for c in cams]), K=np.stack([intrinsics[c] for c in cams]),
        width=width, height=height,
    )

    alpha_files = [[p.with_name("a_" + p.name[2:]) for p in row] for row in grid]
    has_alpha_files = all(p.is_file() for row in alpha_files for p in row)
    background = [plates.get(c) for c in cams]
    for cam, p in zip(cams, background):
        if p is not None:
            require_file(p, f"the background plate of camera {cam} listed in {index.name}")
    has_plates = all(p is not None for p in background)
    exclusion = [exclusions.get(c) for c in cams]
    for cam, p in zip(cams, exclusion):
        if p is not None:
            require_file(p, f"the loss-exclusion mask of camera {cam} listed in {index.name}")

    scene = MultiViewScene(
        root=root,
        name=root.resolve().name,
        cameras=cameras,
        times=frame_times,
        image_paths=grid,
        mask_paths=alpha_files if has_alpha_files else None,
        background_paths=background if has_plates else None,
        exclusion_mask_paths=exclusion if any(p is not None for p in exclusion) else None,
        ground_truth=_ground_truth(root),
        fps=fps_from_times(frame_times, 24.0),
        layout="pac_nerf",
        camera_names=[names[c] for c in cams],
        mask_source=_mask_source(has_alpha_files, grid[0][0], has_plates),
    )
    world = load_world(root, PAC_NERF_WORLD)
    check_frame_rate(frame_times, world, str(index))
    into_canonical_world(scene, world)
    if verify_sizes:
        scene.verify_image_sizes()
    return scene


def _mask_source(has_alpha_files: bool, first_image: Path, has_plates: bool) -> str | None:
    if has_alpha_files:
        return "file"
    alpha = alpha_of(read_raw(first_image))
    if alpha is not None and alpha.min() < alpha.max():
        return "alpha"
    return "background" if has_plates else None


def _frame_times(times: dict[int, dict[int, float]], cams: list[int], n_frames: int, index: Path) -> np.ndarray:
    ref = np.array([times[cams[0]][t] for t in range(n_frames)])
    for cam in cams[1:]:
        for t in range(n_frames):
            if abs(times[cam][t] - ref[t]) > _TIME_TOL:
                raise DatasetError(
                    f"{index}: camera {cam}, frame {t} has time {times[cam][t]} but camera {cams[0]} "
                    f"has {ref[t]}; frames must be synchronised"
                )
    return ref


def _ground_truth(root: Path) -> GroundTruth | None:
    own = root / "ground_truth.json"
    if own.is_file():
        return read_ground_truth(own)
    material_dir = root.resolve().parent
    entry = None
    for table_path in (material_dir.with_suffix(".json"), material_dir / f"{material_dir.name}.json"):
        if table_path.is_file():
            table = load_json(table_path, "PAC-NeRF ground-truth parameters")
            if isinstance(table, dict) and isinstance(table.get(root.resolve().name), dict):
                entry = table[root.resolve().name]
                break
    clouds: list[Path] = []
    parts = list(root.resolve().parts)
    if "pacnerf" in parts:
        i = len(parts) - 1 - parts[::-1].index("pacnerf")
        clouds = numbered_plys(Path(*parts[:i], "simulation_data", *parts[i + 1 :]))
    if entry is None and not clouds:
        return None
    return ground_truth_from_flat(
        entry or {}, material=_MATERIALS.get(material_dir.name), point_clouds=clouds
    )

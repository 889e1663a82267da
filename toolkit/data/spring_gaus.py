"""Readers for the Spring-Gaus datasets: synthetic (``mpm_synthetic``) and real capture.

Synthetic layout (facts from Colmar-zlicheng/Spring-Gaus ``lib/datasets/mpm_synthetic.py`` and
daniel03c1/ProJo4D ``scene/dataset_readers.py::readCamerasFromFrameAndCamera``,
``train_projo4d.py::load_gt_params``, ``utils/data_utils.py::load_gt_pcds``, README)::

    <root>/render/<object>/camera.json     list of {"camera": "camera_k", "K": 3x3,
                                            "c2w": 4x4 OpenGL/Blender camera-to-world}
    <root>/render/<object>/frame.json      per frame a one-entry object whose value is the time (s)
    <root>/render/<object>/camera_k/NNN.png   RGBA frames (alpha = object mask), 3-digit index
    <root>/render/<object>/physical.json   list of objects; [0] has "E" and "NU",
                                            [1] has "INIT_VELOCITY"
    <root>/simulation/<object>/NNN.ply     ground-truth particles ("render" -> "simulation")

Real-capture layout (facts from Spring-Gaus ``lib/datasets/real_capture.py``,
``config/real_capture/*.yaml`` and ProJo4D ``readSpringGausCaptureRealCameras``)::

    <real_capture>/dynamic/cameras_calib.json   {camera: {"rvecs": [3], "tvecs": [3]}} OpenCV
                                                 world-to-camera (x_cam = R(rvec) x + t)
    <real_capture>/dynamic/sequences/<object>/<seq>.json   {"hit_frame": int,
                                                 camera: [image file names per frame], ...}
    <real_capture>/dynamic/videos_images/<camera>/<name>.jpg     frames (1920x1080)
    <real_capture>/dynamic/videos_masks/<camera>/<name>.png      masks (gray 0..255)
    <real_capture>/static/colmap/<object>/cameras.bin   COLMAP intrinsics of the static photos
                                                 (4752x2672); video K = fx * W / W_s,
                                                 fy * H / H_s, principal point at the image centre
    <real_capture>/dynamic/sync.json            (read by Spring-Gaus, not needed here)
    <real_capture>/dynamic/sequences/<object>/ground_truth.json   optional, this project's format
                                                 (scenes written in this layout by the tests)

The cameras are C0733, C0787 and C0801; frames are 120 fps (``FREQ: 120``).

Worlds (both readers then move the scene into the canonical world, :mod:`toolkit.data.world`):

* synthetic: gravity (0, -9.8, 0) (``config/mpm_synthetic/default.yaml``: ``G``), ground plane
  ``y = 0.2`` or ``0.3`` with normal +y depending on the object (``config/mpm_synthetic/<object>.yaml``:
  ``BC: [[[0, h, 0], [0, 1, 0]]]``), frames 0.03 s apart (``DT: 0.03``; ProJo4D's configs
  ``config/spring_gaus/mpm_synthetic/*_projo4d.json``: ``fps 33.3333333``). Spring-Gaus itself
  never reads ``frame.json``; ProJo4D (``readCamerasFromFrameAndCamera``) uses its values as the
  frame times of the deformation field. The reader takes them as seconds and warns when their
  step is not 0.03 s.
* real capture: gravity (0, 0, +9.8) (``config/real_capture/default.yaml``: ``G``), ground plane
  with normal -z at ``z = -0.01`` (bun, potato) or ``-0.025`` (burger, dog, pig)
  (``config/real_capture/<object>.yaml``: ``BC``; ProJo4D's ``config/spring_gaus/real_capture/
  projo4d.json`` uses ``-0.01`` for all, with ``voxel_size 0.01`` and gravity learnt), 120 fps.

Sources: github.com/Colmar-zlicheng/Spring-Gaus (commit c3b44b0) and github.com/daniel03c1/ProJo4D.
A ``world.json`` in the object's folder (synthetic) or ``dynamic/sequences/<object>/`` (real)
overrides any field. ProJo4D passes
``<real_capture>/<object>`` as the scene path (the folder need not exist); both that and
``<real_capture>`` plus ``obj_name`` are accepted.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from toolkit.cameras import Cameras
from toolkit.data._common import (
    fps_from_times,
    frame_grid,
    ground_truth_from_flat,
    matrix,
    matrix_field,
    numbered_plys,
)
from toolkit.data.errors import DatasetError, field, load_json, require_file
from toolkit.data.ground_truth import read_ground_truth
from toolkit.data.images import image_size
from toolkit.data.scene import GroundTruth, MultiViewScene
from toolkit.data.world import World, check_frame_rate, into_canonical_world, load_world

__all__ = [
    "SPRING_GAUS_FPS",
    "SPRING_GAUS_GROUND",
    "SPRING_GAUS_REAL_GROUND",
    "read_colmap_intrinsics",
    "read_spring_gaus",
    "read_spring_gaus_real",
    "spring_gaus_real_world",
    "spring_gaus_world",
]

_SG = "Colmar-zlicheng/Spring-Gaus"
#: Frame rate of the synthetic set: ``DT: 0.03`` s in every config/mpm_synthetic/<object>.yaml.
SPRING_GAUS_FPS = 1.0 / 0.03
#: Ground height y (normal +y) per synthetic object: ``BC`` of config/mpm_synthetic/<object>.yaml.
SPRING_GAUS_GROUND = {
    **dict.fromkeys(("C", "E", "V", "rope", "toothpaste"), 0.2),
    **dict.fromkeys(("apple", "banana", "chess", "cream", "cross", "doraemon", "droplet", "duck",
                     "torus", "torus_heterogeneous"), 0.3),
}
#: Ground z (normal -z) per real-capture object: ``BC`` of config/real_capture/<object>.yaml.
SPRING_GAUS_REAL_GROUND = {"bun": -0.01, "potato": -0.01, "burger": -0.025, "dog": -0.025, "pig": -0.025}


def spring_gaus_world(obj_name: str, ground_height: float | None = None) -> World:
    """The Spring-Gaus synthetic world of ``obj_name`` (see the module docstring).

    Args:
        obj_name: object folder name (``torus``, ``rope``, ...).
        ground_height: y of the ground; default the object's config value, 0.3 (the most common
            one) with a warning for an object the configs do not list.
    """
    source = f"{_SG} config/mpm_synthetic/{obj_name}.yaml (BC, DT) and default.yaml (G)"
    if ground_height is None:
        ground_height = SPRING_GAUS_GROUND.get(obj_name)
        if ground_height is None:
            import warnings

            ground_height = 0.3
            source = f"{_SG} config/mpm_synthetic/default.yaml (G); ground y = 0.3 assumed: object {obj_name!r} has no config"
            warnings.warn(f"Spring-Gaus synthetic object {obj_name!r} is not in the dataset's configs "
                          f"({sorted(SPRING_GAUS_GROUND)}); assuming the ground at y = 0.3 m. Pass "
                          "ground_height= or write world.json if it is elsewhere.", stacklevel=3)
    else:
        source = f"ground_height={ground_height} given to the reader; {_SG} default.yaml (G)"
    return World(gravity=(0.0, -9.8, 0.0), ground_point=(0.0, float(ground_height), 0.0),
                 ground_normal=(0.0, 1.0, 0.0), fps=SPRING_GAUS_FPS, source=source)


def spring_gaus_real_world(obj_name: str) -> World:
    """The Spring-Gaus real-capture world of ``obj_name`` (see the module docstring)."""
    z = SPRING_GAUS_REAL_GROUND.get(obj_name)
    source = f"{_SG} config/real_capture/{obj_name}.yaml (BC, FREQ) and default.yaml (G)"
    if z is None:
        import warnings

        z = -0.01
        source = f"{_SG} config/real_capture/default.yaml (G); ground z = -0.01 assumed (ProJo4D's value)"
        warnings.warn(f"Spring-Gaus real-capture object {obj_name!r} is not in the dataset's configs "
                      f"({sorted(SPRING_GAUS_REAL_GROUND)}); assuming the ground at z = -0.01 m (normal -z).",
                      stacklevel=3)
    return World(gravity=(0.0, 0.0, 9.8), ground_point=(0.0, 0.0, float(z)), ground_normal=(0.0, 0.0, -1.0),
                 fps=120.0, source=source)

_FRAME = re.compile(r"^(\d+)\.png$")
_SUFFIX = re.compile(r"_(\d+)$")


# ---------------------------------------------------------------------------- synthetic


def read_spring_gaus(
    root: str | Path, *, fps: float | None = None, ground_height: float | None = None,
    verify_sizes: bool = True,
) -> MultiViewScene:
    """Read a Spring-Gaus synthetic scene (``render/<object>``, see the module docstring).

    Cameras are ordered by the number at the end of their names (``camera_0``, ``camera_1``,
    ...; ProJo4D's camera index), or as listed when a name has no number.

    Args:
        root: The object's folder holding ``camera.json``.
        fps: Frame rate; given, it sets the times (frame / fps) and ``frame.json`` is ignored.
            Default: the times of ``frame.json``, else frame * 0.03 s (the dataset's ``DT``).
        ground_height: y of the ground plane (default: the object's Spring-Gaus config).
        verify_sizes: Check every image's size from its header.

    A ``frame.json`` whose step is not 0.03 s gives a warning naming both rates.
    """
    root = Path(root)
    cam_file = root / "camera.json"
    entries = load_json(cam_file, "the Spring-Gaus camera list (camera.json)")
    if not isinstance(entries, list) or not entries:
        raise DatasetError(f"{cam_file}: expected a non-empty JSON list of cameras")
    cams = []
    for i, entry in enumerate(entries):
        name = str(field(entry, "camera", cam_file, f"entry {i}"))
        K = matrix_field(entry, "K", cam_file, f"entry {i} ({name})", ((3, 3),))
        c2w = matrix_field(entry, "c2w", cam_file, f"entry {i} ({name})", ((3, 4), (4, 4)))
        cams.append((name, K, c2w[:3]))
    numbers = [_SUFFIX.search(name) for name, _, _ in cams]
    if all(numbers):
        cams = [c for _, c in sorted(zip((int(m.group(1)) for m in numbers), cams), key=lambda x: x[0])]

    found: dict[int, dict[int, Path]] = {}
    for c, (name, _, _) in enumerate(cams):
        folder = root / name
        if not folder.is_dir():
            raise DatasetError(
                f"missing folder {folder}: expected the frames (NNN.png) of camera {name} listed in {cam_file.name}"
            )
        found[c] = {int(m.group(1)): p for p in folder.iterdir() if (m := _FRAME.match(p.name))}
        if not found[c]:
            raise DatasetError(f"{folder}: no frames; expected 000.png, 001.png, ...")
    names = {c: cams[c][0] for c in found}
    grid = frame_grid(found, names, lambda c, t: root / names[c] / f"{t:03d}.png", root)
    n_frames = len(grid[0])

    world = load_world(root, spring_gaus_world(root.resolve().name, ground_height))
    if fps is not None:
        times = np.arange(n_frames, dtype=np.float64) / fps
    else:
        times = _synthetic_times(root / "frame.json", n_frames, world.fps)
        if (root / "frame.json").is_file():
            check_frame_rate(times, world, str(root / "frame.json"))
    width, height = image_size(grid[0][0])
    cameras = Cameras.from_opengl_c2w(
        np.stack([c[2] for c in cams]), K=np.stack([c[1] for c in cams]), width=width, height=height
    )
    scene = MultiViewScene(
        root=root,
        name=root.resolve().name,
        cameras=cameras,
        times=times,
        image_paths=grid,
        ground_truth=_synthetic_ground_truth(root),
        fps=fps_from_times(times, world.fps),
        layout="spring_gaus",
        camera_names=[c[0] for c in cams],
        mask_source="alpha",
    )
    into_canonical_world(scene, world)
    if verify_sizes:
        scene.verify_image_sizes()
    return scene


def _synthetic_times(path: Path, n_frames: int, fps: float) -> np.ndarray:
    if not path.is_file():
        return np.arange(n_frames, dtype=np.float64) / fps
    data = load_json(path, "the Spring-Gaus frame times (frame.json)")
    if isinstance(data, dict):
        data = [data[k] for k in sorted(data, key=lambda k: int(k) if str(k).isdigit() else k)]
    if not isinstance(data, list) or len(data) < n_frames:
        got = len(data) if isinstance(data, list) else type(data).__name__
        raise DatasetError(f"{path}: expected a list of at least {n_frames} frame times, got {got}")
    times = []
    for t, item in enumerate(data[:n_frames]):
        value = next(iter(item.values()), None) if isinstance(item, dict) else item
        try:
            times.append(float(value))
        except (TypeError, ValueError):
            raise DatasetError(
                f"{path}: entry {t} must be a time or a one-entry object holding it, got {item!r}"
            ) from None
    return np.asarray(times)


def _synthetic_ground_truth(root: Path) -> GroundTruth | None:
    own = root / "ground_truth.json"
    if own.is_file():
        return read_ground_truth(own)
    clouds = []
    if root.resolve().parent.name == "render":
        clouds = numbered_plys(root.resolve().parent.parent / "simulation" / root.resolve().name)
    path = root / "physical.json"
    if not path.is_file():
        return GroundTruth(point_clouds=clouds) if clouds else None
    data = load_json(path, "Spring-Gaus ground-truth parameters (physical.json)")
    parts = data if isinstance(data, list) else [data]
    flat: dict = {}
    for i, part in enumerate(parts):
        if not isinstance(part, dict):
            raise DatasetError(f"{path}: entry {i} must be a JSON object, got {type(part).__name__}")
        flat.update(part)
    return ground_truth_from_flat(flat, material="neo_hookean", point_clouds=clouds)


# ---------------------------------------------------------------------------- real capture


_COLMAP_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12}
_COLMAP_NAMES = {
    "SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
    "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6, "FOV": 7, "SIMPLE_RADIAL_FISHEYE": 8,
    "RADIAL_FISHEYE": 9, "THIN_PRISM_FISHEYE": 10,
}
_SINGLE_FOCAL = {0, 2, 3, 7, 8, 9}


def read_colmap_intrinsics(path: str | Path) -> tuple[float, float, float, float, int, int]:
    """``(fx, fy, cx, cy, width, height)`` of the first camera (id 1 if present) of a COLMAP
    ``cameras.bin`` or ``cameras.txt``."""
    path = Path(path)
    require_file(path, "COLMAP camera intrinsics")
    cameras: dict[int, tuple[int, int, int, list[float]]] = {}
    try:
        if path.suffix == ".txt":
            for line in path.read_text().splitlines():
                words = line.split()
                if not words or words[0].startswith("#"):
                    continue
                model = _COLMAP_NAMES[words[1]]
                cameras[int(words[0])] = (model, int(words[2]), int(words[3]), [float(w) for w in words[4:]])
        else:
            data = path.read_bytes()
            (count,), offset = struct.unpack_from("<Q", data, 0), 8
            for _ in range(count):
                cam_id, model, w, h = struct.unpack_from("<iiQQ", data, offset)
                offset += 24
                n = _COLMAP_PARAMS[model]
                cameras[cam_id] = (model, w, h, list(struct.unpack_from(f"<{n}d", data, offset)))
                offset += 8 * n
    except (KeyError, struct.error, ValueError, IndexError) as exc:
        raise DatasetError(f"{path}: malformed COLMAP cameras file ({type(exc).__name__}: {exc})") from None
    if not cameras:
        raise DatasetError(f"{path}: no cameras")
    model, w, h, p = cameras[1] if 1 in cameras else cameras[min(cameras)]
    fx, fy = (p[0], p[0]) if model in _SINGLE_FOCAL else (p[0], p[1])
    cx, cy = (p[1], p[2]) if model in _SINGLE_FOCAL else (p[2], p[3])
    return fx, fy, cx, cy, w, h


def read_spring_gaus_real(
    root: str | Path,
    obj_name: str | None = None,
    *,
    seq: int | str = 0,
    fps: float = 120.0,
    verify_sizes: bool = True,
) -> MultiViewScene:
    """Read a Spring-Gaus real-capture sequence (see the module docstring).

    Args:
        root: ``<real_capture>`` (the folder holding ``dynamic/``), or ``<real_capture>/<object>``
            as ProJo4D passes it.
        obj_name: Object name (``bun``, ``burger``, ...); defaults to ``root``'s name in the
            second form, or to the only sequence folder.
        seq: Sequence file name under ``dynamic/sequences/<object>/`` (without ``.json``).
        fps: Video frame rate (times = frame / fps).
        verify_sizes: Check every image's and mask's size from its header.
    """
    root = Path(root)
    if (root / "dynamic").is_dir():
        base = root
    elif (root.parent / "dynamic").is_dir():
        base, obj_name = root.parent, obj_name or root.resolve().name
    else:
        raise DatasetError(
            f"missing folder {root / 'dynamic'}: expected the Spring-Gaus real-capture layout "
            "(dynamic/cameras_calib.json, dynamic/sequences/<object>/<seq>.json, "
            "dynamic/videos_images/, dynamic/videos_masks/, static/colmap/<object>/cameras.bin)"
        )
    dynamic = base / "dynamic"
    if obj_name is None:
        objects = sorted(p.name for p in (dynamic / "sequences").glob("*") if p.is_dir())
        if len(objects) != 1:
            raise DatasetError(f"{dynamic / 'sequences'}: choose obj_name among {objects}")
        obj_name = objects[0]
    calib_path = dynamic / "cameras_calib.json"
    calib = load_json(calib_path, "the camera calibration (cameras_calib.json)")
    seq_path = dynamic / "sequences" / obj_name / f"{seq}.json"
    seq_info = load_json(seq_path, f"the frame list of sequence {seq} of {obj_name}")
    if not isinstance(seq_info, dict):
        raise DatasetError(f"{seq_path}: expected a JSON object")
    names = sorted(k for k, v in seq_info.items() if isinstance(v, list))
    if not names:
        raise DatasetError(f"{seq_path}: no camera lists (expected e.g. {{'C0733': [...]}})")
    n_frames = max(len(seq_info[n]) for n in names)
    grid, masks = [], []
    for name in names:
        listed = seq_info[name]
        if len(listed) < n_frames:
            raise DatasetError(
                f"{seq_path}: camera {name} has no frame {len(listed)}: it lists {len(listed)} "
                f"frames, other cameras list {n_frames}"
            )
        row = [dynamic / "videos_images" / name / str(f) for f in listed]
        for t, p in enumerate(row):
            require_file(p, f"frame {t} of camera {name} listed in {seq_path.name}")
        mrow = [dynamic / "videos_masks" / name / (Path(str(f)).stem + ".png") for f in listed]
        for t, p in enumerate(mrow):
            require_file(p, f"the mask of frame {t} of camera {name}")
        grid.append(row)
        masks.append(mrow)

    width, height = image_size(grid[0][0])
    rvecs, tvecs, Ks = [], [], []
    colmap = None
    for name in names:
        entry = field(calib, name, calib_path, "the calibration")
        vec_shapes = ((3,), (3, 1), (1, 3))
        rvecs.append(matrix_field(entry, "rvecs", calib_path, f"camera {name}", vec_shapes).reshape(3))
        tvecs.append(matrix_field(entry, "tvecs", calib_path, f"camera {name}", vec_shapes).reshape(3))
        own_k = entry.get("K", entry.get("mtx"))
        if own_k is not None:
            Ks.append(matrix(own_k, calib_path, f"camera {name} field 'K'", ((3, 3),)))
            continue
        if colmap is None:
            colmap = _colmap_for(base, obj_name)
        fx, fy, _, _, w_s, h_s = colmap
        Ks.append(np.array([[fx * width / w_s, 0, width / 2], [0, fy * height / h_s, height / 2], [0, 0, 1]]))
    cameras = Cameras.from_opencv(np.stack(rvecs), np.stack(tvecs), np.stack(Ks), width, height)
    times = np.arange(n_frames, dtype=np.float64) / fps
    scene = MultiViewScene(
        root=base,
        name=obj_name,
        cameras=cameras,
        times=times,
        image_paths=grid,
        mask_paths=masks,
        fps=fps,
        layout="spring_gaus_real",
        camera_names=names,
        mask_source="file",
        metadata={"hit_frame": seq_info.get("hit_frame"), "sequence": str(seq), "object": obj_name},
        ground_truth=read_ground_truth(own_gt) if (own_gt := seq_path.parent / "ground_truth.json").is_file() else None,
    )
    world = load_world(seq_path.parent, spring_gaus_real_world(obj_name)).with_fps(fps)
    into_canonical_world(scene, world)
    if verify_sizes:
        scene.verify_image_sizes()
    return scene


def _colmap_for(base: Path, obj_name: str) -> tuple:
    folder = base / "static" / "colmap" / obj_name
    for name in ("cameras.bin", "cameras.txt"):
        if (folder / name).is_file():
            return read_colmap_intrinsics(folder / name)
    raise DatasetError(
        f"missing file {folder / 'cameras.bin'}: expected the COLMAP intrinsics of the static "
        "capture (or a 'K' per camera in dynamic/cameras_calib.json)"
    )

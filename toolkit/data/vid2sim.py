"""Reader for the Vid2Sim GSO layout as ProJo4D uses it.

Facts from daniel03c1/ProJo4D ``scene/dataset_readers.py::readGSOData`` (later
``readVid2SimData``), ``train_projo4d.py::load_gt_params`` and a public generator of this layout
that writes the same files (``transforms_{train,test,val,simulation}[_nvs].json``,
``gt_phys_params.yaml`` as ``yms: E`` / ``prs: nu``); CzzzzH/Vid2Sim's objaverse renderer writes
``gt_phys_params.yaml`` with the same ``yms``/``prs`` keys. The public GSO archive itself was not
available to check::

    <scene>/transforms_train.json      {"camera_angle_x": rad, "frames": [{"file_path":
                                        "./data/m_{cam}_0", "transform_matrix": 4x4 Blender c2w}]}
                                        (training cameras, 0..11)
    <scene>/transforms_train_nvs.json  the same for novel-view cameras (12..); ProJo4D notes they
                                        lack the future frames
    <scene>/data/a_{cam}_{frame}.png   RGBA frames (alpha = object mask; ProJo4D uses alpha > 0)
    <scene>/data/r_{cam}_-1.png        background plate (optional)
    <scene>/gt_phys_params.yaml        yms (Young's modulus) and prs (Poisson's ratio)
    <scene>/simulation/NNN.ply         ground-truth particles, when present

The material is Vid2Sim's (Simplicits) neo-Hookean form, ``neo_hookean_simplicits`` (paper,
appendix "Experimental Details for the GSO Dataset"). Frames are 0.05 s apart (20 fps; ProJo4D:
24 frames, the first 16 for fitting) and start at rest (ProJo4D evaluates the velocity against
v0 = 0). The ``time`` fields of the JSON are 0 and ignored. Square pixels:
``fx = fy = W / (2 tan(camera_angle_x / 2))``.

World: z up, gravity (0, 0, -9.8), floor plane ``z = -0.7`` with normal +z, 20 fps. Vid2Sim's
simulator (CzzzzH/Vid2Sim ``simulators/lbs_simulator.py``) puts gravity and the floor on one axis
(``floor_axis``, ``floor_level`` arguments; gravity magnitude 9.8); the values z and -0.7 are
those of the GSO renders as given in this project's DESIGN (section 8) and issue 14, not found in
a public config. ProJo4D (``readGSOData``: ``dt=0.05``) gives the frame step. The reader moves the
scene into the canonical world (:mod:`toolkit.data.world`); a ``world.json`` in the scene folder
overrides any field.
"""

from __future__ import annotations

import re
from pathlib import Path, PurePosixPath

import numpy as np

from toolkit.cameras import Cameras
from toolkit.data._common import frame_grid, ground_truth_from_flat, matrix_field, numbered_plys
from toolkit.data.errors import DatasetError, field, load_json
from toolkit.data.ground_truth import read_ground_truth
from toolkit.data.images import image_size
from toolkit.data.scene import GroundTruth, MultiViewScene
from toolkit.data.world import World, into_canonical_world, load_world

__all__ = ["VID2SIM_GSO_WORLD", "read_vid2sim_gso"]

#: Vid2Sim GSO's world (see the module docstring for the sources).
VID2SIM_GSO_WORLD = World(
    gravity=(0.0, 0.0, -9.8), ground_point=(0.0, 0.0, -0.7), ground_normal=(0.0, 0.0, 1.0), fps=20.0,
    source="Vid2Sim GSO (z up, floor z = -0.7: DESIGN section 8 / issue 14; CzzzzH/Vid2Sim "
           "simulators/lbs_simulator.py floor_axis/floor_level; dt 0.05 s: ProJo4D readGSOData)",
)

_FRAME = re.compile(r"^a_(\d+)_(\d+)\.png$")


def read_vid2sim_gso(
    root: str | Path, *, include_nvs: bool = False, fps: float = 20.0, verify_sizes: bool = True
) -> MultiViewScene:
    """Read a Vid2Sim GSO scene (see the module docstring).

    Args:
        root: Scene folder holding ``transforms_train.json``.
        include_nvs: Also load the cameras of ``transforms_train_nvs.json``; every camera must
            then have every frame (they lack the future frames in ProJo4D's copy).
        fps: Frame rate (times = frame / fps).
        verify_sizes: Check every image's size from its header.
    """
    root = Path(root)
    files = [root / "transforms_train.json"]
    if include_nvs:
        files.append(root / "transforms_train_nvs.json")
    angle, poses = None, {}
    for path in files:
        doc = load_json(path, "Vid2Sim GSO cameras (camera_angle_x, frames with transform_matrix)")
        try:
            this_angle = float(field(doc, "camera_angle_x", path, "the file"))
        except (TypeError, ValueError):
            raise DatasetError(f"{path}: field 'camera_angle_x' must be a number") from None
        if angle is not None and abs(this_angle - angle) > 1e-9:
            raise DatasetError(f"{path}: camera_angle_x {this_angle} differs from {files[0].name}'s {angle}")
        angle = this_angle
        frames = field(doc, "frames", path, "the file")
        if not isinstance(frames, list):
            raise DatasetError(f"{path}: field 'frames' must be a list")
        for i, fr in enumerate(frames):
            fp = str(field(fr, "file_path", path, f"frames[{i}]"))
            try:
                cam = int(PurePosixPath(fp).name.split("_")[1])
            except (IndexError, ValueError):
                raise DatasetError(
                    f"{path}: frames[{i}] field 'file_path' is {fp!r}, expected ./data/m_{{camera}}_0"
                ) from None
            if cam in poses:
                raise DatasetError(f"{path}: frames[{i}]: camera {cam} is listed twice")
            poses[cam] = matrix_field(fr, "transform_matrix", path, f"frames[{i}]", ((4, 4), (3, 4)))[:3]
    cams = sorted(poses)
    data = root / "data"
    found: dict[int, dict[int, Path]] = {c: {} for c in cams}
    if data.is_dir():
        for p in data.iterdir():
            m = _FRAME.match(p.name)
            if m and int(m.group(1)) in found:
                found[int(m.group(1))][int(m.group(2))] = p
    for cam in cams:
        if not found[cam]:
            raise DatasetError(f"missing file {data / f'a_{cam}_0.png'}: expected the RGBA frames of camera {cam}")
    grid = frame_grid(found, {c: str(c) for c in cams}, lambda c, t: data / f"a_{c}_{t}.png", data)
    width, height = image_size(grid[0][0])
    cameras = Cameras.from_blender(angle, np.stack([poses[c] for c in cams]), width, height)
    plates = [data / f"r_{c}_-1.png" for c in cams]
    n_frames = len(grid[0])
    times = np.arange(n_frames, dtype=np.float64) / fps
    scene = MultiViewScene(
        root=root,
        name=root.resolve().name,
        cameras=cameras,
        times=times,
        image_paths=grid,
        background_paths=plates if all(p.is_file() for p in plates) else None,
        ground_truth=_ground_truth(root),
        fps=fps,
        layout="vid2sim_gso",
        camera_names=[str(c) for c in cams],
        mask_source="alpha",
    )
    into_canonical_world(scene, load_world(root, VID2SIM_GSO_WORLD).with_fps(fps))
    if verify_sizes:
        scene.verify_image_sizes()
    return scene


def _ground_truth(root: Path) -> GroundTruth | None:
    own = root / "ground_truth.json"
    if own.is_file():
        return read_ground_truth(own)
    clouds = numbered_plys(root / "simulation")
    path = root / "gt_phys_params.yaml"
    if not path.is_file():
        return GroundTruth(point_clouds=clouds) if clouds else None
    import yaml

    try:
        values = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise DatasetError(f"malformed YAML in {path}{where}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(values, dict):
        raise DatasetError(f"{path}: expected 'yms: <E>' and 'prs: <nu>' entries, got {values!r}")
    gt = ground_truth_from_flat(values, material="neo_hookean_simplicits", point_clouds=clouds)
    if gt.v0 is None:
        gt.v0 = [0.0, 0.0, 0.0]
    return gt

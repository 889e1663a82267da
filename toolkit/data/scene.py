"""The in-memory description of a multi-view video scene that every dataset reader returns.

Indices are 0-based everywhere: camera ``c`` is ``scene.cameras[c]`` and ``image_paths[c]``;
frame ``t`` is at ``times[t]`` seconds. Images are loaded lazily, as float32 in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from toolkit.cameras import Cameras
from toolkit.data.errors import DatasetError
from toolkit.data.images import alpha_of, image_size, mask_of, read_raw, rgb_of, to_unit
from toolkit.data.world import RigidTransform, World

__all__ = ["GroundTruth", "MultiViewScene", "MaskSource"]

MaskSource = Literal["file", "alpha", "background"]


@dataclass
class GroundTruth:
    """What a synthetic scene was generated with; for EVALUATION only, never for fitting.

    Attributes:
        material: Material registry name (``"neo_hookean"``, ``"sand"``, ...) or None.
        params: Material parameters by toolkit name (see :mod:`toolkit.metrics.parameters`),
            SI units, angles in degrees.
        v0: Initial velocity (3,), m/s, or None.
        gravity: Gravity (3,), m/s^2, or None.
        effects: Effect parameters by effect name, e.g. ``{"ground_friction": {"mu": 0.3}}``.
        point_clouds: Per-frame ground-truth particle clouds (PLY), frame order; may be empty.
        extra: Everything else the source file holds (density, simulation settings, ...).
        to_canonical: Rigid map from the dataset's frame into the canonical world (set by
            :func:`~toolkit.data.world.into_canonical_world`); ``v0`` and ``gravity`` are already
            in the canonical frame, point clouds are mapped when loaded.
        dataset_frame: ``v0`` and ``gravity`` as the dataset states them (empty when the
            dataset's frame is the canonical one).
    """

    material: str | None = None
    params: dict[str, float] = field(default_factory=dict)
    v0: list[float] | None = None
    gravity: list[float] | None = None
    effects: dict[str, dict] = field(default_factory=dict)
    point_clouds: list[Path] = field(default_factory=list)
    extra: dict = field(default_factory=dict)
    to_canonical: RigidTransform | None = None
    dataset_frame: dict = field(default_factory=dict)

    def all_params(self) -> dict:
        """``params`` plus ``v0`` (when known): the ground-truth side of ``parameter_errors``."""
        out = dict(self.params)
        if self.v0 is not None:
            out["v0"] = list(self.v0)
        return out

    def load_point_cloud(self, frame: int, canonical: bool = True) -> np.ndarray:
        """Ground-truth particles of ``frame`` as an (N, 3) float64 array, metres.

        Args:
            frame: 0-based frame index.
            canonical: in the canonical world (y up, ground y = 0; the default), or as stored in
                the dataset's frame.
        """
        from toolkit.data.ply import read_ply_points

        if not 0 <= frame < len(self.point_clouds):
            raise DatasetError(
                f"ground-truth frame {frame} does not exist: valid 0..{len(self.point_clouds) - 1}"
            )
        points = read_ply_points(self.point_clouds[frame])
        if canonical and self.to_canonical is not None and not self.to_canonical.is_identity:
            points = self.to_canonical.apply_points(points)
        return points


@dataclass
class MultiViewScene:
    """C calibrated cameras observing T frames of one object.

    Attributes:
        root: Scene folder.
        name: Scene name (usually the folder name).
        cameras: All C cameras of the dataset, 0-based order, sized like the images on disk.
        times: (T,) frame times in seconds.
        image_paths: ``[camera][frame]`` image files.
        mask_paths: ``[camera][frame]`` mask files (alpha channel, or gray value), or None.
        background_paths: Per-camera background plates (PAC-NeRF frame -1), or None.
        exclusion_mask_paths: Per-camera loss-exclusion masks (PAC-NeRF frame -2; None for a
            camera without one), or None.
        ground_truth: Synthetic ground truth, or None.
        fps: Frames per second of the video.
        layout: Name of the reader's layout (``"pac_nerf"``, ``"spring_gaus"``, ...).
        camera_names: The dataset's own name of each camera (``"0"``, ``"camera_3"``, ``"C0733"``).
        mask_source: Where :meth:`load_mask` takes masks from: ``"file"`` (``mask_paths``),
            ``"alpha"`` (the image's alpha channel) or ``"background"`` (difference to the
            background plate); None picks the first available in that order.
        mask_threshold: Colour difference (max over channels, [0, 1] units) above which a pixel
            counts as object for ``mask_source="background"``.
        metadata: Layout-specific extras (e.g. ``hit_frame``).
        world: The dataset's world as its conventions state it (gravity, ground plane, nominal
            fps, source); see :mod:`toolkit.data.world`.
        to_canonical: Rigid map from the dataset's frame into the canonical world (y up, ground
            y = 0). Readers apply it on load: ``cameras`` and the ground truth are already in the
            canonical world; map results back with ``to_canonical.inverse()``.
    """

    root: Path
    name: str
    cameras: Cameras
    times: np.ndarray
    image_paths: list[list[Path]]
    mask_paths: list[list[Path]] | None = None
    background_paths: list[Path] | None = None
    exclusion_mask_paths: list[Path | None] | None = None
    ground_truth: GroundTruth | None = None
    fps: float = 24.0
    layout: str = "unknown"
    camera_names: list[str] | None = None
    mask_source: MaskSource | None = None
    mask_threshold: float = 0.1
    metadata: dict = field(default_factory=dict)
    world: World = field(default_factory=World)
    to_canonical: RigidTransform = field(default_factory=RigidTransform)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        self.times = np.asarray(self.times, dtype=np.float64)
        n_cams, n_frames = len(self.cameras), len(self.times)
        if len(self.image_paths) != n_cams:
            raise DatasetError(f"{self.root}: {n_cams} cameras but image paths for {len(self.image_paths)}")
        for c, paths in enumerate(self.image_paths):
            if len(paths) != n_frames:
                raise DatasetError(f"{self.root}: camera {c} has {len(paths)} frames, expected {n_frames}")
        if self.mask_paths is not None and [len(m) for m in self.mask_paths] != [n_frames] * n_cams:
            raise DatasetError(f"{self.root}: mask paths do not cover {n_cams} cameras x {n_frames} frames")
        for name in ("background_paths", "exclusion_mask_paths"):
            value = getattr(self, name)
            if value is not None and len(value) != n_cams:
                raise DatasetError(f"{self.root}: {name} has {len(value)} entries for {n_cams} cameras")
        if self.camera_names is None:
            self.camera_names = [str(c) for c in range(n_cams)]
        if self.mask_source is None:
            self.mask_source = "file" if self.mask_paths is not None else None

    # ------------------------------------------------------------------ sizes and indices

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    @property
    def n_frames(self) -> int:
        return len(self.times)

    @property
    def width(self) -> int:
        return self.cameras.width

    @property
    def height(self) -> int:
        return self.cameras.height

    def check_camera(self, cam: int) -> int:
        """Return ``cam`` if it is a valid camera index, else raise :class:`DatasetError`."""
        if not isinstance(cam, (int, np.integer)) or not 0 <= cam < self.n_cameras:
            raise DatasetError(
                f"camera index {cam!r} does not exist in {self.name}: valid indices are "
                f"0..{self.n_cameras - 1} ({self.n_cameras} cameras, 0-based)"
            )
        return int(cam)

    def check_frame(self, frame: int) -> int:
        """Return ``frame`` if it is a valid frame index, else raise :class:`DatasetError`."""
        if not isinstance(frame, (int, np.integer)) or not 0 <= frame < self.n_frames:
            raise DatasetError(
                f"frame index {frame!r} does not exist in {self.name}: valid indices are "
                f"0..{self.n_frames - 1}"
            )
        return int(frame)

    # ------------------------------------------------------------------ loading

    def _read_sized(self, path: Path) -> np.ndarray:
        arr = read_raw(path)
        h, w = arr.shape[:2]
        if (w, h) != (self.width, self.height):
            ref = self.image_paths[0][0]
            raise DatasetError(
                f"image sizes differ: {path} is {w}x{h} but {ref} (and the cameras) are "
                f"{self.width}x{self.height}"
            )
        return arr

    def load_image(self, cam: int, frame: int) -> np.ndarray:
        """(H, W, 3) float32 colour image in [0, 1] (alpha, if any, is not applied)."""
        path = self.image_paths[self.check_camera(cam)][self.check_frame(frame)]
        return to_unit(rgb_of(self._read_sized(path)))

    def load_mask(self, cam: int, frame: int) -> np.ndarray:
        """(H, W) float32 object mask in [0, 1], from :attr:`mask_source` (see the class doc)."""
        cam, frame = self.check_camera(cam), self.check_frame(frame)
        source = self.mask_source
        image = None
        if source is None:
            image = self._read_sized(self.image_paths[cam][frame])
            if alpha_of(image) is not None:
                source = "alpha"
            elif self.background_paths is not None:
                source = "background"
            else:
                raise DatasetError(
                    f"{self.name}: no mask for camera {cam}, frame {frame}: no mask files, "
                    f"{self.image_paths[cam][frame]} has no alpha channel and there is no "
                    "background plate"
                )
        if source == "file":
            if self.mask_paths is None:
                raise DatasetError(f"{self.name}: mask_source is 'file' but the scene has no mask files")
            return mask_of(self._read_sized(self.mask_paths[cam][frame]))
        if image is None:
            image = self._read_sized(self.image_paths[cam][frame])
        if source == "alpha":
            alpha = alpha_of(image)
            if alpha is None:
                raise DatasetError(f"{self.image_paths[cam][frame]} has no alpha channel to use as mask")
            return to_unit(alpha)
        if source == "background":
            diff = np.abs(to_unit(rgb_of(image)) - self.load_background(cam)).max(axis=-1)
            return (diff > self.mask_threshold).astype(np.float32)
        raise DatasetError(f"{self.name}: unknown mask_source {source!r}")

    def load_background(self, cam: int) -> np.ndarray:
        """(H, W, 3) float32 background plate of camera ``cam``."""
        cam = self.check_camera(cam)
        if self.background_paths is None:
            raise DatasetError(f"{self.name} has no background plates")
        return to_unit(rgb_of(self._read_sized(self.background_paths[cam])))

    def load_exclusion_mask(self, cam: int) -> np.ndarray:
        """(H, W) float32, 1 where pixels are excluded from the image loss (PAC-NeRF: alpha of
        the frame -2 image > 50/255); all zeros for a camera without one."""
        cam = self.check_camera(cam)
        path = None if self.exclusion_mask_paths is None else self.exclusion_mask_paths[cam]
        if path is None:
            return np.zeros((self.height, self.width), dtype=np.float32)
        arr = self._read_sized(path)
        alpha = alpha_of(arr)
        values = to_unit(alpha) if alpha is not None else mask_of(arr)
        return (values > 50.0 / 255.0).astype(np.float32)

    def verify_image_sizes(self) -> None:
        """Check (from file headers) that every image, mask and plate has the cameras' size.

        Raises:
            DatasetError: naming the first offending file, its size and the reference file.
        """
        ref = self.image_paths[0][0]
        files = [p for row in self.image_paths for p in row]
        files += [p for row in (self.mask_paths or []) for p in row]
        files += list(self.background_paths or [])
        files += [p for p in (self.exclusion_mask_paths or []) if p is not None]
        for path in files:
            w, h = image_size(path)
            if (w, h) != (self.width, self.height):
                raise DatasetError(
                    f"image sizes differ: {path} is {w}x{h} but {ref} is {self.width}x{self.height}"
                )

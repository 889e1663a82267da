"""The physical world a scene lives in, and the rigid map into the simulator's canonical world.

Every dataset states gravity and the ground in its own coordinates. The simulator knows one world,
the **canonical** one (PAC-NeRF's): metres, ``+y`` up, ground plane ``y = 0`` with normal ``+y``,
gravity along ``-y``. Readers describe the dataset's world with a :class:`World` and call
:func:`into_canonical_world`, which moves the cameras and the ground truth (point clouds, v0,
gravity) by one rigid transform ``x_canonical = R x_dataset + t`` (:class:`RigidTransform`) and
keeps that transform on the scene, so results can be reported back in the dataset's frame.

Conventions:

* ``ground_normal`` is a unit vector pointing from the ground into the free half-space (where the
  body is); ``ground_point`` is any point of the plane. Both in the dataset's frame, metres.
* ``gravity`` is the acceleration vector in m/s^2 in the dataset's frame; its magnitude is kept
  (9.8 unless the dataset says otherwise). It should point against ``ground_normal``; a tilted
  gravity is allowed and stays tilted in the canonical frame.
* ``R`` is the smallest rotation taking ``ground_normal`` to ``+y`` (a half turn about ``x`` when
  the normal is ``-y``); ``t`` moves along ``+y`` only, so the ground ends at ``y = 0`` and the
  other two coordinates of a point on the normal's axis keep their values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Optional, Sequence

import numpy as np

from toolkit.data.errors import DatasetError

__all__ = [
    "CANONICAL_GRAVITY",
    "WORLD_FILE",
    "RigidTransform",
    "World",
    "canonical_rotation",
    "check_frame_rate",
    "into_canonical_world",
    "load_world",
]

#: The simulator's default gravity (m/s^2): canonical world, y up.
CANONICAL_GRAVITY = (0.0, -9.8, 0.0)
_UNIT_TOL = 1e-6


def _vec3(value, name: str, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: {name} must be 3 numbers, got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise DatasetError(f"{where}: {name} must be 3 finite numbers, got {value!r}")
    return arr


@dataclass(frozen=True)
class World:
    """Gravity, ground plane and frame rate of a dataset, in the dataset's own frame.

    Attributes:
        gravity: (3,) gravitational acceleration, m/s^2.
        ground_point: (3,) a point of the ground plane, metres.
        ground_normal: (3,) unit normal of the ground, pointing into the free half-space.
        fps: the dataset's nominal frame rate (frames per second), or None if it has none.
        source: where these conventions come from (file or URL), for messages and reports.
    """

    gravity: tuple[float, float, float] = CANONICAL_GRAVITY
    ground_point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ground_normal: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fps: Optional[float] = None
    source: str = "canonical world (PAC-NeRF convention: y up, ground y = 0)"

    def __post_init__(self) -> None:
        where = f"world ({self.source})"
        g = _vec3(self.gravity, "gravity", where)
        p = _vec3(self.ground_point, "ground_point", where)
        n = _vec3(self.ground_normal, "ground_normal", where)
        norm = float(np.linalg.norm(n))
        if norm < 1e-9:
            raise DatasetError(f"{where}: ground_normal must be non-zero, got {self.ground_normal!r}")
        if not float(np.linalg.norm(g)) > 0:
            raise DatasetError(f"{where}: gravity must be non-zero, got {self.gravity!r} (m/s^2)")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise DatasetError(f"{where}: fps must be a positive number or null, got {self.fps!r}")
        object.__setattr__(self, "gravity", tuple(float(v) for v in g))
        object.__setattr__(self, "ground_point", tuple(float(v) for v in p))
        object.__setattr__(self, "ground_normal", tuple(float(v) for v in n / norm))
        if self.fps is not None:
            object.__setattr__(self, "fps", float(self.fps))

    # ------------------------------------------------------------------ derived
    @property
    def up(self) -> np.ndarray:
        """(3,) unit ground normal (the dataset's "up")."""
        return np.asarray(self.ground_normal)

    @property
    def ground_offset(self) -> float:
        """Signed height of the dataset's origin above the ground: ``-(n . p)``, metres."""
        return -float(np.dot(self.up, self.ground_point))

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed height above the ground, metres, of (..., 3) points in the dataset's frame."""
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.ground_point)) @ self.up

    def canonical_transform(self) -> "RigidTransform":
        """The rigid map from this world's frame into the canonical one (module docstring)."""
        R = canonical_rotation(self.up)
        t = np.array([0.0, -float(np.dot(self.up, self.ground_point)), 0.0])
        return RigidTransform(R, t)

    @property
    def is_canonical(self) -> bool:
        """True when the canonical transform is the identity (y up, ground y = 0)."""
        return self.canonical_transform().is_identity

    def canonical_gravity(self) -> tuple[float, float, float]:
        """Gravity (m/s^2) in the canonical frame (magnitude kept)."""
        return tuple(float(v) for v in self.canonical_transform().apply_vectors(np.asarray(self.gravity)))

    def describe(self) -> str:
        """One line naming the settings, for messages."""
        fps = "unknown" if self.fps is None else f"{self.fps:g}"
        return (f"gravity {list(self.gravity)} m/s^2, ground through {list(self.ground_point)} m with normal "
                f"{[round(v, 6) for v in self.ground_normal]}, {fps} fps (source: {self.source})")

    def with_fps(self, fps: Optional[float]) -> "World":
        return replace(self, fps=fps)

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict:
        return {"gravity": list(self.gravity), "ground_point": list(self.ground_point),
                "ground_normal": list(self.ground_normal), "fps": self.fps, "source": self.source}

    @classmethod
    def from_dict(cls, d: dict, where: str = "world") -> "World":
        """A world from a dict with optional keys ``gravity``, ``ground_point``, ``ground_normal``,
        ``fps``, ``source`` (missing ones take the canonical defaults).

        Raises:
            DatasetError: unknown keys or malformed values, naming ``where``.
        """
        if not isinstance(d, dict):
            raise DatasetError(f"{where}: expected an object with gravity / ground_point / ground_normal / fps, got {d!r}")
        known = {"gravity", "ground_point", "ground_normal", "fps", "source"}
        extra = set(d) - known
        if extra:
            raise DatasetError(f"{where}: unknown world fields {sorted(extra)}; expected some of {sorted(known)}")
        kw = {k: d[k] for k in known if k in d and d[k] is not None}
        kw.setdefault("source", where)
        return cls(**kw)


def canonical_rotation(up: Sequence[float]) -> np.ndarray:
    """(3, 3) smallest rotation taking the unit vector ``up`` to ``+y`` (Rodrigues' formula).

    ``-y`` (no unique smallest rotation) maps by a half turn about ``x``.
    """
    a = np.asarray(up, dtype=np.float64)
    a = a / np.linalg.norm(a)
    b = np.array([0.0, 1.0, 0.0])
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(a, b)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


@dataclass(frozen=True)
class RigidTransform:
    """``x' = R x + t`` with a proper rotation ``R`` (3, 3) and a translation ``t`` (3,), metres."""

    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"RigidTransform needs R (3, 3) and t (3,), got {R.shape} and {t.shape}")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1.0) > 1e-6:
            raise ValueError(f"RigidTransform.R must be a rotation (orthonormal, det +1), got {R.tolist()}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @property
    def is_identity(self) -> bool:
        return bool(np.abs(self.R - np.eye(3)).max() < 1e-12 and np.abs(self.t).max() < 1e-12)

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return m

    def inverse(self) -> "RigidTransform":
        return RigidTransform(self.R.T, -self.R.T @ self.t)

    def apply_points(self, points) -> np.ndarray:
        """(..., 3) points, float64: ``R x + t``."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def apply_vectors(self, vectors) -> np.ndarray:
        """(..., 3) free vectors (velocities, accelerations), float64: ``R v``."""
        return np.asarray(vectors, dtype=np.float64) @ self.R.T

    def apply_cameras(self, cameras):
        """The same physical cameras expressed in the transformed frame: ``w2c' = w2c T^-1``."""
        import torch

        from toolkit.cameras import Cameras

        w2c = cameras.w2c.detach().cpu().double().numpy() @ self.inverse().matrix
        return Cameras(cameras.K.detach().cpu().clone(), torch.from_numpy(w2c).float(), cameras.width,
                       cameras.height, cameras.near, cameras.far)

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: Optional[dict]) -> "RigidTransform":
        """Inverse of :meth:`to_dict`; None gives the identity."""
        if d is None:
            return cls()
        return cls(np.asarray(d["R"]), np.asarray(d["t"]))


def into_canonical_world(scene, world: World):
    """Move ``scene`` (a :class:`~toolkit.data.scene.MultiViewScene` in ``world``'s frame) into
    the canonical world, in place, and return it.

    Sets ``scene.world`` (the dataset's world, as stated) and ``scene.to_canonical``; transforms
    ``scene.cameras``; the ground truth's ``v0``/``gravity`` are rotated (the dataset-frame values
    are kept in ``ground_truth.dataset_frame``) and its point clouds are transformed when
    loaded (``ground_truth.to_canonical``). A scene already moved is left as it is.
    """
    if getattr(scene, "_canonicalized", False):
        return scene
    T = world.canonical_transform()
    scene.world = world
    scene.to_canonical = T
    if not T.is_identity:
        scene.cameras = T.apply_cameras(scene.cameras)
    gt = scene.ground_truth
    if gt is not None:
        gt.to_canonical = T
        if not T.is_identity:
            gt.dataset_frame = {"v0": gt.v0, "gravity": gt.gravity}
            if gt.v0 is not None:
                gt.v0 = [float(v) for v in T.apply_vectors(gt.v0)]
            if gt.gravity is not None:
                gt.gravity = [float(v) for v in T.apply_vectors(gt.gravity)]
    scene._canonicalized = True
    return scene


#: File a scene folder may hold to state (or override) its world; keys as :meth:`World.from_dict`.
WORLD_FILE = "world.json"


def load_world(root, default: World) -> World:
    """``default`` with the fields of ``<root>/world.json`` (when present) laid over it.

    Raises:
        DatasetError: malformed ``world.json`` (naming the file and field).
    """
    from pathlib import Path

    from toolkit.data.errors import load_json

    path = Path(root) / WORLD_FILE
    if not path.is_file():
        return default
    doc = load_json(path, "the scene's world (gravity, ground_point, ground_normal, fps)")
    merged = {**default.to_dict(), "source": str(path)}
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object with gravity / ground_point / ground_normal / fps")
    merged.update(doc)
    return World.from_dict(merged, where=str(path))


def check_frame_rate(times: np.ndarray, world: World, where: str, rel_tol: float = 0.01) -> Optional[str]:
    """Warn (and return the message) when the data's frame rate disagrees with ``world.fps``.

    Args:
        times: (T,) frame times in seconds, as the data gives them.
        world: the dataset's world; nothing is checked when ``world.fps`` is None.
        where: the file the times come from, for the message.
        rel_tol: relative difference of the frame steps that counts as a disagreement.
    """
    import warnings

    times = np.asarray(times, dtype=np.float64)
    if world.fps is None or len(times) < 2:
        return None
    steps = np.diff(times)
    step = float(np.median(steps))
    want = 1.0 / world.fps
    if step > 0 and abs(step - want) <= rel_tol * want:
        return None
    data_fps = f"{1.0 / step:.4g} fps" if step > 0 else "no positive frame step"
    msg = (f"{where}: frame step {step:.6g} s ({data_fps}) disagrees with the dataset's {want:.6g} s "
           f"({world.fps:.4g} fps, {world.source}); the simulator steps by the data's times: pass fps= to the "
           "reader (or set 'fps' in world.json) if the file's times are not seconds")
    warnings.warn(msg, stacklevel=3)
    return msg

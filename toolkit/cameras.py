"""One pinhole camera type for every dataset and renderer.

Conventions (DESIGN section 5):

* OpenCV camera frame: x right, y down, z forward (the camera looks along +z).
* Extrinsics are world-to-camera rigid transforms: ``x_cam = R x_world + t``.
* Pixel ``(i, j)`` (column ``i``, row ``j``) covers ``[i, i+1) x [j, j+1)``; its centre is at
  ``(i + 0.5, j + 0.5)``. A camera-space point projects to ``u = fx x / z + cx``,
  ``v = fy y / z + cy`` (no skew, no distortion).
* World up is +y in this project; the ground plane is ``y = 0``.

Loaders convert at the boundary: OpenGL/Blender camera-to-world matrices (x right, y up,
z backward; PAC-NeRF, Spring-Gaus synthetic, NeRF-synthetic/Vid2Sim GSO) with
:meth:`Cameras.from_opengl_c2w` / :meth:`Cameras.from_blender`, OpenCV Rodrigues vectors with
:meth:`Cameras.from_opencv`.

Camera tensors are stored as float32. Methods that take points (``project``, ``unproject``,
``world_to_camera``) compute in the dtype of the points (float32 or float64) and are
differentiable with respect to them (and to ``K``/``w2c`` when those require grad).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch

__all__ = ["Cameras", "rodrigues", "rotmat_to_rodrigues", "OPENGL_TO_OPENCV"]

ROTATION_TOL = 1e-4  # max |R R^T - I| and |det R - 1| accepted for a rotation
SKEW_TOL = 1e-6  # |K[0,1]|, |K[1,0]|, |K[2,:2]| and |K[2,2] - 1| accepted in an intrinsic matrix

# Flips the camera's y and z axes: OpenGL camera (x right, y up, z back) <-> OpenCV (x right,
# y down, z forward). It is its own inverse: c2w_opencv = c2w_opengl @ OPENGL_TO_OPENCV.
OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))

ArrayLike = Union[torch.Tensor, np.ndarray, Sequence]
Index = Union[int, slice, Sequence[int], torch.Tensor, np.ndarray]


def _as_tensor(x: ArrayLike, name: str, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """``x`` as a floating tensor of ``dtype`` (keeps autograd history for tensors)."""
    if isinstance(x, torch.Tensor):
        if x.is_complex() or x.dtype == torch.bool:
            raise ValueError(f"{name} must be a real-valued tensor, got dtype {x.dtype}")
        return x.to(dtype=dtype, device=device if device is not None else x.device)
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be array-like of numbers, got {type(x).__name__}: {exc}") from None
    return torch.as_tensor(arr, dtype=dtype, device=device)


def _check_int(value: Any, name: str) -> int:
    try:
        ivalue = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive integer, got {value!r}") from None
    if ivalue != value or ivalue <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return ivalue


def rodrigues(rvec: ArrayLike) -> torch.Tensor:
    """Rotation matrices from OpenCV Rodrigues rotation vectors.

    Args:
        rvec: (3,), (3, 1), (B, 3) or (B, 3, 1) axis-angle vectors (axis * angle in radians).

    Returns:
        (B, 3, 3) rotation matrices ``R = I + sin(a)/a [r]x + (1 - cos(a))/a^2 [r]x^2``, in the
        dtype of ``rvec`` when it is a floating tensor (float64 otherwise). Differentiable,
        including at ``a = 0`` (a Taylor expansion is used for small angles).
    """
    dtype = rvec.dtype if isinstance(rvec, torch.Tensor) and rvec.is_floating_point() else torch.float64
    r = _as_tensor(rvec, "rvec", dtype=dtype)
    if r.ndim >= 1 and r.shape[-1] == 1 and r.ndim in (2, 3):
        r = r[..., 0]
    if r.ndim == 1:
        r = r[None]
    if r.ndim != 2 or r.shape[-1] != 3:
        raise ValueError(f"rvec must have shape (3,), (3, 1), (B, 3) or (B, 3, 1), got {tuple(_as_tensor(rvec, 'rvec').shape)}")
    theta2 = (r * r).sum(-1)
    small = theta2 < 1e-8
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2_safe)
    zero = torch.zeros_like(r[:, 0])
    k = torch.stack(
        [
            torch.stack([zero, -r[:, 2], r[:, 1]], -1),
            torch.stack([r[:, 2], zero, -r[:, 0]], -1),
            torch.stack([-r[:, 1], r[:, 0], zero], -1),
        ],
        -2,
    )
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(k)
    return eye + a[:, None, None] * k + b[:, None, None] * (k @ k)


def rotmat_to_rodrigues(R: ArrayLike) -> torch.Tensor:
    """Inverse of :func:`rodrigues`: (B, 3, 3) or (3, 3) rotations -> (B, 3) rotation vectors.

    The angle is in ``[0, pi]``; at exactly ``pi`` the sign of the axis is arbitrary. Not meant to
    be differentiated.
    """
    Rt = _as_tensor(R, "R", dtype=torch.float64)
    if Rt.ndim == 2:
        Rt = Rt[None]
    if Rt.ndim != 3 or Rt.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (3, 3) or (B, 3, 3), got {tuple(Rt.shape)}")
    out = torch.zeros(Rt.shape[0], 3, dtype=torch.float64, device=Rt.device)
    cos = ((Rt.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    angle = torch.arccos(cos)
    vee = torch.stack([Rt[:, 2, 1] - Rt[:, 1, 2], Rt[:, 0, 2] - Rt[:, 2, 0], Rt[:, 1, 0] - Rt[:, 0, 1]], -1)
    sin = torch.sin(angle)
    for i in range(Rt.shape[0]):
        if angle[i] < 1e-6:
            out[i] = 0.5 * vee[i]
        elif math.pi - float(angle[i]) > 1e-3:
            out[i] = vee[i] * (angle[i] / (2.0 * sin[i]))
        else:  # near pi: axis from the symmetric part, R + I = 2 n n^T (1 - cos) + ... ~ 2 n n^T
            sym = (Rt[i] + torch.eye(3, dtype=torch.float64, device=Rt.device)) / 2.0
            col = int(torch.argmax(sym.diagonal()))
            axis = sym[:, col] / sym[col, col].clamp_min(1e-12).sqrt()
            axis = axis / axis.norm()
            if (vee[i] @ axis) < 0:  # keep the axis consistent with the (small) antisymmetric part
                axis = -axis
            out[i] = axis * angle[i]
    return out


@dataclass(eq=False)
class Cameras:
    """A batch of B pinhole cameras, OpenCV convention (x right, y down, z forward), world-to-camera extrinsics.

    Attributes:
        K: (B, 3, 3) float32 intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
        w2c: (B, 4, 4) float32 world->camera rigid transform (``x_cam = R x_world + t``), metres.
        width: image width in pixels.
        height: image height in pixels.
        near: near-plane depth (metres); renderers drop Gaussians whose centre has ``z <= near``.
        far: far-plane depth (metres), ``> near``.

    ``K`` of shape (3, 3) and ``w2c`` of shape (4, 4) describe a single camera (a batch dim is
    added); a single ``K`` is shared by every camera of a ``w2c`` batch. Construction validates
    everything and raises ``ValueError`` naming the argument and the camera index.
    """

    K: torch.Tensor
    w2c: torch.Tensor
    width: int
    height: int
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self) -> None:
        dev = None
        if isinstance(self.K, torch.Tensor):
            dev = self.K.device
        elif isinstance(self.w2c, torch.Tensor):
            dev = self.w2c.device
        if isinstance(self.K, torch.Tensor) and isinstance(self.w2c, torch.Tensor) and self.K.device != self.w2c.device:
            raise ValueError(f"K is on {self.K.device} but w2c is on {self.w2c.device}; put both on one device")
        K = _as_tensor(self.K, "K", device=dev)
        w2c = _as_tensor(self.w2c, "w2c", device=dev)
        if K.ndim not in (2, 3) or K.shape[-2:] != (3, 3):
            raise ValueError(f"K must have shape (3, 3) or (B, 3, 3), got {tuple(K.shape)}")
        if w2c.ndim not in (2, 3) or w2c.shape[-2:] != (4, 4):
            raise ValueError(f"w2c must have shape (4, 4) or (B, 4, 4), got {tuple(w2c.shape)}")
        if K.ndim == 2:
            K = K[None]
        if w2c.ndim == 2:
            w2c = w2c[None]
        if K.shape[0] == 1 and w2c.shape[0] > 1:
            K = K.expand(w2c.shape[0], 3, 3)
        if K.shape[0] != w2c.shape[0]:
            raise ValueError(f"K has {K.shape[0]} cameras but w2c has {w2c.shape[0]}; the batch sizes must match")
        self.K = K
        self.w2c = w2c
        self.width = _check_int(self.width, "width")
        self.height = _check_int(self.height, "height")
        self.near = float(self.near)
        self.far = float(self.far)
        self.validate()

    @classmethod
    def _trusted(cls, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, near: float, far: float) -> "Cameras":
        """Build without validation from already-validated parts (slicing, moving, scaling)."""
        cam = object.__new__(cls)
        cam.K, cam.w2c, cam.width, cam.height, cam.near, cam.far = K, w2c, width, height, near, far
        return cam

    def validate(self) -> None:
        """Raise ``ValueError`` if any camera is malformed (see the class docstring).

        Renderers call this on every render. A check that passed is remembered with the tensors it
        checked and their version counters (bumped by any in-place change), so the same unchanged
        cameras are checked once; new tensors, an in-place edit or a new near/far check again."""
        checked = getattr(self, "_checked", None)
        if (checked is not None and checked[0] is self.K and checked[1] == self.K._version and checked[2] is self.w2c
                and checked[3] == self.w2c._version and checked[4:] == (self.near, self.far)):
            return
        self._check()
        self._checked = (self.K, self.K._version, self.w2c, self.w2c._version, self.near, self.far)

    def _check(self) -> None:
        K, w2c = self.K.detach(), self.w2c.detach()
        if K.shape[0] == 0:
            raise ValueError("Cameras needs at least one camera, got an empty batch (B = 0)")
        if K.dtype != torch.float32 or w2c.dtype != torch.float32:
            raise ValueError(f"K and w2c must be float32, got {K.dtype} and {w2c.dtype}")
        for name, t in (("K", K), ("w2c", w2c)):
            bad = ~torch.isfinite(t).reshape(t.shape[0], -1).all(-1)
            if bad.any():
                raise ValueError(f"{name} has NaN or inf values for camera index {int(bad.nonzero()[0, 0])}")
        fx, fy = K[:, 0, 0], K[:, 1, 1]
        for name, f in (("fx (K[0, 0])", fx), ("fy (K[1, 1])", fy)):
            bad = f <= 0
            if bad.any():
                i = int(bad.nonzero()[0, 0])
                raise ValueError(f"K: {name} must be positive, got {float(f[i])} for camera index {i}")
        got = torch.stack([K[:, 0, 1], K[:, 1, 0], K[:, 2, 0], K[:, 2, 1], K[:, 2, 2]], -1)
        dev = (got - torch.tensor([0.0, 0.0, 0.0, 0.0, 1.0], device=K.device)).abs().amax(-1)
        bad = dev > SKEW_TOL
        if bad.any():
            i = int(bad.nonzero()[0, 0])
            raise ValueError(
                f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew); camera index {i} has "
                f"K = {K[i].tolist()}"
            )
        bottom = (w2c[:, 3] - torch.tensor([0.0, 0.0, 0.0, 1.0], device=w2c.device)).abs().amax(-1)
        bad = bottom > SKEW_TOL
        if bad.any():
            i = int(bad.nonzero()[0, 0])
            raise ValueError(f"w2c: the last row must be [0, 0, 0, 1], got {w2c[i, 3].tolist()} for camera index {i}")
        R = w2c[:, :3, :3].double()
        eye = torch.eye(3, dtype=torch.float64, device=R.device)
        ortho = (R @ R.transpose(-1, -2) - eye).abs().amax((-1, -2))
        det = torch.linalg.det(R)
        for i in range(R.shape[0]):
            if float(ortho[i]) > ROTATION_TOL:
                raise ValueError(
                    f"w2c: the rotation part of camera index {i} is not orthonormal: max |R R^T - I| = "
                    f"{float(ortho[i]):.3g} > {ROTATION_TOL} (a scaled or sheared matrix is not a rigid transform)"
                )
            if abs(float(det[i]) - 1.0) > ROTATION_TOL:
                raise ValueError(
                    f"w2c: the rotation part of camera index {i} has det = {float(det[i]):.6g}, expected +1 "
                    f"(deviation {abs(float(det[i]) - 1.0):.3g}; det -1 is a reflection, e.g. an OpenGL/OpenCV axis mix-up)"
                )
        for name, v in (("near", self.near), ("far", self.far)):
            if math.isnan(v):
                raise ValueError(f"{name} must be a number, got {v}")
        if not (math.isfinite(self.near) and self.near >= 0.0):
            raise ValueError(f"near must be finite and >= 0, got {self.near}")
        if not self.near < self.far:
            raise ValueError(f"near must be < far, got near={self.near}, far={self.far}")

    # ------------------------------------------------------------------ constructors

    @staticmethod
    def _intrinsics(
        K: Optional[ArrayLike], fx, fy, cx, cy, width: int, height: int, batch: int, device
    ) -> torch.Tensor:
        if K is not None:
            if any(v is not None for v in (fx, fy, cx, cy)):
                raise ValueError("give either K or fx/fy/cx/cy, not both")
            Kt = _as_tensor(K, "K", device=device)
            if Kt.ndim == 2:
                Kt = Kt[None]
            return Kt
        if fx is None:
            raise ValueError("give K or at least fx (fy defaults to fx, cx to width/2, cy to height/2)")
        n = batch

        def vec(v, default, name):
            v = default if v is None else v
            t = _as_tensor(v, name, device=device).reshape(-1)
            if t.numel() not in (1, n):
                raise ValueError(f"{name} must be a scalar or have {n} entries, got {t.numel()}")
            return t.expand(n)

        fxv = vec(fx, None, "fx")
        fyv = vec(fy, fx, "fy")
        cxv = vec(cx, width / 2.0, "cx")
        cyv = vec(cy, height / 2.0, "cy")
        Kt = torch.zeros(n, 3, 3, dtype=torch.float32, device=device)
        Kt[:, 0, 0], Kt[:, 1, 1], Kt[:, 0, 2], Kt[:, 1, 2], Kt[:, 2, 2] = fxv, fyv, cxv, cyv, 1.0
        return Kt

    @staticmethod
    def _homogeneous(m: ArrayLike, name: str) -> torch.Tensor:
        """(…, 3, 4) or (…, 4, 4) -> (B, 4, 4) float64 (keeps the device of a tensor)."""
        dev = m.device if isinstance(m, torch.Tensor) else None
        t = _as_tensor(m, name, dtype=torch.float64, device=dev)
        if t.ndim == 2:
            t = t[None]
        if t.ndim != 3 or t.shape[-2:] not in ((3, 4), (4, 4)):
            raise ValueError(f"{name} must have shape (4, 4), (3, 4), (B, 4, 4) or (B, 3, 4), got {tuple(t.shape)}")
        if t.shape[-2] == 3:
            row = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=t.dtype, device=t.device).expand(t.shape[0], 1, 4)
            t = torch.cat([t, row], -2)
        return t

    @staticmethod
    def _rigid_inverse(m: torch.Tensor) -> torch.Tensor:
        R, t = m[:, :3, :3], m[:, :3, 3:]
        Rt = R.transpose(-1, -2)
        top = torch.cat([Rt, -Rt @ t], -1)
        bottom = torch.zeros_like(m[:, 3:])
        bottom[:, :, 3] = 1.0
        return torch.cat([top, bottom], -2)

    @classmethod
    def from_opengl_c2w(
        cls,
        c2w: ArrayLike,
        K: Optional[ArrayLike] = None,
        *,
        fx: Any = None,
        fy: Any = None,
        cx: Any = None,
        cy: Any = None,
        width: int,
        height: int,
        near: float = 0.01,
        far: float = 100.0,
    ) -> "Cameras":
        """Cameras from OpenGL/Blender camera-to-world matrices (x right, y up, z backward).

        Args:
            c2w: (4, 4), (3, 4), (B, 4, 4) or (B, 3, 4) camera-to-world matrices, metres.
            K: optional (3, 3) or (B, 3, 3) OpenCV-style intrinsics in pixels; otherwise ``fx``
                (required), ``fy`` (default ``fx``), ``cx`` (default ``width / 2``), ``cy``
                (default ``height / 2``), each a scalar or one value per camera.
            width, height: image size in pixels.
            near, far: clipping depths in metres.
        """
        m = cls._homogeneous(c2w, "c2w")
        flip = OPENGL_TO_OPENCV.to(m.device)
        w2c = cls._rigid_inverse(m @ flip)
        Kt = cls._intrinsics(K, fx, fy, cx, cy, width, height, m.shape[0], m.device)
        return cls(Kt.float(), w2c.float(), width, height, near, far)

    @classmethod
    def from_blender(
        cls,
        camera_angle_x: Any,
        transform_matrix: ArrayLike,
        width: int,
        height: int,
        near: float = 0.01,
        far: float = 100.0,
    ) -> "Cameras":
        """Cameras from a NeRF-synthetic / Blender ``transforms.json`` (Vid2Sim GSO).

        Args:
            camera_angle_x: horizontal field of view in radians (scalar or one per camera).
            transform_matrix: (4, 4) or (B, 4, 4) OpenGL camera-to-world matrices.
            width, height: image size in pixels (of the images actually used).

        ``fx = fy = 0.5 width / tan(0.5 camera_angle_x)``, ``cx = width / 2``, ``cy = height / 2``.
        """
        m = cls._homogeneous(transform_matrix, "transform_matrix")
        ang = _as_tensor(camera_angle_x, "camera_angle_x", dtype=torch.float64).reshape(-1).cpu()
        if ang.numel() not in (1, m.shape[0]):
            raise ValueError(f"camera_angle_x must be a scalar or have {m.shape[0]} entries, got {ang.numel()}")
        if not bool(((ang > 0) & (ang < math.pi)).all()):
            raise ValueError(f"camera_angle_x must be in (0, pi) radians, got {ang.tolist()}")
        f = 0.5 * width / torch.tan(0.5 * ang)
        return cls.from_opengl_c2w(m, fx=f, fy=f, width=width, height=height, near=near, far=far)

    @classmethod
    def from_opencv(
        cls,
        rvec: ArrayLike,
        tvec: ArrayLike,
        K: ArrayLike,
        width: int,
        height: int,
        near: float = 0.01,
        far: float = 100.0,
    ) -> "Cameras":
        """Cameras from OpenCV extrinsics: Rodrigues ``rvec`` and ``tvec`` with ``x_cam = R x_world + t``.

        Args:
            rvec: (3,), (3, 1), (B, 3) or (B, 3, 1) rotation vectors (radians).
            tvec: (3,), (3, 1), (B, 3) or (B, 3, 1) translations (metres).
            K: (3, 3) or (B, 3, 3) intrinsics in pixels.
        """
        R = rodrigues(rvec)
        dev = R.device
        t = _as_tensor(tvec, "tvec", dtype=torch.float64, device=dev)
        if t.ndim in (2, 3) and t.shape[-1] == 1:
            t = t[..., 0]
        if t.ndim == 1:
            t = t[None]
        if t.ndim != 2 or t.shape[-1] != 3 or t.shape[0] != R.shape[0]:
            raise ValueError(f"tvec must have shape (3,) or (B, 3) with B = {R.shape[0]} (as rvec), got {tuple(t.shape)}")
        w2c = torch.zeros(R.shape[0], 4, 4, dtype=torch.float64, device=dev)
        w2c[:, :3, :3] = R.double()
        w2c[:, :3, 3] = t
        w2c[:, 3, 3] = 1.0
        return cls(_as_tensor(K, "K", device=dev), w2c.float(), width, height, near, far)

    @classmethod
    def look_at(
        cls,
        eye: ArrayLike,
        target: ArrayLike = (0.0, 0.0, 0.0),
        up: ArrayLike = (0.0, 1.0, 0.0),
        *,
        fov_y_deg: Optional[float] = None,
        K: Optional[ArrayLike] = None,
        width: int,
        height: int,
        near: float = 0.01,
        far: float = 100.0,
    ) -> "Cameras":
        """Cameras at ``eye`` looking at ``target`` with ``up`` pointing up in the image (world up +y).

        Args:
            eye: (3,) or (B, 3) camera centres, metres.
            target: (3,) or (B, 3) points on the optical axis.
            up: (3,) world direction that appears upward in the image (image -y).
            fov_y_deg: vertical field of view in degrees (square pixels, principal point at the
                image centre: ``fy = fx = 0.5 height / tan(0.5 fov_y)``); or give ``K`` instead.
        """
        e = _as_tensor(eye, "eye", dtype=torch.float64).reshape(-1, 3)
        tg = _as_tensor(target, "target", dtype=torch.float64, device=e.device).reshape(-1, 3)
        u = _as_tensor(up, "up", dtype=torch.float64, device=e.device).reshape(-1, 3)
        n = max(e.shape[0], tg.shape[0], u.shape[0])
        e, tg, u = e.expand(n, 3), tg.expand(n, 3), u.expand(n, 3)
        fwd = tg - e
        fnorm = fwd.norm(dim=-1)
        right = torch.linalg.cross(fwd, u, dim=-1)
        rnorm = right.norm(dim=-1)
        for i in range(n):
            if float(fnorm[i]) < 1e-12:
                raise ValueError(f"look_at: eye and target coincide for camera index {i}")
            if float(rnorm[i]) < 1e-9 * float(fnorm[i]) * float(u[i].norm()):
                raise ValueError(f"look_at: the viewing direction is parallel to up for camera index {i}; choose another up")
        fwd = fwd / fnorm[:, None]
        right = right / rnorm[:, None]
        down = torch.linalg.cross(fwd, right, dim=-1)
        R = torch.stack([right, down, fwd], dim=-2)  # rows: camera axes in world coordinates
        w2c = torch.zeros(n, 4, 4, dtype=torch.float64, device=e.device)
        w2c[:, :3, :3] = R
        w2c[:, :3, 3] = -(R @ e[:, :, None])[..., 0]
        w2c[:, 3, 3] = 1.0
        if (K is None) == (fov_y_deg is None):
            raise ValueError("look_at needs exactly one of fov_y_deg or K")
        if K is None:
            if not 0.0 < float(fov_y_deg) < 180.0:
                raise ValueError(f"fov_y_deg must be in (0, 180), got {fov_y_deg}")
            f = 0.5 * height / math.tan(math.radians(float(fov_y_deg)) / 2.0)
            Kt = cls._intrinsics(None, f, f, None, None, width, height, n, e.device)
        else:
            Kt = _as_tensor(K, "K", device=e.device)
        return cls(Kt, w2c.float(), width, height, near, far)

    # ------------------------------------------------------------------ container protocol

    def __len__(self) -> int:
        return int(self.K.shape[0])

    def __getitem__(self, idx: Index) -> "Cameras":
        """A sub-batch; an int index keeps the batch dimension (returns B = 1)."""
        if isinstance(idx, (int, np.integer)):
            n = len(self)
            i = int(idx)
            if not -n <= i < n:
                raise IndexError(f"camera index {i} out of range for {n} cameras")
            sel: Any = slice(i % n, i % n + 1)
        elif isinstance(idx, slice):
            sel = idx
        else:
            sel = torch.as_tensor(np.asarray(idx) if not isinstance(idx, torch.Tensor) else idx, device=self.K.device)
            if sel.dtype == torch.bool:
                sel = sel.nonzero()[:, 0]
            sel = sel.long().reshape(-1)
        K, w2c = self.K[sel], self.w2c[sel]
        if K.shape[0] == 0:
            raise ValueError(f"camera index {idx!r} selects no camera (of {len(self)})")
        return Cameras._trusted(K, w2c, self.width, self.height, self.near, self.far)

    def __repr__(self) -> str:
        return (
            f"Cameras(B={len(self)}, width={self.width}, height={self.height}, near={self.near}, far={self.far}, "
            f"device={self.device})"
        )

    @property
    def device(self) -> torch.device:
        return self.K.device

    def to(self, device: torch.device | str) -> "Cameras":
        return Cameras._trusted(self.K.to(device), self.w2c.to(device), self.width, self.height, self.near, self.far)

    def with_centre_moved(self, index: int, offset: ArrayLike) -> "Cameras":
        """The same cameras with camera ``index``'s centre moved by ``offset`` (3,) metres in the
        world frame and its orientation kept (a calibration error of the position alone):
        ``t' = t - R offset``."""
        w2c = self.w2c.clone()
        e = torch.as_tensor(offset, dtype=w2c.dtype, device=w2c.device).reshape(3)
        w2c[index, :3, 3] = w2c[index, :3, 3] - w2c[index, :3, :3] @ e
        return Cameras._trusted(self.K.clone(), w2c, self.width, self.height, self.near, self.far)

    @classmethod
    def cat(cls, cameras: Sequence["Cameras"]) -> "Cameras":
        """Concatenate batches; all must share width, height, near, far and device."""
        cams = list(cameras)
        if not cams:
            raise ValueError("Cameras.cat needs at least one Cameras")
        first = cams[0]
        for i, c in enumerate(cams):
            if not isinstance(c, Cameras):
                raise ValueError(f"Cameras.cat: item {i} is a {type(c).__name__}, expected Cameras")
            if (c.width, c.height) != (first.width, first.height):
                raise ValueError(
                    f"Cameras.cat: item {i} has image size {c.width}x{c.height}, item 0 has "
                    f"{first.width}x{first.height}; all must match (use .scaled())"
                )
            if (c.near, c.far) != (first.near, first.far):
                raise ValueError(f"Cameras.cat: item {i} has near/far {c.near}/{c.far}, item 0 has {first.near}/{first.far}")
            if c.device != first.device:
                raise ValueError(f"Cameras.cat: item {i} is on {c.device}, item 0 on {first.device}")
        return cls._trusted(
            torch.cat([c.K for c in cams]), torch.cat([c.w2c for c in cams]), first.width, first.height, first.near, first.far
        )

    # ------------------------------------------------------------------ properties

    @property
    def R(self) -> torch.Tensor:
        """(B, 3, 3) world->camera rotation."""
        return self.w2c[:, :3, :3]

    @property
    def t(self) -> torch.Tensor:
        """(B, 3) world->camera translation (metres)."""
        return self.w2c[:, :3, 3]

    @property
    def centers(self) -> torch.Tensor:
        """(B, 3) camera centres in world coordinates (metres), ``-R^T t``."""
        return -(self.R.transpose(-1, -2) @ self.t[..., None])[..., 0]

    @property
    def fx(self) -> torch.Tensor:
        """(B,) focal length along x in pixels."""
        return self.K[:, 0, 0]

    @property
    def fy(self) -> torch.Tensor:
        """(B,) focal length along y in pixels."""
        return self.K[:, 1, 1]

    @property
    def cx(self) -> torch.Tensor:
        """(B,) principal point x in pixels (image left edge is 0)."""
        return self.K[:, 0, 2]

    @property
    def cy(self) -> torch.Tensor:
        """(B,) principal point y in pixels (image top edge is 0)."""
        return self.K[:, 1, 2]

    def c2w_opencv(self) -> torch.Tensor:
        """(B, 4, 4) camera->world transform in the OpenCV camera convention."""
        return self._rigid_inverse(self.w2c)

    def c2w_opengl(self) -> torch.Tensor:
        """(B, 4, 4) OpenGL/Blender camera->world (x right, y up, z back); inverse of :meth:`from_opengl_c2w`."""
        return self.c2w_opencv() @ OPENGL_TO_OPENCV.to(device=self.device, dtype=self.w2c.dtype)

    # ------------------------------------------------------------------ geometry

    def _batched_points(self, points: torch.Tensor, name: str = "points") -> torch.Tensor:
        if not isinstance(points, torch.Tensor):
            points = _as_tensor(points, name, device=self.device)
        if not points.is_floating_point():
            points = points.float()
        if points.ndim == 2:
            points = points[None].expand(len(self), -1, -1)
        if points.ndim != 3 or points.shape[-1] != 3 or points.shape[0] != len(self):
            raise ValueError(f"{name} must have shape (N, 3) or (B, N, 3) with B = {len(self)}, got {tuple(points.shape)}")
        return points

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """Camera-space coordinates ``R x + t``.

        Args:
            points: (N, 3) world points shared by all cameras, or (B, N, 3), metres.

        Returns:
            (B, N, 3) camera-space points (OpenCV frame), in the dtype of ``points``.
        """
        p = self._batched_points(points)
        R = self.R.to(p.dtype)
        t = self.t.to(p.dtype)
        return p @ R.transpose(-1, -2) + t[:, None, :]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points to pixels.

        Args:
            points: (N, 3) or (B, N, 3) world points (metres).

        Returns:
            ``(pixels, depth)``: (B, N, 2) continuous pixel coordinates ``(u, v)`` (pixel
            ``(i, j)`` has its centre at ``(i + 0.5, j + 0.5)``) and (B, N) camera-space ``z``.
            Points at or behind the camera (``z <= 0``) still get ``fx x / z + cx`` (meaningless,
            inf at ``z = 0``): check ``depth`` before using them.
        """
        pc = self.world_to_camera(points)
        z = pc[..., 2]
        K = self.K.to(pc.dtype)
        u = K[:, None, 0, 0] * pc[..., 0] / z + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * pc[..., 1] / z + K[:, None, 1, 2]
        return torch.stack([u, v], -1), z

    def unproject(self, pixels: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Lift pixels with camera-space depth back to world points (inverse of :meth:`project`).

        Args:
            pixels: (B, N, 2) or (N, 2) continuous pixel coordinates ``(u, v)``.
            depth: (B, N) or (N,) camera-space ``z`` (metres), not the distance along the ray.

        Returns:
            (B, N, 3) world points.
        """
        pix = pixels if isinstance(pixels, torch.Tensor) else _as_tensor(pixels, "pixels", device=self.device)
        z = depth if isinstance(depth, torch.Tensor) else _as_tensor(depth, "depth", device=self.device)
        if pix.ndim == 2:
            pix = pix[None].expand(len(self), -1, -1)
        if z.ndim == 1:
            z = z[None].expand(len(self), -1)
        if pix.ndim != 3 or pix.shape[-1] != 2 or pix.shape[0] != len(self):
            raise ValueError(f"pixels must have shape (N, 2) or (B, N, 2) with B = {len(self)}, got {tuple(pix.shape)}")
        if z.shape != pix.shape[:2]:
            raise ValueError(f"depth must have shape {tuple(pix.shape[:2])} to match pixels, got {tuple(z.shape)}")
        K = self.K.to(pix.dtype)
        x = (pix[..., 0] - K[:, None, 0, 2]) / K[:, None, 0, 0] * z
        y = (pix[..., 1] - K[:, None, 1, 2]) / K[:, None, 1, 1] * z
        pc = torch.stack([x, y, z.to(pix.dtype)], -1)
        R = self.R.to(pix.dtype)
        t = self.t.to(pix.dtype)
        return (pc - t[:, None, :]) @ R

    def scaled(self, factor: float) -> "Cameras":
        """The same cameras for images resized by ``factor``.

        The new size is ``round(width * factor) x round(height * factor)``; ``K`` rows are scaled
        by the exact ratios ``new_width / width`` and ``new_height / height`` (pixel edges map to
        pixel edges, so ``cx`` scales without a half-pixel shift).
        """
        if not (isinstance(factor, (int, float)) and math.isfinite(factor) and factor > 0):
            raise ValueError(f"scale factor must be a positive number, got {factor!r}")
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        if w < 1 or h < 1:
            raise ValueError(f"scaling {self.width}x{self.height} by {factor} gives an empty image ({w}x{h})")
        s = torch.tensor([w / self.width, h / self.height, 1.0], dtype=self.K.dtype, device=self.device)
        return Cameras._trusted(self.K * s[None, :, None], self.w2c, w, h, self.near, self.far)

    # ------------------------------------------------------------------ serialization

    def to_dict(self) -> dict:
        """JSON-serializable dict (nested lists of floats) for checkpoints and scene files."""
        return {
            "K": self.K.detach().cpu().tolist(),
            "w2c": self.w2c.detach().cpu().tolist(),
            "width": self.width,
            "height": self.height,
            "near": self.near,
            "far": self.far,
        }

    @classmethod
    def from_dict(cls, d: dict, device: torch.device | str = "cpu") -> "Cameras":
        """Inverse of :meth:`to_dict` (validates)."""
        missing = {"K", "w2c", "width", "height"} - set(d)
        if missing:
            raise ValueError(f"camera dict is missing keys {sorted(missing)}")
        return cls(
            torch.tensor(d["K"], dtype=torch.float32, device=device),
            torch.tensor(d["w2c"], dtype=torch.float32, device=device),
            d["width"],
            d["height"],
            d.get("near", 0.01),
            d.get("far", 100.0),
        )

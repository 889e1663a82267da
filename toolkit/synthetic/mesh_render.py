"""The truth renderer: ray casting a textured, deforming triangle mesh with Warp.

It is deliberately *different* from the fitting renderer (3D Gaussian splatting): the object is
a closed triangle surface whose vertices are carried by the simulation (topology fixed), hit by
one ray per sample (``wp.Mesh`` + ``wp.mesh_query_ray``, BVH refit per frame), so silhouettes are
sharp and the nearest surface wins (a z-buffer). Shading:

* albedo: the procedural texture evaluated at the hit point's REST-pose position (barycentric
  interpolation of the rest vertices), so the pattern is glued to the material;
* Lambert + ambient from one fixed directional light, with smooth (area-weighted vertex)
  normals of the deformed surface: brightness changes as the object turns, which Gaussians
  with fixed colours cannot reproduce exactly;
* optional ground plane ``y = ground_height`` (grey checker, same light) and a constant sky; the
  background plate is the same scene without the object.

Anti-aliasing: ``supersample`` x ``supersample`` samples per pixel on a regular grid. Outputs,
per camera: straight (non-premultiplied) RGB, alpha = object coverage, and the plate:

* ``rgb`` is the mean colour of the samples that hit the object where ``alpha > 0`` and the
  plate elsewhere, so ``alpha * rgb`` is the object on black and
  ``alpha * rgb + (1 - alpha) * background`` is the photograph.

Camera convention: :class:`toolkit.cameras.Cameras` (OpenCV, pixel centres at ``i + 0.5``).
Runs on ``cpu`` and ``cuda`` (``device``); shading is done in numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import warp as wp

from toolkit.cameras import Cameras
from toolkit.synthetic.texture import ground_checker

__all__ = ["Lighting", "RenderOutput", "MeshRenderer", "vertex_normals"]


@dataclass(frozen=True)
class Lighting:
    """One directional light plus ambient.

    Attributes:
        direction: (3,) world direction *towards* the light (normalized on use).
        ambient: fraction of the albedo seen in full shadow, in [0, 1].
    """

    direction: tuple[float, float, float] = (0.35, 1.0, 0.25)
    ambient: float = 0.3

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-9:
            raise ValueError(f"light direction must be a non-zero 3-vector, got {self.direction!r}")
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f"ambient must be in [0, 1], got {self.ambient!r}")

    @property
    def unit_direction(self) -> np.ndarray:
        d = np.asarray(self.direction, dtype=np.float64)
        return d / np.linalg.norm(d)

    def shade(self, normals: np.ndarray) -> np.ndarray:
        """(N, 3) unit normals -> (N,) shading factor ``ambient + (1 - ambient) max(0, n . l)``."""
        return (self.ambient + (1.0 - self.ambient) * np.maximum(normals @ self.unit_direction, 0.0)).astype(np.float32)


@dataclass
class RenderOutput:
    """One camera's image.

    Attributes:
        rgb: (H, W, 3) float32 straight colour in [0, 1] (object colour where alpha > 0, plate elsewhere).
        alpha: (H, W) float32 object coverage in [0, 1].
        background: (H, W, 3) float32 plate (the scene without the object).
    """

    rgb: np.ndarray
    alpha: np.ndarray
    background: np.ndarray

    def composite(self) -> np.ndarray:
        """(H, W, 3) the photograph: object over the plate."""
        a = self.alpha[..., None]
        return a * self.rgb + (1.0 - a) * self.background

    def rgba8(self) -> np.ndarray:
        """(H, W, 4) uint8 straight RGBA (alpha = coverage)."""
        rgba = np.concatenate([self.rgb, self.alpha[..., None]], axis=-1)
        return np.round(np.clip(rgba, 0.0, 1.0) * 255.0).astype(np.uint8)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals of a triangle mesh (outward for CCW faces)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 x area
    out = np.zeros_like(v)
    for c in range(3):
        for k in range(3):
            out[:, c] += np.bincount(f[:, k], weights=fn[:, c], minlength=len(v))
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return (out / np.maximum(norm, 1e-20)).astype(np.float32)


@wp.kernel
def _cast(
    mesh: wp.uint64,
    has_mesh: int,
    rest: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    rot: wp.mat33,
    eye: wp.vec3,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    ss: int,
    hit_out: wp.array(dtype=wp.int32),
    t_out: wp.array(dtype=float),
    rest_out: wp.array(dtype=wp.vec3),
    normal_out: wp.array(dtype=wp.vec3),
    dir_out: wp.array(dtype=wp.vec3),
):
    """One ray per (row, column, sample); samples on an ss x ss grid inside the pixel."""
    tid = wp.tid()
    n_sub = ss * ss
    pix = tid / n_sub
    s = tid - pix * n_sub
    row = pix / width
    col = pix - row * width
    sy = s / ss
    sx = s - sy * ss
    u = float(col) + (float(sx) + 0.5) / float(ss)
    v = float(row) + (float(sy) + 0.5) / float(ss)
    d = wp.normalize(rot @ wp.vec3((u - cx) / fx, (v - cy) / fy, 1.0))
    dir_out[tid] = d
    hit_out[tid] = 0
    if has_mesh != 0:
        q = wp.mesh_query_ray(mesh, eye, d, 1.0e6)
        if q.result:
            f = q.face
            a = indices[3 * f]
            b = indices[3 * f + 1]
            c = indices[3 * f + 2]
            w = 1.0 - q.u - q.v
            rest_out[tid] = q.u * rest[a] + q.v * rest[b] + w * rest[c]
            n = q.u * normals[a] + q.v * normals[b] + w * normals[c]
            if wp.length(n) < 1.0e-12:
                n = q.normal
            n = wp.normalize(n)
            if wp.dot(n, d) > 0.0:
                n = -n  # seen from inside (tangled surface): light the side that faces the camera
            normal_out[tid] = n
            t_out[tid] = q.t
            hit_out[tid] = 1


class MeshRenderer:
    """Ray-cast renderer of one deforming closed mesh (see the module docstring).

    Args:
        faces: (F, 3) triangle vertex indices (fixed topology, CCW = outward).
        rest_vertices: (V, 3) rest-pose vertex positions, metres (texture coordinates).
        texture: ``(N, 3) rest points -> (N, 3) albedo`` (e.g. :class:`ProceduralTexture`).
        device: Warp device (``"cpu"``, ``"cuda:0"``).
        supersample: samples per pixel side (1 = one ray through each pixel centre).
        lighting: light direction and ambient level.
        ground: render the ground plane ``y = ground_height`` (else only the sky colour).
        ground_height: y of the ground, metres.
        ground_period: checker cell size of the ground, metres.
        sky_color: RGB of rays that hit nothing.

    Example::

        r = MeshRenderer(mesh.faces, mesh.vertices, ProceduralTexture.from_seed(0))
        r.set_vertices(deformed_vertices)
        out = r.render(cameras[0])     # RenderOutput with rgb, alpha, background
    """

    def __init__(
        self,
        faces: np.ndarray,
        rest_vertices: np.ndarray,
        texture: Callable[[np.ndarray], np.ndarray],
        *,
        device: str = "cpu",
        supersample: int = 2,
        lighting: Lighting = Lighting(),
        ground: bool = True,
        ground_height: float = 0.0,
        ground_period: float = 0.2,
        sky_color: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ):
        faces = np.asarray(faces)
        rest = np.asarray(rest_vertices, dtype=np.float64)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"faces must have shape (F, 3) with F >= 1, got {faces.shape}")
        if rest.ndim != 2 or rest.shape[1] != 3 or not np.all(np.isfinite(rest)):
            raise ValueError(f"rest_vertices must be a finite (V, 3) array, got shape {rest.shape}")
        if faces.min() < 0 or faces.max() >= len(rest):
            raise ValueError(f"faces index vertices 0..{len(rest) - 1}, got indices {faces.min()}..{faces.max()}")
        if not (isinstance(supersample, int) and 1 <= supersample <= 8):
            raise ValueError(f"supersample must be an integer in 1..8, got {supersample!r}")
        self.device = str(wp.get_device(device))
        self.faces = faces.astype(np.int32)
        self.texture = texture
        self.supersample = supersample
        self.lighting = lighting
        self.ground = ground
        self.ground_height = float(ground_height)
        self.ground_period = float(ground_period)
        self.sky_color = np.asarray(sky_color, dtype=np.float32)
        self._indices = wp.array(self.faces.reshape(-1), dtype=wp.int32, device=self.device)
        self._rest = wp.array(rest.astype(np.float32), dtype=wp.vec3, device=self.device)
        self._points = wp.array(rest.astype(np.float32), dtype=wp.vec3, device=self.device)
        self._normals = wp.array(vertex_normals(rest, self.faces), dtype=wp.vec3, device=self.device)
        self._mesh = wp.Mesh(points=self._points, indices=self._indices)
        self._buffers: dict = {}

    @property
    def n_vertices(self) -> int:
        return self._points.shape[0]

    def set_vertices(self, vertices: np.ndarray) -> None:
        """Move the surface to ``vertices`` (V, 3) (same topology) and refit the BVH."""
        v = np.asarray(vertices, dtype=np.float32)
        if v.shape != (self.n_vertices, 3):
            raise ValueError(f"vertices must have shape ({self.n_vertices}, 3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("vertices contain NaN or inf values")
        self._points.assign(v)
        self._normals.assign(vertex_normals(v, self.faces))
        self._mesh.refit()

    def _alloc(self, n: int):
        if self._buffers.get("n") != n:
            dev = self.device
            self._buffers = {
                "n": n,
                "hit": wp.zeros(n, dtype=wp.int32, device=dev),
                "t": wp.zeros(n, dtype=float, device=dev),
                "rest": wp.zeros(n, dtype=wp.vec3, device=dev),
                "normal": wp.zeros(n, dtype=wp.vec3, device=dev),
                "dir": wp.zeros(n, dtype=wp.vec3, device=dev),
            }
        return self._buffers

    def _cast(self, camera: Cameras, with_object: bool):
        if len(camera) != 1:
            raise ValueError(f"render one camera at a time (got a batch of {len(camera)}); index it, e.g. cameras[i]")
        H, W, ss = camera.height, camera.width, self.supersample
        n = H * W * ss * ss
        buf = self._alloc(n)
        c2w = camera.c2w_opencv()[0].detach().cpu().double().numpy()
        K = camera.K[0].detach().cpu().double().numpy()
        wp.launch(
            _cast,
            dim=n,
            inputs=[
                self._mesh.id, int(with_object), self._rest, self._normals, self._indices,
                wp.mat33(*c2w[:3, :3].astype(np.float32).reshape(-1)), wp.vec3(*c2w[:3, 3].astype(np.float32)),
                float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), W, ss,
                buf["hit"], buf["t"], buf["rest"], buf["normal"], buf["dir"],
            ],
            device=self.device,
        )
        eye = c2w[:3, 3]
        return buf, eye, (H, W, ss * ss)

    def _background(self, dirs: np.ndarray, eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample background colour and the distance to the ground (inf where none)."""
        col = np.broadcast_to(self.sky_color, dirs.shape).copy()
        t_ground = np.full(len(dirs), np.inf)
        if self.ground and eye[1] > self.ground_height:
            down = dirs[:, 1] < -1e-9
            t = (self.ground_height - eye[1]) / dirs[down, 1]
            t_ground[down] = t
            pts = eye[None] + t[:, None] * dirs[down]
            up = np.array([[0.0, 1.0, 0.0]])
            col[down] = ground_checker(pts, self.ground_period) * self.lighting.shade(up)[0]
        return col, t_ground

    def render_background(self, camera: Cameras) -> np.ndarray:
        """(H, W, 3) float32 background plate of one camera (the scene without the object)."""
        buf, eye, (H, W, S) = self._cast(camera, with_object=False)
        bg, _ = self._background(buf["dir"].numpy().astype(np.float64), eye)
        return bg.reshape(H, W, S, 3).mean(axis=2).astype(np.float32)

    def render(self, camera: Cameras) -> RenderOutput:
        """Render one camera (a length-1 :class:`Cameras`) with the current vertices."""
        buf, eye, (H, W, S) = self._cast(camera, with_object=True)
        dirs = buf["dir"].numpy().astype(np.float64)
        bg, t_ground = self._background(dirs, eye)
        hit = buf["hit"].numpy().astype(bool)
        hit &= buf["t"].numpy() < t_ground  # z-buffer against the ground plane
        obj = np.zeros_like(bg)
        if hit.any():
            obj[hit] = self.texture(buf["rest"].numpy()[hit]) * self.lighting.shade(buf["normal"].numpy()[hit])[:, None]
        hit3 = hit.reshape(H, W, S)
        count = hit3.sum(axis=2)
        alpha = (count / S).astype(np.float32)
        obj_rgb = (obj.reshape(H, W, S, 3) * hit3[..., None]).sum(axis=2) / np.maximum(count, 1)[..., None]
        plate = bg.reshape(H, W, S, 3).mean(axis=2)
        rgb = np.where(count[..., None] > 0, obj_rgb, plate).astype(np.float32)
        return RenderOutput(rgb=np.clip(rgb, 0, 1), alpha=alpha, background=plate.astype(np.float32))

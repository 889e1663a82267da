"""A second truth renderer: particles drawn as opaque screen-space discs with a z-buffer.

It exists to image a scene *differently* from :mod:`toolkit.synthetic.mesh_render` (a ray-cast
textured mesh) and from the fitting side's Gaussian splatting, for the ``render_style="points"``
scene variant (:mod:`toolkit.synthetic.variants`, issue #20). Definition, per camera:

* every point ``p`` (world frame, metres) with camera-space depth ``z > near`` is projected with
  the pinhole model of :class:`toolkit.cameras.Cameras` (OpenCV frame: x right, y down, z
  forward; pixel ``(i, j)`` has its centre at ``(i + 0.5, j + 0.5)``) to ``(u, v)``;
* it is drawn as a disc of radius ``r_px = max(1, fx * radius_m / z)`` pixels: pixel ``(i, j)``
  is covered when ``(i + 0.5 - u)^2 + (j + 0.5 - v)^2 <= r_px^2`` (a radius >= 1 px always covers
  at least one pixel centre);
* z-buffer: a covered pixel takes the colour of the covering disc of smallest ``z`` (a disc's
  depth is its point's ``z`` everywhere on it; ties go to the lower point index);
* colour: the point's albedo (``colours``, fixed per point index, so a texture carried by the
  particles moves with the material) times a sphere-impostor Lambert term: at the offset
  ``(a, b) = (i + 0.5 - u, j + 0.5 - v) / r_px`` the camera-space normal is
  ``(a, b, -sqrt(1 - a^2 - b^2))`` and the factor is ``ambient + (1 - ambient) max(0, n . l)``
  (``l`` the unit direction towards the light, world frame; no light: factor 1);
* output: (H, W, 4) uint8 straight RGBA, alpha = coverage (255 inside a disc, 0 elsewhere), RGB
  the shaded disc colour where covered and ``background`` elsewhere, as the generator writes its
  frames (:mod:`toolkit.synthetic.layout`: RGB = the plate where alpha is 0);
* supersampling: where a disc would be under a pixel (``fx * radius_m / z < 1``), the 1-px floor
  would draw it up to several times its size and swell the silhouette (at 64 px, 5 mm discs seen
  from 1.1 m are 0.4 px: the floor drew them 2.5x too large and the masks came out 10-20 % larger in
  area than the mesh truth's). The image is then drawn at ``s`` times the resolution, ``s`` the
  smallest integer that brings every disc to >= 1 px (at most :data:`MAX_SUPERSAMPLE`), and each
  ``s x s`` block becomes one pixel: covered when at least half its samples are (alpha 255), with
  the mean colour of its covered samples; else alpha 0 and ``background``.

No anti-aliasing: silhouettes are hard pixel staircases and the surface shows the disc pattern,
which is the point of the style.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

__all__ = ["DISC_RADIUS_FACTOR", "MAX_SUPERSAMPLE", "supersample_factor", "PointStyle", "particle_spacing", "disc_radius_px", "texture_from_record", "camera_matrices",
           "render_points"]

#: disc radius (metres, world) per unit of particle spacing: half of it, so the outermost particles
#: (half a spacing inside the surface) reach the surface; ``sqrt(2) / 2`` swells silhouettes
#: (mask IoU with the mesh truth 0.91 instead of 0.96 at 160 px)
DISC_RADIUS_FACTOR = 0.5
#: the largest supersampling factor :func:`render_points` chooses by itself (discs under 1/8 px stay floored)
MAX_SUPERSAMPLE = 8
_CHUNK_CANDIDATES = 4_000_000  # (point, pixel) pairs tested at once, bounds the memory used


def particle_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance of (N, 3) points, metres (N >= 2; duplicates ignored)."""
    from scipy.spatial import cKDTree

    p = np.unique(np.asarray(points, dtype=np.float64).reshape(-1, 3), axis=0)
    if len(p) < 2:
        raise ValueError(f"the particle spacing needs at least 2 distinct points, got {len(p)}")
    d, _ = cKDTree(p).query(p, k=2)
    return float(np.median(d[:, 1]))


def disc_radius_px(depth: np.ndarray, fx: float, radius_m: float) -> np.ndarray:
    """Disc radius in pixels of a world radius ``radius_m`` (metres) at camera depths ``depth``
    (metres, > 0): ``max(1, fx * radius_m / depth)`` (``fx`` in pixels)."""
    return np.maximum(1.0, fx * radius_m / np.asarray(depth, dtype=np.float64))


def supersample_factor(radius_px: np.ndarray) -> int:
    """The smallest integer ``s`` that draws every disc of true radius ``radius_px`` (pixels, before
    the 1-px floor) at >= 1 px, at most :data:`MAX_SUPERSAMPLE`; 1 when there is none or all are."""
    r = np.asarray(radius_px, dtype=np.float64)
    if r.size == 0 or r.min() >= 1.0:
        return 1
    return int(min(MAX_SUPERSAMPLE, math.ceil(1.0 / max(float(r.min()), 1e-9))))


def _downsample(rgba: np.ndarray, s: int, background: np.ndarray) -> np.ndarray:
    """(H*s, W*s, 4) uint8 -> (H, W, 4): a block is covered when half its samples are; its colour
    is the mean of its covered samples' (``background`` (H, W, 3) float in [0, 1] where not covered)."""
    H, W = rgba.shape[0] // s, rgba.shape[1] // s
    blocks = rgba.reshape(H, s, W, s, 4).astype(np.float64)
    cov = (blocks[..., 3] > 0).astype(np.float64)
    n = cov.sum(axis=(1, 3))
    mean = (blocks[..., :3] * cov[..., None]).sum(axis=(1, 3)) / np.maximum(n, 1.0)[..., None] / 255.0
    hit = n >= 0.5 * s * s
    rgb = np.where(hit[..., None], mean, background)
    rgb8 = np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.concatenate([rgb8, np.where(hit, 255, 0).astype(np.uint8)[..., None]], axis=2)


def _background_rgb(background: Optional[np.ndarray], width: int, height: int) -> np.ndarray:
    """(H, W, 3) float64 in [0, 1] of ``background`` ((H, W, 3 or 4) uint8 or float in [0, 1]); black for None."""
    if background is None:
        return np.zeros((height, width, 3))
    bg = np.asarray(background)
    bg = bg[..., :3].astype(np.float64) / 255.0 if bg.dtype == np.uint8 else bg[..., :3].astype(np.float64)
    if bg.shape != (height, width, 3):
        raise ValueError(f"background must be ({height}, {width}, 3), got {bg.shape}")
    return bg


def texture_from_record(record: Optional[dict]):
    """The texture a scene's ``ground_truth.json`` records (``render.texture``: a procedural or a
    constant texture of :mod:`toolkit.synthetic.texture`), or None if it records none it knows."""
    from toolkit.synthetic.texture import ConstantTexture, ProceduralTexture

    if not isinstance(record, dict):
        return None
    try:
        if record.get("kind") == "procedural":
            fields = {k: v for k, v in record.items() if k != "kind"}
            fields["colors"] = tuple(tuple(float(x) for x in c) for c in fields["colors"])
            for k in ("origin", "gradient_dir", "stripe_dir"):
                fields[k] = tuple(float(x) for x in fields[k])
            return ProceduralTexture(**fields)
        if record.get("kind") == "constant":
            return ConstantTexture(tuple(float(x) for x in record["color"]))
    except (KeyError, TypeError, ValueError):
        return None
    return None


def camera_matrices(c2w_opengl: Sequence, intrinsic: Sequence, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """``(K, w2c)`` float64 (3, 3) and (4, 4) OpenCV matrices of a camera recorded the way
    ``all_data.json`` records it (``c2w``: 4x4 or 3x4 OpenGL camera-to-world, metres;
    ``intrinsic``: 3x3 pixels), converted by :meth:`toolkit.cameras.Cameras.from_opengl_c2w`."""
    from toolkit.cameras import Cameras

    c2w = np.asarray(c2w_opengl, dtype=np.float64)
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
    cam = Cameras.from_opengl_c2w(c2w, np.asarray(intrinsic, dtype=np.float64), width=width, height=height)
    # float64 inverse of the OpenCV c2w (the stored float32 w2c loses ~1e-7 m, irrelevant but avoidable)
    c2w_cv = c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
    return cam.K[0].double().numpy(), np.linalg.inv(c2w_cv)


def _rasterize(u: np.ndarray, v: np.ndarray, r: np.ndarray, z: np.ndarray, width: int, height: int):
    """Z-buffered disc coverage: (H*W,) index of the winning point (-1: none), its depth, and the
    normalised offsets ``a, b`` of each pixel centre from its disc's centre."""
    n_pix = width * height
    win = np.full(n_pix, -1, dtype=np.int64)
    zbuf = np.full(n_pix, np.inf)
    off_a = np.zeros(n_pix)
    off_b = np.zeros(n_pix)
    k_all = np.ceil(r).astype(np.int64)
    for k in np.unique(k_all):
        idx = np.flatnonzero(k_all == k)
        dj, di = np.mgrid[-k:k + 1, -k:k + 1]
        di, dj = di.ravel(), dj.ravel()
        step = max(1, _CHUNK_CANDIDATES // len(di))
        for s in range(0, len(idx), step):
            pts = idx[s:s + step]
            i = np.floor(u[pts])[:, None].astype(np.int64) + di[None]  # all pixels whose centre may be in the disc
            j = np.floor(v[pts])[:, None].astype(np.int64) + dj[None]
            a = (i + 0.5 - u[pts, None]) / r[pts, None]
            b = (j + 0.5 - v[pts, None]) / r[pts, None]
            inside = (a * a + b * b <= 1.0) & (i >= 0) & (i < width) & (j >= 0) & (j < height)
            pix = (j * width + i)[inside]
            point = np.broadcast_to(pts[:, None], i.shape)[inside]
            depth = z[point]
            order = np.lexsort((point, depth, pix))  # per pixel: nearest first, then lowest index
            pix_s = pix[order]
            first = order[np.r_[True, pix_s[1:] != pix_s[:-1]]]
            p1, d1 = pix[first], depth[first]
            better = (d1 < zbuf[p1]) | ((d1 == zbuf[p1]) & (point[first] < win[p1]))
            p1, f1 = p1[better], first[better]
            win[p1], zbuf[p1] = point[f1], depth[f1]
            off_a[p1], off_b[p1] = a[inside][f1], b[inside][f1]
    return win, zbuf, off_a, off_b


def render_points(points: np.ndarray, colours: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int,
                  radius_m: float, background: Optional[np.ndarray] = None, *,
                  light_direction: Optional[Sequence[float]] = None, ambient: float = 0.3,
                  near: float = 0.01, supersample: Optional[int] = None) -> np.ndarray:
    """Render points as shaded opaque discs (definition in the module docstring).

    Args:
        points: (N, 3) world positions, metres.
        colours: (N, 3) albedo in [0, 1] (float) or uint8, per point index.
        K: (3, 3) OpenCV intrinsics, pixels.
        w2c: (4, 4) or (3, 4) world-to-camera (OpenCV frame) rigid transform, metres.
        width, height: image size, pixels.
        radius_m: disc radius in world units (metres), e.g. ``DISC_RADIUS_FACTOR * particle_spacing(...)``.
        background: (H, W, 3) uint8 (or float in [0, 1]) colour where no disc covers a pixel;
            None: black.
        light_direction: (3,) world direction towards the light (normalised here); None: no shading.
        ambient: shading floor in [0, 1].
        near: points with camera depth ``<= near`` metres are not drawn.
        supersample: draw at this many times the resolution and reduce (module docstring);
            None: :func:`supersample_factor` of the discs in view (1 where every disc is >= 1 px).

    Returns:
        (H, W, 4) uint8 straight RGBA; alpha 255 where a disc covers the pixel centre (supersampled:
        half the pixel's sample centres), else 0.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    col = np.asarray(colours)
    col = col.astype(np.float64) / 255.0 if col.dtype == np.uint8 else col.astype(np.float64)
    if col.shape != p.shape:
        raise ValueError(f"colours must be (N, 3) for N = {len(p)} points, got {col.shape}")
    if not (math.isfinite(radius_m) and radius_m > 0):
        raise ValueError(f"radius_m must be a positive length in metres, got {radius_m!r}")
    if supersample is not None and (isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer))
                                    or supersample < 1):
        raise ValueError(f"supersample must be None (chosen per view) or an integer >= 1, got {supersample!r}")
    K = np.asarray(K, dtype=np.float64)
    w2c = np.asarray(w2c, dtype=np.float64)
    R, t = w2c[:3, :3], w2c[:3, 3]
    pc = p @ R.T + t
    z = pc[:, 2]
    keep = np.flatnonzero(np.isfinite(z) & (z > near))
    zk = z[keep]
    u = K[0, 0] * pc[keep, 0] / zk + K[0, 2]
    v = K[1, 1] * pc[keep, 1] / zk + K[1, 2]
    bg = _background_rgb(background, width, height)
    if supersample is None:
        seen = (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
        supersample = supersample_factor(float(K[0, 0]) * radius_m / zk[seen])
    if supersample > 1:
        s = supersample
        Ks = np.diag([float(s), float(s), 1.0]) @ K
        fine = render_points(p, col, Ks, w2c, width * s, height * s, radius_m, None, light_direction=light_direction,
                             ambient=ambient, near=near, supersample=1)
        return _downsample(fine, s, bg)
    r = disc_radius_px(zk, float(K[0, 0]), radius_m)
    on = (u + r >= 0) & (u - r <= width) & (v + r >= 0) & (v - r <= height)
    keep, u, v, r, zk = keep[on], u[on], v[on], r[on], zk[on]
    win, _, a, b = _rasterize(u, v, r, zk, width, height)

    out_rgb = bg.reshape(-1, 3).copy()
    hit = win >= 0
    albedo = col[keep[win[hit]]]
    if light_direction is not None:
        l_world = np.asarray(light_direction, dtype=np.float64)
        l_cam = R @ (l_world / np.linalg.norm(l_world))
        ah, bh = a[hit], b[hit]
        cos = ah * l_cam[0] + bh * l_cam[1] - np.sqrt(np.clip(1.0 - ah * ah - bh * bh, 0.0, 1.0)) * l_cam[2]
        albedo = albedo * (ambient + (1.0 - ambient) * np.maximum(cos, 0.0))[:, None]
    out_rgb[hit] = albedo
    alpha = np.where(hit, 255, 0).astype(np.uint8)
    rgb8 = np.round(np.clip(out_rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.concatenate([rgb8, alpha[:, None]], axis=1).reshape(height, width, 4)


class PointStyle:
    """A scene's particle clouds drawn with :func:`render_points`, textured by frame-0 position.

    Args:
        clouds: per frame, (N, 3) particle positions, metres, the same particle at the same index
            in every frame (as the truth simulation writes them), so colours move with the material.
        texture: callable (N, 3) positions -> (N, 3) albedo in [0, 1], evaluated once at
            ``clouds[0]``.
        light_direction, ambient: shading (see :func:`render_points`).
        radius_factor: disc radius per unit of :func:`particle_spacing` of ``clouds[0]``.
    """

    def __init__(self, clouds: Sequence[np.ndarray], texture, light_direction: Optional[Sequence[float]] = None,
                 ambient: float = 0.3, radius_factor: float = DISC_RADIUS_FACTOR) -> None:
        self.clouds = [np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in clouds]
        sizes = {len(c) for c in self.clouds}
        if len(sizes) != 1:
            raise ValueError(f"the point clouds must hold the same particles in every frame, got sizes {sorted(sizes)}")
        self.colours = np.asarray(texture(self.clouds[0]), dtype=np.float64)
        self.spacing = particle_spacing(self.clouds[0])
        self.radius_m = radius_factor * self.spacing
        self.light_direction = None if light_direction is None else [float(x) for x in light_direction]
        self.ambient = float(ambient)
        self.radius_factor = float(radius_factor)
        self.texture_rule = "given"

    @classmethod
    def from_render_record(cls, clouds: Sequence[np.ndarray], render: dict, seed: int) -> "PointStyle":
        """The style of a generated scene: ``render`` is its ground truth's ``render`` record, whose
        ``texture``, ``light_direction`` and ``ambient`` are used when present; else a
        ``ProceduralTexture.from_seed(seed)`` spanning the frame-0 bounding box and the default
        :class:`~toolkit.synthetic.mesh_render.Lighting`."""
        from toolkit.synthetic.mesh_render import Lighting
        from toolkit.synthetic.texture import ProceduralTexture

        texture, rule = texture_from_record(render.get("texture")), "source ground_truth render.texture"
        if texture is None:
            p0 = np.asarray(clouds[0], dtype=np.float64).reshape(-1, 3)
            lo, hi = p0.min(axis=0), p0.max(axis=0)
            texture = ProceduralTexture.from_seed(seed, size=float(max(np.max(hi - lo), 1e-3)), origin=tuple((lo + hi) / 2))
            rule = f"ProceduralTexture.from_seed({seed}) on the frame-0 bounding box"
        d = Lighting()
        light = Lighting(tuple(render.get("light_direction") or d.direction), float(render.get("ambient", d.ambient)))
        style = cls(clouds, texture, light.direction, light.ambient)
        style.texture_rule = rule
        return style

    def record(self) -> dict:
        """JSON-ready description (for ``variant.json``)."""
        return {"style": "points", "n_points": len(self.colours), "particle_spacing_m": self.spacing,
                "radius_factor": self.radius_factor, "radius_m": self.radius_m,
                "supersample": "discs under 1 px: drawn at the resolution that makes them 1 px, then reduced",
                "texture": self.texture_rule,
                "light_direction": self.light_direction, "ambient": self.ambient}

    def render(self, frame: int, K: np.ndarray, w2c: np.ndarray, width: int, height: int,
               background: Optional[np.ndarray] = None) -> np.ndarray:
        """(H, W, 4) uint8 RGBA of frame ``frame`` seen by the camera ``(K, w2c)`` (OpenCV, pixels / metres)."""
        return render_points(self.clouds[frame], self.colours, K, w2c, width, height, self.radius_m, background,
                             light_direction=self.light_direction, ambient=self.ambient)

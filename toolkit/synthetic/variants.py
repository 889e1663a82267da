"""Perturbed copies of a scene folder: the same physics, imaged the way a real capture might be.

:func:`make_variant` reads a PAC-NeRF-layout folder (what :func:`~toolkit.synthetic.generate_scene`
writes, see :mod:`toolkit.synthetic.layout`) and writes a copy whose *observations* differ from the
generator's truth rendering while its ground truth stays correct for evaluation. What can change
(:class:`VariantSpec`; every default leaves that aspect unchanged), applied in this order
(re-rendering first, then colours and masks):

* **render style** (``render_style``, ``"source"`` or ``"points"``): with ``"points"`` every frame
  image of every camera (not the plates) is re-rendered by :mod:`toolkit.synthetic.point_render`
  from the truth particle cloud of that frame (``ground_truth.json`` ``point_clouds``; the same
  particle has the same index in every frame): each particle is an opaque screen-space disc of
  radius ``max(1 px, fx * r / z)`` with ``r = 0.5 * s`` (``s`` the median nearest-neighbour
  distance of the frame-0 cloud, metres; ``z`` the particle's camera depth), z-buffered by ``z``,
  seen with the *true* camera of the source (``all_data.json``: OpenGL ``c2w``, ``intrinsic``).
  A particle's colour is the source's texture (``render.texture`` of its ground truth; else a
  :class:`~toolkit.synthetic.texture.ProceduralTexture` seeded with ``seed``) at its frame-0
  position, so the pattern moves with the material, times a sphere-impostor Lambert term with
  the source's light (``render.light_direction``, ``render.ambient``; else
  :class:`~toolkit.synthetic.mesh_render.Lighting`'s defaults). Alpha is coverage (255 in a
  disc, else 0; no anti-aliasing), the colour outside the discs is the camera's background plate
  (``r_{cam}_-1.png``; black without one), so the images keep the generator's RGBA convention and
  their alpha is the new mask; when the source has ``a_`` mask files they are rewritten with
  it. ``variant.json`` records the radius, spacing, texture, light and the pooled IoU of the new
  masks (alpha >= 0.5) with the source's.
* **mask noise** (``mask_noise`` = p in [0, 1]): the binary mask of an image is ``mask >= 0.5``
  (the source's mask: its ``a_`` files, else the image's alpha; the re-rendered alpha under
  ``render_style="points"``). Its *boundary pixels* are the
  pixels with at least one 4-neighbour (up, down, left, right, inside the image) of the other
  value, on both sides of the edge. In every camera x frame, ``round(p * n_boundary)`` of them,
  drawn uniformly without replacement (seeded), are flipped: mask 1 where it was < 0.5, else 0;
  the other pixels keep their (soft) values. The noisy masks are written as ``data/a_{cam}_{frame}.png``
  (RGBA: the image's colours, alpha = the mask), which the reader prefers to the image alpha; the
  images themselves are not changed by this option.
* **calibration error** (``calibration_deg``, ``calibration_m``): each camera's recorded pose is
  rotated about its own centre by ``calibration_deg`` degrees about a random axis and its centre
  moved ``calibration_m`` metres in a random direction (both seeded, per camera). In OpenGL
  camera-to-world terms: ``R_new = R_rand @ R_old`` (so ``R_new R_old^T = R_rand``, whose angle is
  exactly ``calibration_deg``) and ``C_new = C_old + calibration_m * u`` (``|u| = 1``). The images
  stay as rendered with the true cameras: a fit sees slightly wrong cameras. Intrinsics unchanged.
* **photometric change** (``gamma``, ``brightness``, ``tint``, ``blur_px``, ``noise_std``): every
  colour value ``x`` in [0, 1] of the frames and background plates becomes
  ``clip(brightness * tint[c] * x ** gamma + blur + noise, 0, 1)``, in this order: the power and
  gains per channel c, a Gaussian blur of standard deviation ``blur_px`` pixels (reflecting edges),
  additive Gaussian noise of standard deviation ``noise_std`` (seeded), then rounding to 8 bits.
  Alpha (hence the masks) and loss-exclusion masks are unchanged.
* **frame-rate mismatch**: ``frame_stride = k`` keeps frames 0, k, 2k, ... (a video taken at
  fps / k; the times stay true); ``fps_scale = s`` makes the folder *claim* ``s`` times the true
  frame rate (the times in ``all_data.json``, and ``fps`` of ``world.json`` when it has one, are
  divided by ``s``), while the images and point clouds still show the states at the true times.

Ground truth of a variant (``ground_truth.json``): material, parameters, v0, gravity and effects
are the source's (the physics did not change); the point clouds are the source's clouds of the
kept frames (frame j of the variant is frame ``k * j`` of the source). ``frames`` records the
kept frames: ``n_frames``, ``n_train_frames`` (the kept frames that were training frames of the
source, but at most all but the last when the source had future frames), ``train``, ``future``, ``fps`` = the **true** rate of the kept frames (source fps / k),
``fps_claimed`` = what the folder claims (``fps * s / k``) and ``source_frames``. ``simulation``
(the truth simulation's settings) is not changed. Evaluation matches predicted and true clouds
frame by frame index, so CD/EMD stay well defined under a mismatch; with ``fps_scale != 1`` the
fit's frame time is wrong by the factor ``s``, so its parameter and v0 errors measure the bias that
mismatch causes (no fitted v0 and gravity can reproduce the true motion exactly).

Every variant folder holds ``variant.json`` (written last: its presence marks a complete
variant): the source folder, the :class:`VariantSpec`, and what was done (flipped pixel counts,
the rotation angle and centre shift of every camera, the kept frames). Files are written
atomically (:mod:`toolkit.atomic`); unchanged images are copied byte for byte.

Example::

    from toolkit.synthetic.variants import VariantSpec, make_variant
    make_variant("scenes/torus", "scenes/torus_noisy", VariantSpec(mask_noise=0.2, gamma=1.2, calibration_deg=0.5))
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Optional

import numpy as np

from toolkit.atomic import write_json, write_with
from toolkit.synthetic.errors import SyntheticError

__all__ = ["RENDER_STYLES", "VARIANT_FILE", "VARIANT_VERSION", "VariantError", "VariantSpec", "make_variant", "variant_is_complete",
           "boundary_pixels", "perturb_pose", "rotation_angle_deg"]

VARIANT_FILE = "variant.json"
#: values of :attr:`VariantSpec.render_style`
RENDER_STYLES = ("source", "points")
#: bumped when :func:`make_variant` writes something else for the same source and spec
VARIANT_VERSION = 1


class VariantError(SyntheticError):
    """A variant that cannot be made: a field out of its range, or a source folder it cannot use."""


@dataclass(frozen=True)
class VariantSpec:
    """How a variant differs from its source (module docstring for the exact definitions).

    Attributes:
        mask_noise: fraction of mask boundary pixels flipped per image, in [0, 1].
        calibration_deg: rotation of each recorded camera about its centre, degrees, in [0, 180].
        calibration_m: displacement of each recorded camera centre, metres, >= 0.
        brightness: gain on every colour channel, > 0.
        gamma: power applied to colour values in [0, 1], > 0.
        tint: (3,) per-channel gains (R, G, B), each > 0.
        blur_px: standard deviation of a Gaussian blur of the colours, pixels, in [0, 20].
        noise_std: standard deviation of additive Gaussian colour noise, [0, 1] units, in [0, 1].
        frame_stride: keep every k-th frame (integer >= 1).
        fps_scale: the folder claims ``fps_scale`` times the true frame rate, > 0.
        seed: seed of every random choice (integer >= 0).
        render_style: ``"source"`` (the images as rendered) or ``"points"`` (re-rendered as
            particle discs, see the module docstring).
    """

    mask_noise: float = 0.0
    calibration_deg: float = 0.0
    calibration_m: float = 0.0
    brightness: float = 1.0
    gamma: float = 1.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    blur_px: float = 0.0
    noise_std: float = 0.0
    frame_stride: int = 1
    fps_scale: float = 1.0
    seed: int = 0
    render_style: str = "source"

    def __post_init__(self) -> None:
        object.__setattr__(self, "tint", tuple(self.tint) if isinstance(self.tint, (list, tuple)) else self.tint)
        self.validate()

    def validate(self) -> None:
        """Raise :class:`VariantError` naming the first field outside its range."""
        ranges = {"mask_noise": (0.0, 1.0, True), "calibration_deg": (0.0, 180.0, True), "calibration_m": (0.0, math.inf, True),
                  "brightness": (0.0, math.inf, False), "gamma": (0.0, math.inf, False), "blur_px": (0.0, 20.0, True),
                  "noise_std": (0.0, 1.0, True), "fps_scale": (0.0, math.inf, False)}
        for name, (lo, hi, closed) in ranges.items():
            v = getattr(self, name)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (v >= lo if closed else v > lo) and v <= hi
            if not ok:
                span = ("[" if closed else "(") + f"{lo:g}, " + ("inf)" if hi == math.inf else f"{hi:g}]")
                raise VariantError(f"variant field {name!r} must be a finite number in {span}, got {v!r}")
        if len(self.tint) != 3 or not all(isinstance(t, (int, float)) and math.isfinite(t) and t > 0 for t in self.tint):
            raise VariantError(f"variant field 'tint' must be 3 finite numbers > 0 (R, G, B gains), got {self.tint!r}")
        for name, lo in (("frame_stride", 1), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise VariantError(f"variant field {name!r} must be an integer >= {lo}, got {v!r}")
        if self.render_style not in RENDER_STYLES:
            raise VariantError(f"variant field 'render_style' must be one of {list(RENDER_STYLES)}, got {self.render_style!r}")

    @property
    def photometric(self) -> bool:
        """Whether the colours of the images change."""
        return (self.brightness, self.gamma, tuple(self.tint), self.blur_px, self.noise_std) != (1.0, 1.0, (1.0, 1.0, 1.0), 0.0, 0.0)

    def to_dict(self) -> dict:
        """JSON-ready fields; ``render_style`` only when not ``"source"``, so the records (and the
        benchmark's fingerprints) of variants made before that field existed stay valid."""
        d = asdict(self)
        d["tint"] = list(self.tint)
        if d["render_style"] == "source":
            del d["render_style"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "VariantSpec":
        """From a dict of its fields (JSON); unknown keys are an error that lists the known ones."""
        if not isinstance(d, dict):
            raise VariantError(f"a variant must be a JSON object of VariantSpec fields, got {d!r}")
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise VariantError(f"unknown variant field(s) {unknown}; known: {known}")
        return cls(**d)


# ------------------------------------------------------------------------------------ pieces
def boundary_pixels(binary: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of a binary mask with a 4-neighbour of the other value (both sides)."""
    b = np.asarray(binary, dtype=bool)
    out = np.zeros_like(b)
    diff_v = b[1:] != b[:-1]
    diff_h = b[:, 1:] != b[:, :-1]
    out[1:] |= diff_v
    out[:-1] |= diff_v
    out[:, 1:] |= diff_h
    out[:, :-1] |= diff_h
    return out


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (degrees, in [0, 180]) of a 3x3 rotation matrix (``atan2`` form: accurate near 0)."""
    R = np.asarray(R, dtype=np.float64)
    skew = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return math.degrees(math.atan2(0.5 * float(np.linalg.norm(skew)), 0.5 * (float(np.trace(R)) - 1.0)))


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * K @ K


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def perturb_pose(c2w: np.ndarray, angle_deg: float, distance_m: float, rng: np.random.Generator) -> np.ndarray:
    """A camera-to-world matrix (3x4 or 4x4, any axis convention) rotated about its camera centre
    by ``angle_deg`` about a random axis and moved ``distance_m`` in a random direction."""
    out = np.array(c2w, dtype=np.float64)
    R = _rotation(_unit(rng), math.radians(angle_deg))
    u = _unit(rng)
    out[:3, :3] = R @ out[:3, :3]
    out[:3, 3] = out[:3, 3] + distance_m * u
    return out


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur of (H, W, C) float pixels (reflecting edges)."""
    r = max(1, int(math.ceil(3 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    k /= k.sum()
    for axis in (0, 1):
        pad = [(0, 0)] * img.ndim
        pad[axis] = (r, r)
        p = np.pad(img, pad, mode="reflect" if img.shape[axis] > r else "edge")
        img = sum(k[i] * np.take(p, np.arange(i, i + img.shape[axis]), axis=axis) for i in range(2 * r + 1))
    return img


def _photometric(rgb8: np.ndarray, v: VariantSpec, rng: np.random.Generator) -> np.ndarray:
    x = rgb8.astype(np.float64) / 255.0
    x = v.brightness * np.asarray(v.tint, dtype=np.float64) * np.power(x, v.gamma)
    if v.blur_px > 0:
        x = _blur(x, v.blur_px)
    if v.noise_std > 0:
        x = x + rng.normal(0.0, v.noise_std, size=x.shape)
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def _rng(v: VariantSpec, *key: int) -> np.random.Generator:
    return np.random.default_rng([v.seed, *[k + 10_000 for k in key]])  # keys >= -10000 (plates are frames -1, -2)


# ------------------------------------------------------------------------------------ the folder
def _read_source(src: Path) -> tuple[list[dict], dict[int, dict[int, dict]], Optional[dict]]:
    from toolkit.data import read_pac_nerf
    from toolkit.data.errors import DatasetError

    if not (src / "all_data.json").is_file():
        raise VariantError(f"{src}: not a PAC-NeRF-layout scene (no all_data.json); variants are made of such folders "
                           "(what `projo4d generate scene` writes)")
    try:
        read_pac_nerf(src)  # the source must load as it is
    except DatasetError as err:
        raise VariantError(f"{src} does not load as a scene: {err}") from None
    entries = json.loads((src / "all_data.json").read_text())
    by_cam: dict[int, dict[int, dict]] = {}
    for e in entries:
        cam, frame = (int(x) for x in Path(e["file_path"]).stem.split("_")[1:3])
        by_cam.setdefault(cam, {})[frame] = e
    gt = json.loads((src / "ground_truth.json").read_text()) if (src / "ground_truth.json").is_file() else None
    return entries, by_cam, gt


def _prepare_out(src: Path, out: Path) -> None:
    if out.resolve() == src.resolve() or src.resolve() in out.resolve().parents:
        raise VariantError(f"out_dir {out} must not be the source scene {src} or inside it")
    if out.exists() and any(out.iterdir()) and not (out / VARIANT_FILE).is_file():
        raise VariantError(f"out_dir {out} exists, is not empty and holds no {VARIANT_FILE}: choose an empty or new folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / VARIANT_FILE).unlink(missing_ok=True)  # incomplete until rewritten last
    for name in ("ground_truth.json", "all_data.json", "world.json"):
        (out / name).unlink(missing_ok=True)
    for folder, pattern in (("data", "*_*_*.png"), ("gt_points", "frame_*.ply")):
        for p in sorted((out / folder).glob(pattern)):
            p.unlink()


def _copy(src: Path, dst: Path) -> None:
    write_with(dst, lambda tmp: shutil.copyfile(src, tmp))


def _write_png(path: Path, pixels: np.ndarray) -> None:
    from toolkit.synthetic.layout import write_png

    write_with(path, lambda tmp: write_png(tmp, pixels))


def make_variant(scene_dir: str | Path, out_dir: str | Path, variant: VariantSpec) -> Path:
    """Write a perturbed copy of a scene folder (definitions in the module docstring).

    Args:
        scene_dir: a PAC-NeRF-layout scene (``projo4d generate scene``; ground truth optional).
        out_dir: the variant's folder: new, empty, or an earlier variant (its layout files are
            replaced). Must not be ``scene_dir`` or inside it.
        variant: what to change.

    Returns:
        ``out_dir`` as a :class:`Path`; it loads with :func:`toolkit.data.load_scene`.

    Raises:
        VariantError: a field out of range, a ``frame_stride`` leaving fewer than 2 frames,
            ``mask_noise`` on a scene without masks, or an unusable source / out folder; all
            raised before anything is written.
    """
    from toolkit.data.images import alpha_of, mask_of, read_raw

    variant.validate()
    src, out = Path(scene_dir), Path(out_dir)
    entries, by_cam, gt = _read_source(src)
    cams = sorted(by_cam)
    n_frames = 1 + max(f for f in by_cam[cams[0]])
    k = variant.frame_stride
    kept = list(range(0, n_frames, k))
    if len(kept) < 2:
        raise VariantError(f"variant field 'frame_stride' must leave at least 2 of the {n_frames} frames, i.e. be in "
                           f"[1, {n_frames - 1}], got {k}")
    has_a = all((src / "data" / f"a_{c}_{f}.png").is_file() for c in cams for f in range(n_frames))
    points = _point_style(src, gt, n_frames, variant) if variant.render_style == "points" else None
    if variant.mask_noise > 0 and points is None and not has_a and alpha_of(
            read_raw(src / by_cam[cams[0]][0]["file_path"])) is None:
        raise VariantError(f"variant field 'mask_noise' needs masks, but {src} has neither a_ mask files nor image alpha")
    _prepare_out(src, out)

    record: dict[str, Any] = {"cameras": {}, "masks": {"boundary_pixels": 0, "flipped_pixels": 0}}
    if points is not None:
        record["render"] = {**points[1], "mask_intersection": 0, "mask_union": 0}
    times = {f: float(by_cam[cams[0]][f]["time"]) for f in range(n_frames)}
    dt_new = (times[kept[1]] - times[kept[0]]) / variant.fps_scale
    new_entries = []
    for c in cams:
        rng = _rng(variant, c, -1000)
        c2w0 = np.asarray(by_cam[c][0]["c2w"], dtype=np.float64)
        c2w = perturb_pose(c2w0, variant.calibration_deg, variant.calibration_m, rng) if (
            variant.calibration_deg or variant.calibration_m) else c2w0
        record["cameras"][str(c)] = {
            "rotation_deg": rotation_angle_deg(c2w[:3, :3] @ np.linalg.inv(c2w0[:3, :3])),
            "centre_shift_m": float(np.linalg.norm(c2w[:3, 3] - c2w0[:3, 3]))}
        plates = [f for f in (-1, -2) if f in by_cam[c]]
        for new_f, old_f in [(f, f) for f in plates] + list(enumerate(kept)):
            e = by_cam[c][old_f]
            name = f"r_{c}_{new_f}.png"
            src_img = src / e["file_path"]
            drawn = None
            if old_f >= 0 and points is not None:
                drawn = _draw_points(points[0], src, by_cam[c], old_f, record["render"], read_raw, mask_of, has_a)
            if drawn is None and (old_f == -2 or not variant.photometric):
                _copy(src_img, out / "data" / name)
            else:
                px = read_raw(src_img) if drawn is None else drawn
                px = np.repeat(px[..., None], 3, -1) if px.ndim == 2 else px
                px = px.copy()
                if variant.photometric:
                    px[..., :3] = _photometric(px[..., :3], variant, _rng(variant, c, old_f))
                _write_png(out / "data" / name, px)
            if old_f >= 0 and (variant.mask_noise > 0 or has_a):
                _write_mask(src, out, c, old_f, new_f, has_a, variant, record["masks"], read_raw, mask_of, drawn)
            time = -dt_new if new_f == -1 else (times[old_f] / variant.fps_scale if new_f >= 0 else e["time"])
            new_entries.append({**e, "file_path": f"./data/{name}", "time": time, "c2w": c2w.tolist()})
    write_json(out / "all_data.json", new_entries)
    if (src / "world.json").is_file():
        world = json.loads((src / "world.json").read_text())
        if isinstance(world, dict) and world.get("fps"):
            world["fps"] = float(world["fps"]) * variant.fps_scale / k
        write_json(out / "world.json", world)
    if gt is not None:
        _write_ground_truth(src, out, gt, kept, n_frames, variant)
    true_fps = 1.0 / (times[kept[1]] - times[kept[0]])
    record["frames"] = {"source_frames": kept, "fps_true": true_fps, "fps_claimed": true_fps * variant.fps_scale}
    mk = record["masks"]
    mk["flipped_fraction"] = mk["flipped_pixels"] / mk["boundary_pixels"] if mk["boundary_pixels"] else 0.0
    if points is not None:
        rr = record["render"]
        rr["mask_iou"] = rr["mask_intersection"] / rr["mask_union"] if rr["mask_union"] else 1.0
    write_json(out / VARIANT_FILE, {"format": "projo4d-scene-variant", "version": VARIANT_VERSION,
                                    "source": str(src.resolve()), "variant": variant.to_dict(), "applied": record})
    return out


def _write_mask(src: Path, out: Path, c: int, old_f: int, new_f: int, has_a: bool, v: VariantSpec, tally: dict,
                read_raw, mask_of, drawn: Optional[np.ndarray] = None) -> None:
    """``a_{c}_{new_f}.png`` (RGBA: the source image's colours, alpha = the possibly noisy mask);
    with ``drawn`` (a re-rendered RGBA frame) its colours and alpha instead."""
    if drawn is not None:
        rgb, m = drawn[..., :3], drawn[..., 3].astype(np.float32) / 255.0
    else:
        mask_file = src / "data" / f"a_{c}_{old_f}.png"
        img = read_raw(src / "data" / f"r_{c}_{old_f}.png")
        rgb = img[..., :3] if img.ndim == 3 else np.repeat(img[..., None], 3, -1)
        m = mask_of(read_raw(mask_file)) if has_a else img[..., 3].astype(np.float32) / 255.0
    alpha = np.round(m * 255.0).astype(np.uint8)
    if v.mask_noise > 0:
        inside = m >= 0.5
        idx = np.flatnonzero(boundary_pixels(inside))
        n_flip = int(round(v.mask_noise * len(idx)))
        flip = _rng(v, c, old_f, 7).choice(idx, size=n_flip, replace=False) if n_flip else np.zeros(0, dtype=np.int64)
        flat = alpha.reshape(-1)
        flat[flip] = np.where(inside.reshape(-1)[flip], 0, 255)
        tally["boundary_pixels"] += len(idx)
        tally["flipped_pixels"] += n_flip
    _write_png(out / "data" / f"a_{c}_{new_f}.png", np.concatenate([rgb, alpha[..., None]], axis=-1))


def _point_style(src: Path, gt: Optional[dict], n_frames: int, v: VariantSpec) -> tuple[Any, dict]:
    """The :class:`~toolkit.synthetic.point_render.PointStyle` of ``render_style="points"`` and its record."""
    from toolkit.data.ply import read_ply_points
    from toolkit.synthetic.point_render import PointStyle

    clouds = (gt or {}).get("point_clouds") or []
    if len(clouds) != n_frames:
        raise VariantError(f"variant field 'render_style' = 'points' needs the truth point cloud of each of the {n_frames} "
                           f"frames (ground_truth.json 'point_clouds'), but {src} lists {len(clouds)}")
    try:
        pts = [read_ply_points(Path(p) if Path(p).is_absolute() else src / p) for p in clouds]
    except Exception as err:  # noqa: BLE001 - any unreadable cloud is the same user error
        raise VariantError(f"variant field 'render_style' = 'points': cannot read the truth point clouds of {src}: "
                           f"{err}") from None
    try:
        style = PointStyle.from_render_record(pts, (gt or {}).get("render") or {}, v.seed)
    except ValueError as err:
        raise VariantError(f"variant field 'render_style' = 'points' cannot draw the particles of {src}: {err}") from None
    return style, style.record()


def _draw_points(style, src: Path, entries: dict[int, dict], frame: int, tally: dict, read_raw, mask_of,
                 has_a: bool) -> np.ndarray:
    """(H, W, 4) uint8: source frame ``frame`` of one camera (``entries``: frame -> all_data entry)
    re-rendered as particle discs over its plate; adds to the mask IoU tally."""
    from toolkit.synthetic.point_render import camera_matrices

    e = entries[frame]
    src_img = read_raw(src / e["file_path"])
    H, W = src_img.shape[:2]
    plate = read_raw(src / entries[-1]["file_path"]) if -1 in entries else None
    if plate is not None:
        plate = np.repeat(plate[..., None], 3, -1) if plate.ndim == 2 else plate[..., :3]
    K, w2c = camera_matrices(e["c2w"], e["intrinsic"], W, H)
    drawn = style.render(frame, K, w2c, W, H, plate)
    cam, _ = (int(x) for x in Path(e["file_path"]).stem.split("_")[1:3])
    a_file = src / "data" / f"a_{cam}_{frame}.png"
    alpha = src_img[..., -1] / 255.0 if src_img.ndim == 3 and src_img.shape[-1] in (2, 4) else None
    old = mask_of(read_raw(a_file)) if has_a else alpha
    if old is not None:
        new_m, old_m = drawn[..., 3] >= 128, old >= 0.5
        tally["mask_intersection"] += int((new_m & old_m).sum())
        tally["mask_union"] += int((new_m | old_m).sum())
    return drawn


def _write_ground_truth(src: Path, out: Path, gt: dict, kept: list[int], n_frames: int, v: VariantSpec) -> None:
    gt = dict(gt)
    clouds = gt.get("point_clouds") or []
    if clouds:
        if len(clouds) != n_frames:
            raise VariantError(f"{src}/ground_truth.json lists {len(clouds)} point clouds for {n_frames} frames")
        new = []
        for j, f in enumerate(kept):
            name = f"gt_points/frame_{j:03d}{Path(clouds[f]).suffix}"
            _copy((src / clouds[f]) if not Path(clouds[f]).is_absolute() else Path(clouds[f]), out / name)
            new.append(name)
        gt["point_clouds"] = new
    frames = dict(gt.get("frames") or {})
    n_train_src = int(frames.get("n_train_frames") or n_frames)
    n_train = sum(1 for f in kept if f < n_train_src)
    if n_train_src < n_frames:  # the source has future frames: so has the variant
        n_train = max(1, min(n_train, len(kept) - 1))
    fps = float(frames.get("fps") or 0.0) / v.frame_stride if frames.get("fps") else None
    frames.update({"n_frames": len(kept), "n_train_frames": n_train, "train": list(range(n_train)),
                   "future": list(range(n_train, len(kept))), "fps": fps,
                   "fps_claimed": None if fps is None else fps * v.fps_scale, "source_frames": kept})
    gt["frames"] = frames
    gt["variant"] = {"source": str(src.resolve()), "spec": v.to_dict()}
    write_json(out / "ground_truth.json", gt)


def variant_is_complete(out_dir: str | Path, variant: Optional[VariantSpec] = None, source: Optional[str | Path] = None) -> bool:
    """True if ``out_dir`` holds a complete variant (of ``source``, made with ``variant``, when given)."""
    root = Path(out_dir)
    try:
        rec = json.loads((root / VARIANT_FILE).read_text())
        entries = json.loads((root / "all_data.json").read_text())
    except (OSError, ValueError):
        return False
    if rec.get("version") != VARIANT_VERSION:
        return False
    if variant is not None and rec.get("variant") != variant.to_dict():
        return False
    if source is not None and rec.get("source") != str(Path(source).resolve()):
        return False
    return all((root / e["file_path"]).is_file() for e in entries)

"""Do the fitting cameras' silhouettes agree? A camera-pose check that needs no model.

With correct camera poses, every ray through a pixel of one camera's object mask passes through
the object, and every other camera sees that object inside its own mask. So the visual hull of
two cameras' masks, projected back into either camera, covers that camera's mask (silhouette
coherence, as used for calibration by Hernández, Schmitt and Cipolla, PAMI 2007). When a camera's
claimed pose is off, rays through its mask miss the other camera's cone: part of both masks is
left uncovered. Pairs localize the error. With three or more cameras, the pairs that contain the
wrong camera lose coverage and the others do not. No physics changes this: it is a statement about
one instant seen from several places, so a missing force cannot cause it. Mask errors and
unsynchronized cameras can, and the message says so.

The check runs on the masks of the training frames, before any model is trained. It compares
pixel footprints, so a shift of about a pixel at the object's distance is below what it can see
(at 96 px and 1.1 m, about 1 cm).

:func:`silhouette_agreement` returns a :class:`SilhouetteAgreement`; ``suspect`` names the
camera whose pairs disagree (or None), and :meth:`SilhouetteAgreement.message` explains it.
:func:`check_scene` runs it on a scene's files; ``projo4d run`` does so before stage 0 and writes
``RUN/silhouettes.json``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import torch

__all__ = ["DISAGREE", "DOMINANT", "SilhouetteAgreement", "check_scene", "silhouette_agreement", "pair_uncovered",
           "inside_masks"]

#: uncovered share of the masks (mean over a camera's pairs and the frames) above which a camera
#: disagrees. Chosen, not calibrated: on generated 96 px scenes, correct cameras leave 0.0 %, a
#: fitting camera moved by 2.5 cm leaves 2.1-2.2 % in its pairs, one moved by 1 cm 0.08-0.12 %
#: (below this: 1.5 px at that distance).
DISAGREE = 0.01
#: a suspect's pairs must leave this many times the uncovered share of the pairs without it
DOMINANT = 3.0


@dataclass
class SilhouetteAgreement:
    """The pairwise silhouette agreement of the fitting cameras.

    Attributes:
        cameras: the cameras checked (indices into the scene's cameras).
        frames: the frames whose masks were used.
        pairs: ``{(a, b): uncovered}``: the share of the two masks (mean over both cameras and the
            frames) that the pair's visual hull leaves uncovered (0: they agree).
        per_camera: ``{c: (with, without)}``: the mean of the pairs that contain ``c`` and of those
            that do not (``without`` is None with two cameras).
        voxel: the hull's voxel edge (m).
        suspect: the one camera whose pairs disagree (``with > DISAGREE`` and ``with >= DOMINANT
            * without``), else None. Two cameras that disagree cannot say which one is wrong.
        disagree: whether any pair leaves more than :data:`DISAGREE` uncovered.
    """

    cameras: list[int]
    frames: list[int]
    pairs: dict[tuple[int, int], float]
    per_camera: dict[int, tuple[float, Optional[float]]]
    voxel: float
    suspect: Optional[int] = None
    disagree: bool = False
    seconds: float = field(default=0.0, compare=False)

    def message(self) -> str:
        """One paragraph for a person: what agrees, what does not, and what to check."""
        worst = max(self.pairs.items(), key=lambda kv: kv[1]) if self.pairs else None
        if not self.disagree:
            return (f"the silhouettes of cameras {self.cameras} agree (at most {100 * (worst[1] if worst else 0):.2f} % "
                    f"of a mask uncovered by a pair's visual hull, frames {self.frames[0]}-{self.frames[-1]})")
        if self.suspect is not None:
            w, wo = self.per_camera[self.suspect]
            return (f"camera {self.suspect}'s silhouettes disagree with the other fitting cameras': the visual hulls of its "
                    f"pairs leave {100 * w:.2f} % of the masks uncovered, the pairs without it {100 * (wo or 0):.2f} % "
                    f"(limit {100 * DISAGREE:.0f} %). Its pose (calibration) is the likely error; a mask that misses "
                    "part of the object, or a camera that is not synchronized with the others, does the same")
        return (f"the silhouettes of cameras {self.cameras} disagree (pair {worst[0]} leaves {100 * worst[1]:.2f} % of "
                f"its masks uncovered; limit {100 * DISAGREE:.0f} %) and no single camera explains it: check the "
                "calibration, the masks and the synchronization of the cameras")

    def to_dict(self) -> dict:
        return {"cameras": list(self.cameras), "frames": list(self.frames), "voxel_m": self.voxel,
                "pairs": {f"{a}-{b}": round(v, 6) for (a, b), v in self.pairs.items()},
                "per_camera": {str(c): [round(w, 6), None if wo is None else round(wo, 6)] for c, (w, wo) in self.per_camera.items()},
                "suspect": self.suspect, "disagree": self.disagree, "limit": DISAGREE, "seconds": round(self.seconds, 2)}


def _grid(lo: np.ndarray, hi: np.ndarray, voxel: float) -> torch.Tensor:
    axes = [torch.arange(float(lo[i]) + voxel / 2, float(hi[i]), voxel) for i in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _pixels(cameras, cam: int, points: torch.Tensor, shape: tuple[int, int]):
    """Integer pixels of ``points`` in camera ``cam`` and which of them fall on the image, in front."""
    uv, depth = cameras[[cam]].project(points)
    u, v = uv[0, :, 0].floor().long(), uv[0, :, 1].floor().long()
    ok = (depth[0] > 0) & (u >= 0) & (v >= 0) & (u < shape[1]) & (v < shape[0])
    return u, v, ok


def inside_masks(cameras, cams: Sequence[int], masks: dict[int, torch.Tensor], points: torch.Tensor):
    """The visual hull's membership test: ``(inside, pixels)``, where ``inside`` (N,) bool says which
    of ``points`` (N, 3; m, world) project in front of every camera of ``cams``, onto its image and
    into its (H, W) bool mask, and ``pixels[c] = (u, v, on_image)`` are camera ``c``'s integer pixels."""
    inside = torch.ones(points.shape[0], dtype=torch.bool)
    pix = {}
    for c in cams:
        u, v, ok = _pixels(cameras, c, points, tuple(masks[c].shape))
        hit = torch.zeros_like(inside)
        hit[ok] = masks[c][v[ok], u[ok]]
        inside &= hit
        pix[c] = (u, v, ok)
    return inside, pix


def pair_uncovered(cameras, masks: dict[int, torch.Tensor], pair: tuple[int, int], lo: np.ndarray, hi: np.ndarray,
                   voxel: float, voxel_pixels: Optional[dict[int, float]] = None) -> tuple[float, float]:
    """The share of each of the two masks that the pair's visual hull does not cover.

    Args:
        cameras: :class:`~toolkit.cameras.Cameras` holding both cameras (world frame, metres).
        masks: camera index -> (H, W) bool mask of one frame.
        pair: the two camera indices.
        lo, hi: (3,) corners of the box the hull is carved in (m); it must hold the object.
        voxel: the voxel edge (m); about half a pixel's footprint at the object resolves the masks.
        voxel_pixels: per camera, the voxel's size in pixels at the object; where it exceeds one
            pixel the covered pixels are widened by it (voxel centres alone would leave gaps).

    Returns:
        ``(uncovered_a, uncovered_b)`` in [0, 1] (0 for an empty mask).
    """
    points = _grid(lo, hi, voxel)
    inside, pix = inside_masks(cameras, pair, masks, points)
    out = []
    for c in pair:
        u, v, ok = pix[c]
        covered = torch.zeros_like(masks[c])
        sel = inside & ok
        covered[v[sel], u[sel]] = True
        k = int((voxel_pixels or {}).get(c, 1.0) // 2) * 2 + 1
        if k > 1:
            covered = torch.nn.functional.max_pool2d(covered.float()[None, None], k, 1, k // 2)[0, 0] > 0
        n = int(masks[c].sum())
        out.append(0.0 if n == 0 else 1.0 - float((covered & masks[c]).sum()) / n)
    return out[0], out[1]


def _all_pairs_uncovered(cameras, masks: dict[int, torch.Tensor], pairs: list[tuple[int, int]], lo: np.ndarray,
                         hi: np.ndarray, voxel: float, foot: dict[int, float]) -> dict[tuple[int, int], tuple[float, float]]:
    """:func:`pair_uncovered` of every pair on one grid, each camera projected once (the same
    numbers; the tests compare the two)."""
    points = _grid(lo, hi, voxel)
    hits, pix = {}, {}
    for c in {c for pair in pairs for c in pair}:
        u, v, ok = _pixels(cameras, c, points, tuple(masks[c].shape))
        hit = torch.zeros(points.shape[0], dtype=torch.bool)
        hit[ok] = masks[c][v[ok], u[ok]]
        hits[c], pix[c] = hit, (u, v)
    out = {}
    for pair in pairs:
        inside = hits[pair[0]] & hits[pair[1]]  # a voxel inside both masks lies on the image of both
        shares = []
        for c in pair:
            u, v = pix[c]
            covered = torch.zeros_like(masks[c])
            covered[v[inside], u[inside]] = True
            k = int((voxel / foot[c]) // 2) * 2 + 1
            if k > 1:
                covered = torch.nn.functional.max_pool2d(covered.float()[None, None], k, 1, k // 2)[0, 0] > 0
            n = int(masks[c].sum())
            shares.append(0.0 if n == 0 else 1.0 - float((covered & masks[c]).sum()) / n)
        out[pair] = (shares[0], shares[1])
    return out


def _bounds(cameras, cams: Sequence[int], masks: dict[int, torch.Tensor]) -> tuple[np.ndarray, np.ndarray, dict[int, float]]:
    """A box holding the object: around the point nearest the rays through the masks' centroids,
    as wide as the largest mask seen at that distance (twice over); and each camera's pixel
    footprint there (m)."""
    centres, dirs, spans = [], [], []
    for c in cams:
        ys, xs = torch.nonzero(masks[c], as_tuple=True)
        if len(xs) == 0:
            raise ValueError(f"camera {c}'s mask is empty in the first frame checked")
        pix = torch.stack([xs.float().mean() + 0.5, ys.float().mean() + 0.5])
        ray = cameras[[c]].unproject(pix[None, None].to(cameras.K.dtype), torch.ones(1, 1, dtype=cameras.K.dtype))[0, 0].double()
        o = cameras.centers[c].double()
        dirs.append((ray - o) / (ray - o).norm())
        centres.append(o)
        spans.append(float(max(xs.max() - xs.min(), ys.max() - ys.min()) + 1))
    A = sum(torch.eye(3, dtype=torch.float64) - d[:, None] * d[None] for d in dirs)
    b = sum((torch.eye(3, dtype=torch.float64) - d[:, None] * d[None]) @ o for d, o in zip(dirs, centres))
    p = torch.linalg.lstsq(A, b).solution
    foot = {}
    for i, (c, o) in enumerate(zip(cams, centres)):
        foot[c] = float((p - o).norm()) / float(cameras.K[c, 0, 0])
        spans[i] *= foot[c]
    half = max(spans)
    p = p.numpy()
    return p - half, p + half, foot


def silhouette_agreement(cameras, masks: dict[int, Sequence[torch.Tensor]] | torch.Tensor, cams: Sequence[int],
                         frames: Sequence[int], max_voxels: int = 2_000_000) -> SilhouetteAgreement:
    """The pairwise silhouette agreement of ``cams`` over ``frames``.

    Args:
        cameras: :class:`~toolkit.cameras.Cameras` of the scene (the poses to check).
        masks: per camera index, a sequence of (H, W) masks indexed by frame; or a (C, T, H, W)
            tensor (e.g. :attr:`toolkit.physics.PhysicsInput.masks`). Nonzero (or ``> 0.5`` for
            floats in [0, 1], ``> 127`` for uint8) is object.
        cams: the cameras to check (at least 2).
        frames: the frames to use (their masks must show the object in every camera).
        max_voxels: the most voxels of a hull; the voxel grows beyond half a pixel's footprint
            when the box needs more.

    Returns:
        :class:`SilhouetteAgreement`.
    """
    import time

    t0 = time.perf_counter()
    cams = [int(c) for c in cams]
    if len(cams) < 2:
        raise ValueError(f"the silhouette check needs at least 2 cameras, got {cams}")

    def mask(c: int, f: int) -> torch.Tensor:
        m = torch.as_tensor(masks[c][f])
        if m.dtype == torch.uint8:
            return m > 127
        return m > 0.5 if m.is_floating_point() else m.bool()

    frames = [int(f) for f in frames]
    totals = {pair: [] for pair in itertools.combinations(cams, 2)}
    voxel, used = None, []
    for f in frames:
        m = {c: mask(c, f) for c in cams}
        if any(int(m[c].sum()) == 0 for c in cams):
            continue  # the object is not seen by every camera in this frame: nothing to compare
        used.append(f)
        lo, hi, foot = _bounds(cameras, cams, m)
        voxel = max(min(foot.values()) / 2, float(np.prod(hi - lo) / max_voxels) ** (1 / 3))
        for pair, (a, b) in _all_pairs_uncovered(cameras, m, list(totals), lo, hi, voxel, foot).items():
            totals[pair].append((a + b) / 2)
    if voxel is None:
        raise ValueError(f"no frame of {frames} shows the object in every camera of {cams}")
    pairs = {p: float(np.mean(v)) for p, v in totals.items()}
    per = {}
    for c in cams:
        w = [v for p, v in pairs.items() if c in p]
        wo = [v for p, v in pairs.items() if c not in p]
        per[c] = (float(np.mean(w)), float(np.mean(wo)) if wo else None)
    disagree = max(pairs.values()) > DISAGREE
    suspects = [c for c, (w, wo) in per.items() if wo is not None and w > DISAGREE and w >= DOMINANT * wo]
    return SilhouetteAgreement(cameras=cams, frames=used, pairs=pairs, per_camera=per, voxel=float(voxel),
                               suspect=suspects[0] if len(suspects) == 1 else None, disagree=disagree,
                               seconds=time.perf_counter() - t0)


def check_scene(scene, cams: Sequence[int] | str, frames: Sequence[int], out=None, max_frames: int = 16,
                **options) -> Optional[SilhouetteAgreement]:
    """:func:`silhouette_agreement` on a scene's own masks (``scene.load_mask > 0.5``) of the
    cameras ``cams`` (indices, ``"sparse"`` or ``"all"``, as
    :func:`toolkit.data.datamodule.resolve_cameras`), before any model is trained: writes ``out``
    (JSON, when given) and logs a warning with
    :meth:`SilhouetteAgreement.message` when the cameras disagree. ``None`` (and a log line) when
    the check cannot run: a scene without masks, or no frame where every camera sees the object.
    At most ``max_frames`` of ``frames``, evenly spaced, are read (a long high-resolution capture's
    masks would otherwise all sit in memory at once)."""
    import logging

    log = logging.getLogger(__name__)
    frames = [int(f) for f in frames]
    if len(frames) > max_frames:
        frames = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, max_frames).round()]
    try:
        from toolkit.data.datamodule import resolve_cameras

        cams = resolve_cameras(scene, cams)
        masks = {int(c): [torch.as_tensor(scene.load_mask(int(c), int(f)) > 0.5) for f in frames] for c in cams}
        check = silhouette_agreement(scene.cameras, masks, cams, range(len(list(frames))), **options)
    except Exception as exc:  # advice, never a reason to stop a run
        log.info("silhouette check skipped: %s", exc)
        return None
    check.frames = [frames[i] for i in check.frames]
    if out is not None:
        from toolkit.atomic import write_json

        write_json(out, {**check.to_dict(), "message": check.message()})
    if check.disagree:
        log.warning("%s (%s)", check.message(), out if out is not None else "silhouette check")
    else:
        log.info(check.message())
    return check

"""Localize where a fitted base model and the measurements disagree.

3D, against the stage-0 reconstruction (``PhysicsInput.surfaces``, the pseudo-ground-truth of
the geometric loss), per frame:

* **regions** of the observed surface: the *contact* band (in frames where the body touches
  the ground, its points within ``band = max(2 spacing, 0.2 x body height)`` of its lowest
  point), the *top* (the upper 30 % of the body's height at that frame) and the *bulk* (the
  rest); the residual of a region is the RMS distance of its observed points to the nearest
  simulated surface particle (metres);
* **phases**: *flight* before the first frame whose observed surface comes within
  ``1.25 dx`` of the ground (particles closer than ``1.5 dx`` reach the boundary nodes),
  *impact* that frame and the next, *after-contact* the rest;
* **rigid and non-rigid parts**: the centre-of-mass offset (its frame-0 value, a sampling bias,
  removed), the rotation of a rigid alignment (3 ICP iterations, Kabsch) and the RMS residual
  left after that alignment;
* the **noise band**: twice the frame-0 residual (at frame 0 the simulation starts from the
  reconstruction, so what is left there is representation noise), and the first frame whose
  residual leaves it.

2D, per camera and frame (fitted and held-out cameras): the fit's image loss
``(1 - w) L1 + w (1 - SSIM)`` and the mask residual ``1 - IoU`` of the rendered alpha and the
observed mask. A residual that grows in one camera only points at that observation (pose,
timing of one camera), not at the physics: :attr:`Localization.single_camera` names it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import torch

from renderers.base import Gaussians
from toolkit.discovery.library import LibraryModel

__all__ = ["Localization", "localize", "REGIONS", "PHASES"]

REGIONS = ("contact", "bulk", "top")
PHASES = ("flight", "impact", "after-contact")


@dataclass
class Localization:
    """Where the base model and the measurements disagree (see the module docstring).

    Attributes:
        frames: the frames analysed (training frames by default).
        phases: phase of each frame (:data:`PHASES`).
        contact_frame: first frame in contact with the ground, or ``None``.
        heat: (F, 3) RMS residual (m) per frame and region (:data:`REGIONS`), ``nan`` where a
            region has no observed point.
        rigid_translation: (F,) centre-of-mass offset (m), frame-0 offset removed.
        rotation_deg: (F,) rotation of the rigid alignment, degrees.
        nonrigid: (F,) RMS residual after the rigid alignment (m).
        total: (F,) RMS symmetric nearest-neighbour residual (m).
        noise_band: residual level (m) below which a frame counts as explained.
        first_departure: first frame whose residual leaves the noise band, or ``None``.
        cameras: camera indices of the 2D residuals; ``train_cameras`` the fitted ones.
        image: (C, F) image loss per camera and frame.
        mask: (C, F) ``1 - IoU`` of rendered alpha and observed mask.
        single_camera: a camera whose residual grows alone (an observation problem), or ``None``.
        summary: one sentence.
    """

    frames: list[int]
    phases: list[str]
    contact_frame: Optional[int]
    heat: np.ndarray
    rigid_translation: np.ndarray
    rotation_deg: np.ndarray
    nonrigid: np.ndarray
    total: np.ndarray
    noise_band: float
    first_departure: Optional[int]
    cameras: list[int] = field(default_factory=list)
    train_cameras: list[int] = field(default_factory=list)
    image: Optional[np.ndarray] = None
    mask: Optional[np.ndarray] = None
    single_camera: Optional[int] = None
    summary: str = ""

    def region_phase_table(self) -> dict[str, dict[str, float]]:
        """Mean residual (m) per phase and region (``nan`` where empty)."""
        out: dict[str, dict[str, float]] = {}
        for ph in PHASES:
            rows = [i for i, p in enumerate(self.phases) if p == ph]
            out[ph] = {}
            for k, reg in enumerate(REGIONS):
                vals = self.heat[rows, k] if rows else np.array([])
                vals = vals[np.isfinite(vals)]
                out[ph][reg] = float(vals.mean()) if len(vals) else float("nan")
        return out

    def to_dict(self) -> dict:
        def arr(a):
            return None if a is None else np.where(np.isfinite(a), a, np.nan).tolist()

        return {"frames": self.frames, "phases": self.phases, "contact_frame": self.contact_frame, "regions": list(REGIONS),
                "heat": arr(self.heat), "rigid_translation": arr(self.rigid_translation), "rotation_deg": arr(self.rotation_deg),
                "nonrigid": arr(self.nonrigid), "total": arr(self.total), "noise_band": self.noise_band,
                "first_departure": self.first_departure, "cameras": self.cameras, "train_cameras": self.train_cameras,
                "image": arr(self.image), "mask": arr(self.mask), "single_camera": self.single_camera,
                "region_phase": self.region_phase_table(), "summary": self.summary}


def _nn(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices of the nearest point of ``b`` for each point of ``a``."""
    from scipy.spatial import cKDTree

    d, i = cKDTree(b).query(a, k=1)
    return np.asarray(d), np.asarray(i)


def _kabsch(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rotation R minimizing |R p_i - q_i| for centred point sets (N, 3)."""
    H = p.T @ q
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, d])
    return Vt.T @ D @ U.T


def _rigid_split(pred: np.ndarray, obs: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(translation, rotation in degrees, RMS after alignment) of the rigid part of obs vs pred."""
    cp, co = pred.mean(0), obs.mean(0)
    t = co - cp - bias
    p = pred - cp
    o = obs - co
    R = np.eye(3)
    for _ in range(3):
        _, idx = _nn(p @ R.T, o)
        R = _kabsch(p, o[idx])
    angle = math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    aligned = p @ R.T
    d1, _ = _nn(o, aligned)
    d2, _ = _nn(aligned, o)
    rms = math.sqrt(0.5 * (float(np.mean(d1**2)) + float(np.mean(d2**2))))
    return t, angle, rms


@torch.no_grad()
def localize(lib: LibraryModel, q: Optional[np.ndarray] = None, frames: Optional[Sequence[int]] = None,
             ground_height: Optional[float] = None) -> Localization:
    """Per-frame, per-region, rigid/non-rigid and per-camera residuals of the state ``q``.

    Args:
        lib: the library model of the fitted module.
        q: library parameters (default ``lib.q0``: the fitted base model).
        frames: frames to analyse (default: the training frames).
        ground_height: y of the ground (default: the module's ``SimConfig.ground_height``).

    Returns:
        The :class:`Localization`.
    """
    q = lib.q0 if q is None else q
    inp = lib.input
    frames = list(range(inp.n_train)) if frames is None else list(frames)
    cfg = lib.module.sim_config
    ground = cfg.ground_height if ground_height is None else ground_height
    x0, pos = lib.trajectory(q, frames)
    surf = pos[:, lib.module.surface_index].cpu().double().numpy()
    spacing = float(inp.particle_volume) ** (1 / 3)
    obs0 = inp.surfaces[frames[0]].double().numpy()
    height = float(np.ptp(obs0[:, 1])) if len(obs0) else 0.1
    band = max(2 * spacing, 0.2 * height)
    tol = 1.25 * cfg.dx
    F = len(frames)
    heat = np.full((F, len(REGIONS)), np.nan)
    total, nonrigid, rot = np.zeros(F), np.zeros(F), np.zeros(F)
    trans = np.zeros((F, 3))
    contact = None
    bias = None
    for k, f in enumerate(frames):
        obs = inp.surfaces[f].double().numpy()
        pred = surf[k]
        if len(obs) == 0:
            heat[k] = np.nan
            continue
        d_obs, _ = _nn(obs, pred)
        d_pred, _ = _nn(pred, obs)
        total[k] = math.sqrt(0.5 * (float(np.mean(d_obs**2)) + float(np.mean(d_pred**2))))
        y = obs[:, 1]
        touching = ground is not None and y.min() <= ground + tol
        top = y >= y.max() - 0.3 * max(np.ptp(y), 1e-6)
        low = (y <= y.min() + band) & ~top if touching else np.zeros_like(top)
        regions = [low, ~(low | top), top]
        for r, sel in enumerate(regions):
            if sel.any():
                heat[k, r] = math.sqrt(float(np.mean(d_obs[sel] ** 2)))
        if touching and contact is None:
            contact = k
        if bias is None:
            bias = obs.mean(0) - pred.mean(0)
        t, a, rms = _rigid_split(pred, obs, bias)
        trans[k], rot[k], nonrigid[k] = t, a, rms
    phases = []
    for k in range(F):
        if contact is None or k < contact:
            phases.append("flight")
        elif k <= contact + 1:
            phases.append("impact")
        else:
            phases.append("after-contact")
    noise = 2.0 * float(total[0]) if F else 0.0
    departure = next((frames[k] for k in range(1, F) if total[k] > noise), None)
    loc = Localization(frames=frames, phases=phases, contact_frame=None if contact is None else frames[contact], heat=heat,
                       rigid_translation=np.linalg.norm(trans, axis=1), rotation_deg=rot, nonrigid=nonrigid, total=total,
                       noise_band=noise, first_departure=departure)
    _camera_residuals(lib, q, frames, loc)
    loc.summary = _summary(loc)
    return loc


def _camera_residuals(lib: LibraryModel, q: np.ndarray, frames: list[int], loc: Localization) -> None:
    inp = lib.input
    cams = list(range(len(inp.cameras)))
    loc.cameras, loc.train_cameras = cams, list(inp.train_cameras)
    loc.image = lib.image_losses(q, frames, cams).numpy().T  # (C, F)
    x0, pos = lib.trajectory(q, frames)
    means, deform = lib.gaussian_means(q, x0, pos), lib.deformations(x0, pos)
    m = lib.module
    masks = m.masks[:, frames].float().cpu().numpy() / 255.0 > 0.5  # (C, F, H, W)
    iou = np.zeros((len(cams), len(frames)))
    for k, mf in enumerate(means):
        g = Gaussians(means=mf, log_scales=m.log_scales.detach(), quats=m.quats.detach(), opacity_logits=m.opacity_logits.detach(),
                      colors=None if m.colors is None else m.colors.detach(), sh=None if m.sh is None else m.sh.detach(),
                      deformation=None if deform is None else deform[k])
        alpha = m.renderer(g, inp.cameras.to(lib.device)).alpha.cpu().numpy() > 0.5  # (C, H, W)
        inter = (alpha & masks[:, k]).sum((1, 2))
        union = (alpha | masks[:, k]).sum((1, 2))
        iou[:, k] = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    loc.mask = 1.0 - iou
    # growth of each camera's residual over frame 0; one camera alone -> observation
    growth = loc.image[:, 1:].mean(1) - loc.image[:, 0] if loc.image.shape[1] > 1 else loc.image[:, 0]
    order = np.argsort(growth)[::-1]
    if len(cams) >= 3:
        top, rest = growth[order[0]], np.median(growth[order[1:]])
        # a camera whose residual is high from the start and grows alone also counts
        level = loc.image.mean(1)
        lev_top, lev_rest = level[order[0]], np.median(np.delete(level, order[0]))
        if (top > 3.0 * max(rest, 1e-4) and top > 0.01) or lev_top > 2.0 * max(lev_rest, 1e-6):
            loc.single_camera = int(cams[order[0]])


def _summary(loc: Localization) -> str:
    if loc.first_departure is None:
        return "the residual stays within the noise band on every analysed frame"
    table = loc.region_phase_table()
    best = None
    for ph, regs in table.items():
        for reg, v in regs.items():
            if np.isfinite(v) and (best is None or v > best[2]):
                best = (ph, reg, v)
    k = loc.frames.index(loc.first_departure)
    rigid = loc.rigid_translation[k:].mean()
    nonrigid = loc.nonrigid[k:].mean()
    kind = "mostly rigid (centre-of-mass motion)" if rigid > nonrigid else "mostly non-rigid (shape)"
    s = (f"the residual leaves the noise band ({loc.noise_band * 1e3:.1f} mm) at frame {loc.first_departure} "
         f"({loc.phases[k]}), is largest in the {best[1]} region during {best[0]} ({best[2] * 1e3:.1f} mm RMS) and is {kind}")
    if loc.single_camera is not None:
        s += f"; camera {loc.single_camera} alone carries a growing image residual (an observation problem?)"
    return s

"""Re-simulate a digital twin under new conditions and render it (``projo4d simulate TWIN``).

Python API for robotics users::

    from toolkit.twin import DigitalTwin, simulate_twin, render_trajectory, orbit_cameras
    twin = DigitalTwin.load("runs/demo/export/twin.npz")
    traj = simulate_twin(twin, v0=[1.0, 0.5, 0.0], params={"E": 2e5}, n_frames=30)   # (31, N, 3) positions
    video = render_trajectory(twin, traj, orbit_cameras(twin, n=1))                   # (31, 1, H, W, 3)

Conventions: SI units, canonical world (``+y`` up, ground ``y = 0``). ``n_frames`` counts frames
*after* the initial one (``positions`` has ``n_frames + 1`` entries), each ``frame_dt`` seconds apart.
Simulated with exactly the twin's simulator settings, grid and kept dt halvings; with the fitted v0,
parameters and effects it reproduces the run's prediction to round-off.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from toolkit.atomic import write_with
from toolkit.twin.format import DigitalTwin, TwinFormatError

__all__ = ["TwinTrajectory", "simulate_twin", "twin_gaussians", "dataset_cameras", "orbit_cameras", "render_trajectory",
           "write_video"]


@dataclass
class TwinTrajectory:
    """A rollout of a twin.

    Attributes:
        positions: (T, N, 3) particle positions, m (T = n_frames + 1, frame 0 the initial state).
        means: (T, G, 3) Gaussian centres carried by the particles, m.
        times: (T,) seconds from the start.
        substeps: substeps per frame the simulator used.
        conditions: the v0 (m/s), params, effects and gravity (m/s^2) simulated.
        deformations: (T, G, 3, 3) the Gaussians' deformations since frame 0 when the twin's
            Gaussians deform with the material (``deform_index`` in the twin), else None.
    """

    positions: torch.Tensor
    means: torch.Tensor
    times: np.ndarray
    substeps: int
    conditions: dict
    deformations: Optional[torch.Tensor] = None


def _torch_device(device: str) -> torch.device:
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(device)


def _warp_device(dev: torch.device) -> str:
    return f"cuda:{dev.index or 0}" if dev.type == "cuda" else "cpu"


def simulate_twin(twin: DigitalTwin, v0: Optional[Sequence[float]] = None, params: Optional[dict] = None,
                  effects: Optional[dict] = None, gravity: Optional[Sequence[float]] = None, n_frames: Optional[int] = None,
                  device: str = "cpu") -> TwinTrajectory:
    """Simulate ``twin`` from its fitted frame-0 state.

    Args:
        v0: initial velocity (3,) m/s; default the fitted one.
        params: material parameters to change (physical units, e.g. ``{"E": 2e5}``); the others
            keep their fitted values.
        effects: effect parameters to change, ``{effect: {param: value}}`` (only effects the twin has).
        gravity: (3,) m/s^2; default the twin's.
        n_frames: frames after the initial one; default the fitted video's (``T - 1``).
        device: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``.
    """
    from materials import get_material
    from toolkit.mpm import MPMSimulator, SimConfig
    from toolkit.mpm.simulator import GridSpec
    from toolkit.physics.embedding import carry

    meta, a = twin.meta, twin.arrays
    dev = _torch_device(device)
    material = get_material(meta["material"]["name"], **meta["material"].get("options", {}))
    names = list(material.param_names)
    pvec = torch.as_tensor(a["material_params"], dtype=torch.float32).clone()
    if params:
        unknown = set(params) - set(names)
        if unknown:
            raise TwinFormatError(f"params {sorted(unknown)} are not parameters of {material.name!r}; its parameters are {names}")
        for k, v in params.items():
            pvec[names.index(k)] = float(v)
        material.validate(dict(zip(names, pvec.tolist())))
    cfg = SimConfig(**meta["sim"])
    sim = MPMSimulator(material, cfg, effects=meta.get("effect_order", list(meta["effects"])), device=_warp_device(dev))
    evec = torch.as_tensor(a["effect_params"], dtype=torch.float32).clone()
    if effects:
        current = sim.unpack_effects(evec)
        for name, vals in effects.items():
            if name not in current:
                raise TwinFormatError(f"effect {name!r} is not in this twin (its effects: {sorted(current) or 'none'})")
            current[name].update({k: float(v) for k, v in vals.items()})
        evec = sim.pack_effects(current).cpu()
    if meta.get("grid"):
        g = meta["grid"]
        sim.set_grid(GridSpec(tuple(g["origin"]), tuple(int(d) for d in g["dims"]), float(g["dx"])))
    sim.substeps_floor = int(meta.get("substeps_floor", 0))
    v = torch.as_tensor(meta["v0"] if v0 is None else v0, dtype=torch.float32).reshape(-1)
    grav = torch.as_tensor(meta["gravity"] if gravity is None else gravity, dtype=torch.float32).reshape(-1)
    for name, vec in (("v0", v), ("gravity", grav)):
        if vec.shape != (3,) or not torch.isfinite(vec).all():
            raise ValueError(f"{name} must be 3 finite numbers, got {vec.tolist()}")
    n = twin.n_frames - 1 if n_frames is None else int(n_frames)
    if n < 0:
        raise ValueError(f"n_frames must be >= 0, got {n_frames!r}")
    x0 = torch.as_tensor(a["particles"], dtype=torch.float32).to(dev)
    with torch.no_grad():
        out = sim.simulate(x0, v.to(dev), pvec.to(dev), gravity=grav.to(dev), effect_params=evec.to(dev), n_frames=n)
        means = carry(torch.as_tensor(a["gaussian_means"]).to(dev), out.positions, x0,
                      torch.as_tensor(a["embed_index"]).to(dev), torch.as_tensor(a["embed_weight"]).to(dev))
        deform = twin_deformations(twin, out.positions)
    conditions = {"v0": v.tolist(), "params": dict(zip(names, pvec.tolist())), "effects": sim.unpack_effects(evec),
                  "gravity": grav.tolist(), "n_frames": n}
    return TwinTrajectory(positions=out.positions.detach().cpu(), means=means.detach().cpu(),
                          times=np.arange(n + 1) * twin.frame_dt, substeps=int(out.substeps), conditions=conditions,
                          deformations=None if deform is None else deform.detach().cpu())


def twin_deformations(twin: DigitalTwin, positions: torch.Tensor) -> Optional[torch.Tensor]:
    """(T, G, 3, 3) the Gaussians' deformations along ``positions`` (T, N, 3), frame 0 first, or
    None when the twin's Gaussians keep their shapes."""
    from toolkit.physics.embedding import carry_deformation

    a = twin.arrays
    if "deform_index" not in a:
        return None
    dev = positions.device
    return carry_deformation(positions, positions[0], torch.as_tensor(a["deform_index"]).to(dev),
                             torch.as_tensor(a["deform_gradient"]).to(dev))


def twin_gaussians(twin: DigitalTwin, means: Optional[torch.Tensor] = None, device: str = "cpu",
                   deformation: Optional[torch.Tensor] = None):
    """The twin's Gaussians (:class:`renderers.base.Gaussians`), at frame 0 or moved to ``means``
    (G, 3) and shaped by ``deformation`` (G, 3, 3) when given."""
    from renderers.base import Gaussians

    a = twin.arrays
    t = lambda k: None if k not in a else torch.as_tensor(a[k]).to(device)  # noqa: E731
    m = t("gaussian_means") if means is None else torch.as_tensor(means, dtype=torch.float32).to(device)
    return Gaussians(means=m, log_scales=t("gaussian_log_scales"), quats=t("gaussian_quats"),
                     opacity_logits=t("gaussian_opacity_logits"), colors=t("gaussian_colors"), sh=t("gaussian_sh"),
                     deformation=None if deformation is None else torch.as_tensor(deformation, dtype=torch.float32).to(device))


def dataset_cameras(twin: DigitalTwin, indices: Optional[Sequence[int]] = None):
    """The dataset's cameras stored in the twin (:class:`toolkit.cameras.Cameras`), all or ``indices``."""
    from toolkit.cameras import Cameras

    c = twin.meta.get("cameras")
    if not c or "camera_K" not in twin.arrays:
        raise TwinFormatError("this twin stores no cameras; use orbit_cameras")
    cams = Cameras(torch.as_tensor(twin.arrays["camera_K"]), torch.as_tensor(twin.arrays["camera_w2c"]), c["width"],
                   c["height"], c.get("near", 0.01), c.get("far", 100.0))
    if indices is None:
        return cams
    bad = [i for i in indices if not 0 <= int(i) < len(cams)]
    if bad:
        raise ValueError(f"camera indices {bad} out of range 0..{len(cams) - 1}")
    return cams[[int(i) for i in indices]]


def orbit_cameras(twin: DigitalTwin, n: int = 8, width: Optional[int] = None, height: Optional[int] = None,
                  elevation_deg: float = 20.0, distance: Optional[float] = None, fov_y_deg: float = 40.0,
                  target: Optional[Sequence[float]] = None):
    """``n`` cameras on a circle around the object, looking at it (y up).

    Args:
        width, height: image size in px; default the dataset's cameras' (else 256 x 256).
        elevation_deg: height of the circle above the target, degrees.
        distance: metres from the target; default the one that fits 2.5x the object's extent in the view.
        target: point looked at, m; default the particles' centre at frame 0.
    """
    from toolkit.cameras import Cameras

    c = twin.meta.get("cameras") or {}
    w, h = int(width or c.get("width", 256)), int(height or c.get("height", 256))
    p = twin.arrays["particles"].astype(np.float64)
    centre = p.mean(0) if target is None else np.asarray(target, np.float64)
    extent = float(np.linalg.norm(p.max(0) - p.min(0)))
    r = distance if distance is not None else 1.25 * max(extent, 1e-3) / np.tan(np.radians(fov_y_deg) / 2)
    az = np.linspace(0.0, 2 * np.pi, int(n), endpoint=False)
    el = np.radians(elevation_deg)
    eyes = centre[None] + r * np.stack([np.cos(el) * np.sin(az), np.full_like(az, np.sin(el)), np.cos(el) * np.cos(az)], 1)
    return Cameras.look_at(eyes, centre, (0.0, 1.0, 0.0), fov_y_deg=fov_y_deg, width=w, height=h)


@torch.no_grad()
def render_trajectory(twin: DigitalTwin, traj: TwinTrajectory, cameras, renderer: Optional[str] = None,
                      device: str = "cpu") -> np.ndarray:
    """(T, C, H, W, 3) float32 RGB in [0, 1] of the Gaussians carried along ``traj``, object on black.

    Args:
        renderer: registered renderer name; default the twin's (``torch`` if that one is not available here).
    """
    from renderers import RENDERERS, get_renderer

    dev = _torch_device(device)
    name = renderer or twin.meta.get("renderer", "torch")
    if name not in RENDERERS:
        name = "torch"
    r = get_renderer(name)
    cams = cameras.to(dev)
    g0 = twin_gaussians(twin, device=str(dev))
    A = traj.deformations
    frames = [r(g0.replace(means=m.to(dev), deformation=None if A is None else A[t].to(dev)), cams).rgb.clamp(0, 1).cpu().numpy()
              for t, m in enumerate(traj.means)]
    return np.stack(frames).astype(np.float32)


def write_video(path, frames: np.ndarray, fps: float, captions: Optional[Sequence[str]] = None) -> "Path":
    """Write (T, H, W, 3) frames in [0, 1] as MP4 (GIF without ffmpeg) at the frames' own resolution.

    ``captions`` (one per frame) go in a band *below* the picture, never over it.
    """
    from pathlib import Path

    import imageio.v3 as iio

    frames = (np.clip(frames, 0, 1) * 255).astype(np.uint8)
    if captions is not None:
        from toolkit.report import caption_below

        frames = np.stack([caption_below(f, c) for f, c in zip(frames, captions)])
    H, W = frames.shape[1] // 2 * 2, frames.shape[2] // 2 * 2
    frames = frames[:, :H, :W]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        write_with(path, lambda p: iio.imwrite(p, frames, fps=fps, codec="libx264", macro_block_size=1))
        return path
    except Exception:  # noqa: BLE001 - no ffmpeg: a GIF
        gif = path.with_suffix(".gif")
        write_with(gif, lambda p: iio.imwrite(p, frames, duration=1000 / fps, loop=0))
        return gif

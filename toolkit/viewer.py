"""Viewing predicted and ground-truth particles over time (``projo4d view``).

* Where a display exists, :func:`show` opens an open3d window that plays the sequence (space:
  pause/play, N/P: next/previous frame, G: toggle the ground truth).
* On a headless machine, :func:`write_views` renders every frame offscreen to PNG files and an
  MP4: with open3d's offscreen renderer where it works (it needs EGL or Vulkan, probed once in a
  subprocess because a failing renderer can take the process down), else with a matplotlib 3D
  scatter, which works everywhere.

Each image shows the ground truth (left, grey) next to the prediction (right) coloured by its
error: each predicted particle's distance to the nearest ground-truth point, on a fixed scale
for the whole sequence. Frames after the training ones are marked *future*.

Point-cloud I/O and nearest-neighbour queries go through open3d (:func:`read_cloud`,
:func:`write_cloud`, :func:`nearest_distances`), which handles clouds of millions of points;
plain numpy/scipy fallbacks keep them working without it.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = ["RunClouds", "load_run_clouds", "read_cloud", "write_cloud", "nearest_distances", "open3d_offscreen_available",
           "display_available", "render_frames", "write_views", "show"]

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------ point-cloud I/O
def _o3d():
    try:
        import open3d as o3d  # noqa: PLC0415 - heavy: imported only here

        return o3d
    except Exception:  # noqa: BLE001 - missing wheel or a missing system library (libusb)
        return None


def read_cloud(path: str | Path) -> np.ndarray:
    """(N, 3) float64 points of a point-cloud file (PLY, PCD, XYZ, ... through open3d)."""
    o3d = _o3d()
    if o3d is not None:
        pcd = o3d.io.read_point_cloud(str(path))
        pts = np.asarray(pcd.points)
        if len(pts):
            return pts
    from toolkit.data.ply import read_ply_points

    return np.asarray(read_ply_points(path), dtype=np.float64)


def write_cloud(path: str | Path, points: np.ndarray, colors: Optional[np.ndarray] = None) -> Path:
    """Write points (and RGB colours in [0, 1]) to a point-cloud file (format from the suffix)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    o3d = _o3d()
    if o3d is not None:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
        if colors is not None:
            pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64))
        if not o3d.io.write_point_cloud(str(path), pcd):
            raise OSError(f"open3d could not write {path}")
        return path
    from toolkit.data.ply import write_ply_points

    return write_ply_points(path, points)


def nearest_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a`` (N, 3), the distance to its nearest neighbour in ``b`` (M, 3)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if len(a) == 0:
        return np.zeros(0)
    if len(b) == 0:
        return np.full(len(a), np.inf)
    o3d = _o3d()
    if o3d is not None:
        pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a))
        pb = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b))
        return np.asarray(pa.compute_point_cloud_distance(pb))
    from scipy.spatial import cKDTree

    return cKDTree(b).query(a, k=1)[0]


# ------------------------------------------------------------------------------------ data of a run
@dataclass
class RunClouds:
    """Particles of a run over time.

    Attributes:
        predicted: (T, N, 3) predicted particle positions (metres).
        truth: ground-truth clouds, one (M_t, 3) array per frame, or ``None``.
        n_train: frames ``[0, n_train)`` were fitted; the rest are the future.
        name: a label (the run folder's name).
    """

    predicted: np.ndarray
    truth: Optional[list[np.ndarray]]
    n_train: int
    name: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.predicted.shape[0])


def _subsample(points: np.ndarray, n: Optional[int], seed: int = 0) -> np.ndarray:
    if n is None or len(points) <= n:
        return points
    idx = np.random.default_rng(seed).choice(len(points), n, replace=False)
    return points[np.sort(idx)]


def load_run_clouds(run_dir: str | Path, device: str = "cpu", max_points: Optional[int] = None) -> RunClouds:
    """Predicted particles of a run folder (``evaluation/prediction.npz``, else simulated from the
    fitted model) and the ground-truth clouds of its scene when it has them.

    Args:
        run_dir: a run folder of ``projo4d run`` or ``projo4d benchmark``.
        device: device of the simulation when no prediction is stored.
        max_points: subsample each cloud to at most this many points (``None``: all).
    """
    run = Path(run_dir)
    pred_path = run / "evaluation" / "prediction.npz"
    n_train, gt_paths = None, None
    inp_path = run / "physics_input.pt"
    if inp_path.exists():
        import torch

        d = torch.load(inp_path, map_location="cpu", weights_only=False, mmap=True)
        n_train = int(d["n_train"])
        gt_paths = ((d.get("ground_truth") or {}).get("point_clouds")) or None
    if pred_path.is_file():
        predicted = np.load(pred_path)["positions"]
    else:
        from toolkit.pipeline import load_fitted_module

        module = load_fitted_module(run, device=device)
        predicted = module.predict_trajectory()["positions"].cpu().numpy()
        n_train = module.input.n_train
    if n_train is None:
        ev = run / "evaluation" / "evaluation.json"
        n_train = json.loads(ev.read_text())["n_train"] if ev.is_file() else predicted.shape[0]
    truth = None
    if gt_paths and len(gt_paths) >= predicted.shape[0] and all(Path(p).is_file() for p in gt_paths[: predicted.shape[0]]):
        truth = [_subsample(read_cloud(p), max_points, t) for t, p in enumerate(gt_paths[: predicted.shape[0]])]
    if max_points is not None and predicted.shape[1] > max_points:
        idx = np.sort(np.random.default_rng(0).choice(predicted.shape[1], max_points, replace=False))
        predicted = predicted[:, idx]
    return RunClouds(predicted=np.asarray(predicted, dtype=np.float64), truth=truth, n_train=int(n_train), name=run.name)


# ------------------------------------------------------------------------------------ environment
def display_available() -> bool:
    """Whether a window can be opened (an X11 or Wayland display is set)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


_PROBE = """
import numpy as np, open3d as o3d
r = o3d.visualization.rendering.OffscreenRenderer(32, 32)
m = o3d.visualization.rendering.MaterialRecord(); m.shader = "defaultUnlit"; m.point_size = 2.0
p = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.rand(50, 3)))
r.scene.add_geometry("p", p, m)
r.setup_camera(60.0, [0.5, 0.5, 0.5], [0.5, 0.5, 3.0], [0.0, 1.0, 0.0])
img = np.asarray(r.render_to_image())
assert img.shape[0] == 32
print("ok")
"""


@lru_cache(maxsize=1)
def open3d_offscreen_available(timeout: float = 60.0) -> bool:
    """Whether open3d's offscreen renderer works here (tried once, in a subprocess)."""
    if _o3d() is None:
        return False
    try:
        res = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=timeout)
    except (subprocess.TimeoutExpired, OSError):
        return False
    ok = res.returncode == 0 and "ok" in res.stdout
    if not ok:
        log.info("open3d offscreen rendering is not available here: %s", (res.stderr or "").strip().splitlines()[-1:] or "")
    return ok


# ------------------------------------------------------------------------------------ rendering
def _bounds(clouds: RunClouds) -> tuple[np.ndarray, np.ndarray]:
    pts = [clouds.predicted.reshape(-1, 3)] + ([np.concatenate(clouds.truth)] if clouds.truth else [])
    allp = np.concatenate(pts)
    allp = allp[np.isfinite(allp).all(1)]
    lo, hi = allp.min(0), allp.max(0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-3) * 1.05
    return centre - half, centre + half


def _error_colors(clouds: RunClouds) -> tuple[list[np.ndarray], float]:
    """Per frame, RGB colours of the predicted particles by distance to the truth (viridis), and the scale."""
    import matplotlib

    if not clouds.truth:
        return [np.tile([0.12, 0.47, 0.71], (clouds.predicted.shape[1], 1)) for _ in range(clouds.n_frames)], 0.0
    dists = [nearest_distances(p, g) for p, g in zip(clouds.predicted, clouds.truth)]
    finite = np.concatenate([d[np.isfinite(d)] for d in dists]) if dists else np.zeros(1)
    scale = float(np.percentile(finite, 95)) if finite.size else 1.0
    scale = scale if scale > 0 else 1.0
    cmap = matplotlib.colormaps["viridis"]
    return [cmap(np.clip(d / scale, 0, 1))[:, :3] for d in dists], scale


def _caption(clouds: RunClouds, t: int) -> str:
    return f"{clouds.name}  frame {t}/{clouds.n_frames - 1}  {'future' if t >= clouds.n_train else 'fitted'}"


def _render_matplotlib(clouds: RunClouds, frames: Sequence[int], size: tuple[int, int], elev: float, azim: float,
                       point_size: float) -> list[np.ndarray]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = _bounds(clouds)
    colors, scale = _error_colors(clouds)
    dpi = 100
    out = []
    panels = 2 if clouds.truth else 1
    for t in frames:
        fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
        titles = (["ground truth", f"prediction (colour: error, 0-{scale * 100:.1f} cm)"] if clouds.truth else ["prediction"])
        for k in range(panels):
            ax = fig.add_subplot(1, panels, k + 1, projection="3d")
            if clouds.truth and k == 0:
                pts, col = clouds.truth[t], "0.45"
            else:
                pts, col = clouds.predicted[t], colors[t]
                if clouds.truth:  # the truth faintly behind the prediction, for reference
                    g = clouds.truth[t]
                    ax.scatter(g[:, 0], g[:, 2], g[:, 1], s=point_size * 0.5, c="0.85", depthshade=False, linewidths=0)
            # y is up in the toolkit; matplotlib's vertical axis is z
            ax.scatter(pts[:, 0], pts[:, 2], pts[:, 1], s=point_size, c=col, depthshade=False, linewidths=0)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[2], hi[2])
            ax.set_zlim(lo[1], hi[1])
            ax.set_box_aspect((1, 1, 1))
            ax.view_init(elev=elev, azim=azim)
            ax.set_title(titles[k], fontsize=8)
            ax.tick_params(labelsize=5)
        fig.suptitle(_caption(clouds, t), fontsize=9)
        fig.canvas.draw()
        img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        plt.close(fig)
        out.append(img)
    return out


def _render_open3d(clouds: RunClouds, frames: Sequence[int], size: tuple[int, int], elev: float, azim: float,
                   point_size: float) -> list[np.ndarray]:
    import open3d as o3d
    from PIL import Image, ImageDraw

    lo, hi = _bounds(clouds)
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo))
    e, a = np.radians(elev), np.radians(azim)
    eye = centre + radius * np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])
    colors, _ = _error_colors(clouds)
    panels = 2 if clouds.truth else 1
    w = size[0] // panels
    renderer = o3d.visualization.rendering.OffscreenRenderer(w, size[1])
    mat = o3d.visualization.rendering.MaterialRecord()
    mat.shader = "defaultUnlit"
    mat.point_size = float(max(1.0, point_size))
    renderer.scene.set_background([1.0, 1.0, 1.0, 1.0])
    out = []
    for t in frames:
        tiles = []
        for k in range(panels):
            renderer.scene.clear_geometry()
            if clouds.truth and k == 0:
                pts, col = clouds.truth[t], np.tile([0.45, 0.45, 0.45], (len(clouds.truth[t]), 1))
            else:
                pts, col = clouds.predicted[t], colors[t]
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            pcd.colors = o3d.utility.Vector3dVector(col)
            renderer.scene.add_geometry("points", pcd, mat)
            renderer.setup_camera(40.0, centre.tolist(), eye.tolist(), [0.0, 1.0, 0.0])
            tiles.append(np.asarray(renderer.render_to_image())[..., :3])
        img = Image.fromarray(np.concatenate(tiles, axis=1))
        ImageDraw.Draw(img).text((4, 4), _caption(clouds, t) + ("   left: truth, right: prediction" if panels == 2 else ""),
                                 fill=(0, 0, 0))
        out.append(np.asarray(img))
    return out


def render_frames(clouds: RunClouds, frames: Optional[Sequence[int]] = None, backend: str = "auto",
                  size: tuple[int, int] = (960, 480), elev: float = 20.0, azim: float = -60.0,
                  point_size: float = 2.0) -> tuple[list[np.ndarray], str]:
    """RGB images (H, W, 3) uint8 of ``frames`` (default all) and the backend used.

    Args:
        backend: ``"open3d"``, ``"matplotlib"`` or ``"auto"`` (open3d's offscreen renderer when
            :func:`open3d_offscreen_available`, else matplotlib).
    """
    frames = list(range(clouds.n_frames)) if frames is None else [int(t) for t in frames]
    bad = [t for t in frames if not 0 <= t < clouds.n_frames]
    if bad:
        raise ValueError(f"frames {bad} out of range 0..{clouds.n_frames - 1}")
    if backend not in ("auto", "open3d", "matplotlib"):
        raise ValueError(f"backend must be 'auto', 'open3d' or 'matplotlib', got {backend!r}")
    if backend in ("auto", "open3d") and open3d_offscreen_available():
        try:
            return _render_open3d(clouds, frames, size, elev, azim, point_size), "open3d"
        except Exception as err:  # noqa: BLE001 - fall back below
            if backend == "open3d":
                raise
            log.info("open3d offscreen rendering failed (%s); using matplotlib", err)
    elif backend == "open3d":
        raise RuntimeError("open3d's offscreen renderer does not work on this machine (no EGL/Vulkan); use backend='matplotlib'")
    return _render_matplotlib(clouds, frames, size, elev, azim, point_size), "matplotlib"


def _even(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    return img[:h, :w]


def write_views(run_dir: str | Path, out_dir: Optional[str | Path] = None, frames: Optional[Sequence[int]] = None,
                formats: Sequence[str] = ("png", "mp4"), backend: str = "auto", size: tuple[int, int] = (960, 480),
                fps: float = 6.0, max_points: Optional[int] = 20000, export_ply: bool = False, elev: float = 20.0,
                azim: float = -60.0, device: str = "cpu") -> list[Path]:
    """Render a run's particles offscreen: ``frame_XXX.png`` for ``frames`` (default: the first,
    the last fitted and the last frame) and ``strip.png`` of them, ``particles.mp4`` of every
    frame (a GIF without ffmpeg); with ``export_ply``, ``predicted_XXX.ply`` per frame.

    Returns:
        The files written (in ``out_dir``, default ``RUN_DIR/view``).
    """
    import imageio.v3 as iio

    clouds = load_run_clouds(run_dir, device=device, max_points=max_points)
    out = Path(out_dir) if out_dir else Path(run_dir) / "view"
    out.mkdir(parents=True, exist_ok=True)
    T = clouds.n_frames
    if frames is None:
        frames = sorted({0, max(0, clouds.n_train - 1), T - 1})
    written: list[Path] = []
    want_png, want_mp4 = "png" in formats, "mp4" in formats
    render_list = list(range(T)) if want_mp4 else list(frames)
    images, backend_used = render_frames(clouds, render_list, backend, size, elev, azim)
    by_frame = dict(zip(render_list, images))
    if want_png:
        for t in frames:
            p = out / f"frame_{t:03d}.png"
            iio.imwrite(p, by_frame[t])
            written.append(p)
        strip = out / "strip.png"
        iio.imwrite(strip, np.concatenate([by_frame[t] for t in frames], axis=0))
        written.append(strip)
    if want_mp4:
        stack = np.stack([_even(by_frame[t]) for t in range(T)])
        mp4 = out / "particles.mp4"
        try:
            iio.imwrite(mp4, stack, fps=fps, codec="libx264", macro_block_size=1)
            written.append(mp4)
        except Exception:  # noqa: BLE001 - no ffmpeg: a GIF
            gif = mp4.with_suffix(".gif")
            iio.imwrite(gif, stack, duration=1000 / fps, loop=0)
            written.append(gif)
    if export_ply:
        colors, _ = _error_colors(clouds)
        for t in range(T):
            written.append(write_cloud(out / f"predicted_{t:03d}.ply", clouds.predicted[t], colors[t]))
    (out / "view.json").write_text(json.dumps({"backend": backend_used, "frames": list(frames), "n_train": clouds.n_train,
                                               "files": [p.name for p in written]}, indent=2))
    return written


def show(run_dir: str | Path, fps: float = 6.0, max_points: Optional[int] = None, device: str = "cpu") -> None:
    """Play a run's predicted (coloured by error) and ground-truth (grey) particles in an open3d
    window. Keys: space pause/play, N/P next/previous frame, G toggle the ground truth, Q quit."""
    o3d = _o3d()
    if o3d is None:
        raise RuntimeError("open3d is not importable here; use write_views (offscreen files) instead")
    if not display_available():
        raise RuntimeError("no display (DISPLAY/WAYLAND_DISPLAY unset); use write_views (offscreen files) instead")
    import time

    clouds = load_run_clouds(run_dir, device=device, max_points=max_points)
    colors, _ = _error_colors(clouds)
    state = {"t": 0, "playing": True, "truth": clouds.truth is not None, "last": time.time()}
    pred = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(clouds.predicted[0]))
    pred.colors = o3d.utility.Vector3dVector(colors[0])
    truth = o3d.geometry.PointCloud()
    if clouds.truth:
        truth.points = o3d.utility.Vector3dVector(clouds.truth[0])
        truth.paint_uniform_color([0.6, 0.6, 0.6])
    vis = o3d.visualization.VisualizerWithKeyCallback()
    vis.create_window(window_name=f"projo4d view {clouds.name}", width=1280, height=800)
    vis.add_geometry(pred)
    vis.add_geometry(truth)

    def update(v) -> bool:
        t = state["t"]
        pred.points = o3d.utility.Vector3dVector(clouds.predicted[t])
        pred.colors = o3d.utility.Vector3dVector(colors[t])
        if clouds.truth:
            truth.points = o3d.utility.Vector3dVector(clouds.truth[t] if state["truth"] else np.zeros((0, 3)))
            truth.paint_uniform_color([0.6, 0.6, 0.6])
        v.update_geometry(pred)
        v.update_geometry(truth)
        print(f"\r{_caption(clouds, t)}   ", end="", flush=True)
        return True

    def tick(v) -> bool:
        if state["playing"] and time.time() - state["last"] >= 1.0 / fps:
            state["last"] = time.time()
            state["t"] = (state["t"] + 1) % clouds.n_frames
            return update(v)
        return False

    def key(fn):
        def cb(v):
            fn()
            return update(v)
        return cb

    vis.register_animation_callback(tick)
    vis.register_key_callback(ord(" "), key(lambda: state.update(playing=not state["playing"])))
    vis.register_key_callback(ord("N"), key(lambda: state.update(t=(state["t"] + 1) % clouds.n_frames, playing=False)))
    vis.register_key_callback(ord("P"), key(lambda: state.update(t=(state["t"] - 1) % clouds.n_frames, playing=False)))
    vis.register_key_callback(ord("G"), key(lambda: state.update(truth=not state["truth"])))
    vis.run()
    vis.destroy_window()
    print()

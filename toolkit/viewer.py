"""Viewing predicted and ground-truth particles over time (``projo4d view``).

* Interactively, in the browser: :func:`show` starts the viser viewer of :mod:`toolkit.twin.viewer`
  (time slider, prediction against truth, the cameras, sliders that re-simulate the twin); it
  works on a headless server too (open the printed address, or forward the port).
* As files: :func:`write_views` renders every frame to PNG files and an MP4 with matplotlib (works
  everywhere; open3d's offscreen renderer is an optional backend when the ``open3d`` extra is
  installed and EGL/Vulkan work).

Each image shows the ground truth (left, blue) next to the prediction (right) coloured by its
error: each predicted particle's distance to the nearest ground-truth point, in centimetres, on a
fixed scale for the whole sequence (colour bar); the truth is drawn faintly behind it. Axes are in
metres with ``y`` up, equal aspect. Captions (run, frame, time, *fitted* or *future*) sit above the
plots, outside the picture.

Point-cloud I/O and nearest-neighbour queries use numpy and scipy (:func:`read_cloud`,
:func:`write_cloud`, :func:`nearest_distances`); open3d is not needed.
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
    """open3d when the optional extra is installed and importable, else None."""
    try:
        import open3d as o3d  # noqa: PLC0415 - optional, heavy

        return o3d
    except Exception:  # noqa: BLE001 - missing wheel or a missing system library (libusb)
        return None


def read_cloud(path: str | Path) -> np.ndarray:
    """(N, 3) float64 points of a PLY point cloud (ASCII or binary; :func:`toolkit.data.ply.read_ply_points`).

    Other formats (PCD, XYZ, ...) are read through open3d when the optional extra is installed.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        o3d = _o3d()
        if o3d is None:
            raise ValueError(f"{path}: only PLY point clouds are read without open3d (pip install 'projo4d[open3d]')")
        return np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    from toolkit.data.ply import read_ply_points

    return np.asarray(read_ply_points(path), dtype=np.float64)


def write_cloud(path: str | Path, points: np.ndarray, colors: Optional[np.ndarray] = None) -> Path:
    """Write (N, 3) points, m (and (N, 3) RGB colours in [0, 1]) as a binary little-endian PLY
    (``x y z`` float32, ``red green blue`` uchar)."""
    pts = np.asarray(points, dtype="<f4")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"{path}: write_cloud writes PLY files; use a .ply suffix")
    if colors is None:
        from toolkit.data.ply import write_ply_points

        return write_ply_points(path, pts)
    cols = np.asarray(colors, dtype=np.float64)
    if cols.shape != pts.shape:
        raise ValueError(f"colors must have shape {pts.shape} (RGB in [0, 1]), got {cols.shape}")
    table = np.empty(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate("xyz"):
        table[k] = pts[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        table[k] = np.clip(np.round(cols[:, i] * 255), 0, 255).astype(np.uint8)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode("ascii") + table.tobytes())
    return path


def nearest_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a`` (N, 3), the distance (same units) to its nearest neighbour in ``b`` (M, 3)."""
    from scipy.spatial import cKDTree

    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if len(a) == 0:
        return np.zeros(0)
    if len(b) == 0:
        return np.full(len(a), np.inf)
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
    """Per frame, RGB colours of the predicted particles by distance to the truth (viridis), and the
    scale in metres (the 95th percentile of all distances: the top of the colour bar)."""
    import matplotlib

    if not clouds.truth:
        return [np.tile(np.asarray(PREDICTION_COLOR), (clouds.predicted.shape[1], 1)) for _ in range(clouds.n_frames)], 0.0
    dists = [nearest_distances(p, g) for p, g in zip(clouds.predicted, clouds.truth)]
    finite = np.concatenate([d[np.isfinite(d)] for d in dists]) if dists else np.zeros(1)
    scale = float(np.percentile(finite, 95)) if finite.size else 1.0
    scale = scale if scale > 0 else 1.0
    cmap = matplotlib.colormaps[ERROR_CMAP]
    return [cmap(np.clip(d / scale, 0, 1))[:, :3] for d in dists], scale


#: matplotlib colours: the truth blue, a prediction without truth orange; errors on this colour map
TRUTH_COLOR = (0.16, 0.35, 0.78)
PREDICTION_COLOR = (1.0, 0.43, 0.0)
ERROR_CMAP = "plasma"


def _caption(clouds: RunClouds, t: int) -> str:
    return f"{clouds.name}  frame {t}/{clouds.n_frames - 1}  {'future' if t >= clouds.n_train else 'fitted'}"


def _render_matplotlib(clouds: RunClouds, frames: Sequence[int], size: tuple[int, int], elev: float, azim: float,
                       point_size: float) -> list[np.ndarray]:
    """One image per frame: truth | prediction coloured by error (+ colour bar), axes in metres, y up."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    lo, hi = _bounds(clouds)
    colors, scale = _error_colors(clouds)
    dpi = 100
    out = []
    panels = 2 if clouds.truth else 1
    fs = max(5.0, min(9.0, size[1] / 60))

    def marker(n: int, n_ref: int) -> float:
        """Marker area (pt^2) so a sparse cloud covers its volume like a dense one: spacing ~ n^(-1/3)."""
        return float(np.clip(point_size * (max(n_ref, 1) / max(n, 1)) ** (2 / 3), point_size, 40 * point_size))

    for t in frames:
        n_ref = max(clouds.predicted.shape[1], len(clouds.truth[t]) if clouds.truth else 0)
        fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
        # caption in its own band above the plots, never over the picture
        fig.text(0.5, 0.985, _caption(clouds, t), ha="center", va="top", fontsize=fs + 1)
        right = 0.86 if clouds.truth else 0.98
        width = (right - 0.02) / panels
        for k in range(panels):
            ax = fig.add_axes((0.02 + k * width, 0.04, width, 0.86), projection="3d")
            if clouds.truth and k == 0:
                pts, col, title = clouds.truth[t], [TRUTH_COLOR], "ground truth (blue)"
            else:
                pts, col = clouds.predicted[t], colors[t]
                title = "prediction, colour: distance to truth" if clouds.truth else "prediction"
                if clouds.truth:  # the truth faintly behind the prediction, for reference
                    g = clouds.truth[t]
                    ax.scatter(g[:, 0], g[:, 2], g[:, 1], s=marker(len(g), n_ref) * 0.5, c=[(0.75, 0.8, 0.92)],
                               depthshade=False, linewidths=0, alpha=0.5)
            # y is up in the toolkit; matplotlib's vertical axis is z
            ax.scatter(pts[:, 0], pts[:, 2], pts[:, 1], s=marker(len(pts), n_ref), c=col, depthshade=False, linewidths=0)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[2], hi[2])
            ax.set_zlim(lo[1], hi[1])
            ax.set_box_aspect((1, 1, 1))
            ax.view_init(elev=elev, azim=azim)
            ax.set_title(title, fontsize=fs, pad=0)
            ax.set_xlabel("x (m)", fontsize=fs, labelpad=-6)
            ax.set_ylabel("z (m)", fontsize=fs, labelpad=-6)
            ax.set_zlabel("y, up (m)", fontsize=fs, labelpad=-6)
            ax.tick_params(labelsize=fs - 2, pad=-3)
        if clouds.truth:
            cax = fig.add_axes((0.88, 0.15, 0.02, 0.65))
            bar = fig.colorbar(ScalarMappable(Normalize(0, scale * 100), matplotlib.colormaps[ERROR_CMAP]), cax=cax)
            bar.set_label("distance to truth (cm)", fontsize=fs)
            bar.ax.tick_params(labelsize=fs - 1)
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
        backend: ``"matplotlib"`` (axes in metres, colour bar), ``"auto"`` (the same) or ``"open3d"``
            (optional extra; needs :func:`open3d_offscreen_available`).
    """
    frames = list(range(clouds.n_frames)) if frames is None else [int(t) for t in frames]
    bad = [t for t in frames if not 0 <= t < clouds.n_frames]
    if bad:
        raise ValueError(f"frames {bad} out of range 0..{clouds.n_frames - 1}")
    if backend not in ("auto", "open3d", "matplotlib"):
        raise ValueError(f"backend must be 'auto', 'open3d' or 'matplotlib', got {backend!r}")
    if backend == "open3d" and open3d_offscreen_available():
        try:
            return _render_open3d(clouds, frames, size, elev, azim, point_size), "open3d"
        except Exception as err:  # noqa: BLE001 - fall back below
            if backend == "open3d":
                raise
            log.info("open3d offscreen rendering failed (%s); using matplotlib", err)
    elif backend == "open3d":
        raise RuntimeError("open3d's offscreen renderer does not work on this machine (open3d missing, or no EGL/Vulkan); "
                           "use backend='matplotlib'")
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


def show(run_dir: str | Path, host: str = "127.0.0.1", port: int = 8080, max_points: Optional[int] = 20000,
         device: str = "cpu") -> None:
    """Serve the run in the browser viewer (:mod:`toolkit.twin.viewer`) until Ctrl-C.

    Needs the ``viewer`` extra (viser). Prints the address to open.
    """
    try:
        import viser  # noqa: F401
    except ImportError:
        from toolkit.errors import UserError

        raise UserError("the browser viewer needs viser: pip install 'projo4d[viewer]'; or write files with "
                           "`projo4d view RUN --offscreen`") from None
    from toolkit.twin.viewer import serve_run

    serve_run(run_dir, host=host, port=port, max_points=max_points, device=device, block=True)

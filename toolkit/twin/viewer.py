"""An interactive viewer of a run or a digital twin in the browser, built on viser.

``projo4d view RUN --browser`` (or :func:`serve_run`) starts a local web server; open the printed
address. The page shows, in the canonical world (metres, ``+y`` up, the ground grid at ``y = 0``,
10 cm cells):

* the predicted particles (orange) and the ground-truth cloud (blue) of the current frame, and the
  Gaussians carried by the particles (splats, toggled);
* the dataset's cameras as frustums (fitted cameras red, held-out ones grey);
* a time slider with play, a label saying *fitted* or *future*;
* a playground: a slider per material parameter (log10 for moduli and viscosities), the initial
  velocity and the frame count; **Re-simulate** rolls the twin out with them and shows the result
  (truth is hidden then: it belongs to the fitted conditions); **Reset** returns to the fit.

:class:`TwinViewer` can be driven from Python (``set_frame``, ``resimulate``) and reports what it
draws (``drawn()``), which the tests use together with a headless browser.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Optional, Sequence

import numpy as np

from toolkit.twin.format import DigitalTwin

__all__ = ["TwinViewer", "serve_run", "PREDICTION_RGB", "TRUTH_RGB"]

log = logging.getLogger(__name__)

#: colours of the clouds (uint8 RGB): prediction orange, truth blue (told apart also in grey scale)
PREDICTION_RGB = (255, 110, 0)
TRUTH_RGB = (40, 90, 200)


def _subsample(points: np.ndarray, n: Optional[int], seed: int = 0) -> np.ndarray:
    if n is None or len(points) <= n:
        return points
    return points[np.sort(np.random.default_rng(seed).choice(len(points), n, replace=False))]


def _covariances(log_scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(G, 3, 3) covariances R diag(s^2) R^T from log-scales (G, 1|3) and quaternions (w, x, y, z)."""
    s = np.exp(log_scales.astype(np.float64))
    if s.shape[1] == 1:
        s = np.repeat(s, 3, axis=1)
    q = quats.astype(np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    w, x, y, z = q.T
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    return (R * (s ** 2)[:, None, :]) @ R.transpose(0, 2, 1)


def _gaussian_rgb(arrays: dict) -> np.ndarray:
    if "gaussian_colors" in arrays:
        return np.clip(arrays["gaussian_colors"], 0, 1)
    return np.clip(0.28209479 * arrays["gaussian_sh"][:, 0, :] + 0.5, 0, 1)


def _c2w_wxyz_position(w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """viser pose (quaternion w, x, y, z and position) of an OpenCV world-to-camera matrix (viser uses OpenCV axes)."""
    R = w2c[:3, :3].T
    pos = -R @ w2c[:3, 3]
    tr = np.trace(R)
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(max(1 + R[i, i] - R[j, j] - R[k, k], 1e-12))
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    return np.asarray(q), pos


class TwinViewer:
    """A viser server showing a twin's trajectory (see the module docstring).

    Args:
        twin: the digital twin (from :func:`toolkit.twin.export.twin_from_module` or a file).
        prediction: (T, N, 3) predicted particles, m; default the twin simulated with its fitted state.
        truth: ground-truth clouds, one (M_t, 3) array per frame, m, or None.
        host, port: where the server listens (``port=0``: a free one).
        max_points: points drawn per cloud.
        point_size: metres.
        device: simulation device of the playground.
    """

    def __init__(self, twin: DigitalTwin, prediction: Optional[np.ndarray] = None, truth: Optional[Sequence[np.ndarray]] = None,
                 host: str = "127.0.0.1", port: int = 8080, max_points: Optional[int] = 20000, point_size: Optional[float] = None,
                 device: str = "cpu", name: str = ""):
        import viser

        from toolkit.twin.simulate import simulate_twin

        self.twin = twin
        self.device = device
        self.max_points = max_points
        self._lock = threading.RLock()
        if prediction is None:
            traj = simulate_twin(twin, device=device)
            prediction, means = traj.positions.numpy(), traj.means.numpy()
        else:
            means = None
        self.fitted = (np.asarray(prediction, np.float32), means)
        self.positions, self.means = self.fitted
        self.truth = None if truth is None else [np.asarray(_subsample(np.asarray(c), max_points, t), np.float32)
                                                 for t, c in enumerate(truth)]
        self.showing_fit = True
        spacing = float(twin.meta["sim"].get("particle_volume") or (twin.meta["sim"]["dx"] / 2) ** 3) ** (1 / 3)
        self.point_size = point_size or 1.2 * spacing
        if port == 0:
            port = _free_port(host)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.host = host
        self.url = f"http://{host}:{self.port}"
        self._build(name)
        self.set_frame(0)

    # ------------------------------------------------------------------ scene
    def _build(self, name: str) -> None:
        s = self.server
        s.scene.set_up_direction("+y")
        p0 = self.positions[0]
        span = float(np.max(np.ptp(self.positions.reshape(-1, 3), axis=0))) if self.positions.size else 1.0
        centre = p0.mean(0)
        size = max(1.0, math.ceil(2 * span + 0.5))
        s.scene.add_grid("/ground", width=size, height=size, plane="xz", cell_size=0.1, section_size=1.0,
                         position=(float(centre[0]), 0.0, float(centre[2])))
        s.scene.add_frame("/axes", axes_length=0.1, axes_radius=0.003, position=(0.0, 0.0, 0.0))
        s.scene.add_label("/axes/label", "origin; x red, y (up) green, z blue; grid 10 cm", position=(0.0, 0.0, 0.0))
        allp = self.positions.reshape(-1, 3)
        lo, hi = allp.min(0), allp.max(0)
        look = (lo + hi) / 2
        direction = np.array([0.8, 0.5, 1.0]) / np.linalg.norm([0.8, 0.5, 1.0])
        s.initial_camera.look_at = tuple(float(v) for v in look)
        s.initial_camera.position = tuple(float(v) for v in look + 1.6 * max(float(np.linalg.norm(hi - lo)), 0.2) * direction)
        self._add_cameras()
        a = self.twin.arrays
        self._cov = _covariances(a["gaussian_log_scales"], a["gaussian_quats"]).astype(np.float32)
        self._rgb = _gaussian_rgb(a).astype(np.float32)
        self._opacity = (1 / (1 + np.exp(-a["gaussian_opacity_logits"].astype(np.float64))))[:, None].astype(np.float32)
        self._pred = None
        self._truth = None
        self._splats = None
        self._gui(name)

    def _add_cameras(self) -> None:
        c = self.twin.meta.get("cameras")
        if not c or "camera_K" not in self.twin.arrays:
            return
        K, w2c = self.twin.arrays["camera_K"], self.twin.arrays["camera_w2c"]
        train = set(c.get("train", []))
        scale = 0.04 * float(np.median(np.linalg.norm([_c2w_wxyz_position(m)[1] - self.positions[0].mean(0) for m in w2c], axis=1)))
        for i in range(len(K)):
            wxyz, pos = _c2w_wxyz_position(w2c[i].astype(np.float64))
            fov = 2 * math.atan(0.5 * c["height"] / float(K[i][1, 1]))
            self.server.scene.add_camera_frustum(f"/cameras/cam_{i:02d}", fov=fov, aspect=c["width"] / c["height"], scale=scale,
                                                 color=(220, 30, 30) if i in train else (120, 120, 120), wxyz=wxyz, position=pos)

    def _gui(self, name: str) -> None:
        g = self.server.gui
        T = len(self.positions)
        g.add_markdown(f"**projo4d** {name}  \norange: prediction, blue: ground truth; metres, y up, "
                       f"ground y = 0. Fitted frames 0-{self.twin.meta['n_train'] - 1}.")
        self.frame_slider = g.add_slider("frame", min=0, max=max(T - 1, 1), step=1, initial_value=0)
        self.frame_slider.on_update(lambda _: self.set_frame(int(self.frame_slider.value)))
        self.status = g.add_markdown("")
        self.play = g.add_checkbox("play", False)
        self.show_pred = g.add_checkbox("prediction", True)
        self.show_truth = g.add_checkbox("ground truth", self.truth is not None, disabled=self.truth is None)
        self.show_splats = g.add_checkbox("Gaussians", False)
        for box in (self.show_pred, self.show_truth, self.show_splats):
            box.on_update(lambda _: self.set_frame(self.frame))
        with g.add_folder("playground: re-simulate"):
            from materials import get_material

            material = get_material(self.twin.material, **self.twin.meta["material"].get("options", {}))
            self.param_sliders = {}
            for p in material.params:
                v = float(self.twin.params[p.name])
                if p.transform == "log10" and v > 0:
                    lv = math.log10(v)
                    h = g.add_slider(f"log10 {p.name} ({p.units or '-'})", min=round(lv - 2, 2), max=round(lv + 2, 2),
                                     step=0.01, initial_value=round(lv, 4))
                    self.param_sliders[p.name] = (h, True)
                else:
                    lo = p.low if math.isfinite(p.low) else v - 10
                    hi = p.high if math.isfinite(p.high) else v + 10
                    h = g.add_slider(f"{p.name} ({p.units or '-'})", min=float(lo), max=float(hi), step=(hi - lo) / 200,
                                     initial_value=float(np.clip(v, lo, hi)))
                    self.param_sliders[p.name] = (h, False)
            v0 = self.twin.v0
            self.v0_input = g.add_vector3("v0 (m/s)", tuple(round(x, 4) for x in v0), step=0.01)
            self.frames_input = g.add_number("frames", T - 1, min=1, max=1000, step=1)
            self.sim_button = g.add_button("Re-simulate")
            self.reset_button = g.add_button("Reset to the fit")
            self.sim_button.on_click(lambda _: self._resimulate_from_gui())
            self.reset_button.on_click(lambda _: self.reset())
        self._player = threading.Thread(target=self._play_loop, daemon=True)
        self._stop = False
        self._player.start()

    def _play_loop(self) -> None:
        dt = float(self.twin.frame_dt)
        while not self._stop:
            time.sleep(max(dt, 0.05))
            if self.play.value:
                self.frame_slider.value = (self.frame + 1) % len(self.positions)

    # ------------------------------------------------------------------ state
    @property
    def frame(self) -> int:
        return self._frame

    def set_frame(self, t: int) -> None:
        """Show frame ``t`` (0-based) of the current trajectory."""
        with self._lock:
            T = len(self.positions)
            t = int(np.clip(t, 0, T - 1))
            self._frame = t
            pts = _subsample(self.positions[t], self.max_points)
            self._pred = self.server.scene.add_point_cloud(
                "/prediction", pts, np.asarray(PREDICTION_RGB, np.uint8), point_size=self.point_size, point_shape="circle",
                precision="float32", visible=bool(self.show_pred.value))
            show_truth = self.truth is not None and self.showing_fit and t < len(self.truth)
            if show_truth:
                self._truth = self.server.scene.add_point_cloud(
                    "/truth", self.truth[t], np.asarray(TRUTH_RGB, np.uint8), point_size=self.point_size * 0.8,
                    point_shape="circle", precision="float32", visible=bool(self.show_truth.value))
            elif self._truth is not None:
                self._truth.visible = False
            if self.show_splats.value and self.means is not None:
                self._splats = self.server.scene.add_gaussian_splats("/gaussians", self.means[t], self._covariances_at(t), self._rgb,
                                                                    self._opacity)
            elif self._splats is not None:
                self._splats.visible = False
            n_train = int(self.twin.meta["n_train"])
            what = ("fitted" if t < n_train else "future") if self.showing_fit else "re-simulated"
            self.status.content = f"t = {t * self.twin.frame_dt:.3f} s, frame {t}/{T - 1} ({what})"
        if int(self.frame_slider.value) != t:  # driven from Python: move the slider too
            self.frame_slider.value = t

    def drawn(self) -> dict:
        """What the scene holds now: counts of points per cloud, frame, whether it shows the fit."""
        return {"frame": self._frame, "prediction_points": 0 if self._pred is None else int(len(self._pred.points)),
                "truth_points": 0 if self._truth is None or not self._truth.visible else int(len(self._truth.points)),
                "showing_fit": self.showing_fit, "n_frames": int(len(self.positions))}

    def _covariances_at(self, t: int) -> np.ndarray:
        """(G, 3, 3) the Gaussians' covariances at frame ``t``: the twin's, deformed with the
        material (``A Sigma A^T``) when its Gaussians deform."""
        import torch

        from toolkit.twin.simulate import twin_deformations

        if t == 0 or "deform_index" not in self.twin.arrays:
            return self._cov
        A = twin_deformations(self.twin, torch.as_tensor(self.positions[[0, t]]))[1].numpy()
        return (A @ self._cov @ A.transpose(0, 2, 1)).astype(np.float32)

    def resimulate(self, params: Optional[dict] = None, v0: Optional[Sequence[float]] = None,
                   n_frames: Optional[int] = None) -> None:
        """Roll the twin out with changed parameters (physical units) / v0 (m/s) / frames and show it."""
        from toolkit.twin.simulate import simulate_twin

        traj = simulate_twin(self.twin, v0=v0, params=params, n_frames=n_frames, device=self.device)
        with self._lock:
            self.positions, self.means = traj.positions.numpy(), traj.means.numpy()
            self.showing_fit = False
            self.frame_slider.max = max(len(self.positions) - 1, 1)
        self.set_frame(0)

    def _resimulate_from_gui(self) -> None:
        params = {name: (10 ** h.value if is_log else h.value) for name, (h, is_log) in self.param_sliders.items()}
        try:
            self.resimulate(params=params, v0=list(self.v0_input.value), n_frames=int(self.frames_input.value))
        except Exception as err:  # noqa: BLE001 - shown in the page, the server keeps running
            self.status.content = f"simulation failed: {err}"

    def reset(self) -> None:
        """Back to the fitted trajectory (and the ground truth)."""
        with self._lock:
            self.positions, self.means = self.fitted
            self.showing_fit = True
            self.frame_slider.max = max(len(self.positions) - 1, 1)
        self.set_frame(0)

    def close(self) -> None:
        """Stop the server and the player thread."""
        self._stop = True
        self.server.stop()


def _free_port(host: str = "127.0.0.1") -> int:
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def serve_run(run_dir, host: str = "127.0.0.1", port: int = 8080, max_points: Optional[int] = 20000, device: str = "cpu",
              block: bool = True) -> TwinViewer:
    """Start the viewer on a run folder (its fitted twin, stored prediction and ground truth).

    With ``block`` (the CLI), serves until Ctrl-C; otherwise returns the running :class:`TwinViewer`.
    """
    from pathlib import Path

    from toolkit.pipeline import load_fitted_module
    from toolkit.twin.export import twin_from_module
    from toolkit.viewer import load_run_clouds

    run = Path(run_dir)
    twin = twin_from_module(load_fitted_module(run, device=device))
    clouds = load_run_clouds(run, device=device, max_points=None)
    means = None
    pred_file = run / "evaluation" / "prediction.npz"
    if pred_file.is_file():
        with np.load(pred_file) as z:
            means = z["means"]
    viewer = TwinViewer(twin, prediction=clouds.predicted.astype(np.float32), truth=clouds.truth, host=host, port=port,
                        max_points=max_points, device=device, name=run.name)
    if means is not None:
        viewer.fitted = (viewer.fitted[0], means)
        viewer.means = means
    if block:
        print(f"projo4d view: open {viewer.url} in a browser (Ctrl-C stops)", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            viewer.close()
    return viewer

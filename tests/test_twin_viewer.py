"""The browser viewer (viser): scene contents, the re-simulation playground, and a real headless browser."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from tests.test_twin import fitted_run  # noqa: F401 - the module-scoped fitted run of the twin tests

pytest.importorskip("viser", reason="the browser viewer needs the viewer extra (pip install 'projo4d[viewer]')")


def _viewer(fitted_run, **kw):  # noqa: F811
    from toolkit.twin.viewer import serve_run

    return serve_run(fitted_run, port=0, block=False, **kw)


def test_viewer_draws_prediction_truth_and_resimulates(fitted_run):  # noqa: F811
    v = _viewer(fitted_run)
    try:
        pred = np.load(fitted_run / "evaluation" / "prediction.npz")["positions"]
        d = v.drawn()
        assert d["prediction_points"] == pred.shape[1] and d["truth_points"] > 0 and d["n_frames"] == pred.shape[0]
        v.set_frame(pred.shape[0] - 1)
        assert np.allclose(v._pred.points, pred[-1], atol=1e-6)  # noqa: SLF001 - what is drawn is the prediction
        assert "future" in v.status.content and v.frame_slider.value == pred.shape[0] - 1
        v.show_splats.value = True  # the Gaussians, carried by the particles, as splats
        v.set_frame(pred.shape[0] - 1)
        means = np.load(fitted_run / "evaluation" / "prediction.npz")["means"][-1]
        assert v._splats is not None and v._splats.visible  # noqa: SLF001
        np.testing.assert_allclose(v.means[-1], means)
        v.show_splats.value = False
        # the playground: a new throw, 4 frames; the truth (of the fitted throw) is hidden then
        v.resimulate(v0=[0.0, 1.0, 0.0], n_frames=4)
        d = v.drawn()
        assert d["n_frames"] == 5 and not d["showing_fit"] and d["truth_points"] == 0
        v.set_frame(2)
        c = v.positions[2].astype(np.float64).mean(0) - v.positions[0].astype(np.float64).mean(0)
        t = 2 * v.twin.frame_dt
        assert c[1] == pytest.approx(1.0 * t - 0.5 * 9.8 * t * t, abs=2e-3)  # ballistic rise, m
        assert "re-simulated" in v.status.content
        v.reset()
        assert v.drawn()["showing_fit"] and v.drawn()["n_frames"] == pred.shape[0]
    finally:
        v.close()


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def _screenshot(url: str, path) -> np.ndarray:
    import imageio.v3 as iio

    cmd = [_chromium(), "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
           "--window-size=1280,720", "--virtual-time-budget=15000", f"--screenshot={path}", url]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return iio.imread(path)[..., :3].astype(int)


def _screenshot_until(url: str, path, ready, tries: int = 8) -> np.ndarray:
    """A screenshot once ``ready(img)`` holds: the page draws only after its websocket delivered the
    scene, which on a loaded machine can take longer than Chromium's virtual-time budget."""
    for _ in range(tries):
        img = _screenshot(url, path)
        if ready(img):
            break
    return img


def _view(img: np.ndarray) -> np.ndarray:
    """The 3D view of a screenshot: without the control panel (right 340 px) and the browser's
    software-WebGL notice (top left, which has an orange bar)."""
    view = img[:, : img.shape[1] - 340].copy()
    view[:150, :320] = 255
    return view


def _blue(img: np.ndarray) -> int:
    """Pixels of the ground truth's colour (TRUTH_RGB = 40, 90, 200, shaded)."""
    r, g, b = np.moveaxis(_view(img), -1, 0)
    return int(((b > 150) & (r < 110) & (g > 60) & (g < 150)).sum())


def _orange(img: np.ndarray) -> int:
    """Pixels of the prediction's colour (PREDICTION_RGB = 255, 110, 0, shaded) in the 3D view."""
    r, g, b = np.moveaxis(_view(img), -1, 0)
    return int(((r > 180) & (g > 75) & (g < 170) & (b < 50)).sum())


@pytest.mark.skipif(_chromium() is None, reason="needs chromium (Debian: apt-get install chromium; `make test` installs it)")
def test_viewer_page_draws_the_object_in_a_headless_browser(fitted_run, tmp_path):  # noqa: F811
    """Chromium loads the page, connects to the server and draws the predicted particles (WebGL, software)."""
    v = _viewer(fitted_run)
    try:
        shown = _screenshot_until(v.url, tmp_path / "shown.png", lambda img: _orange(img) > 300)
        v.show_pred.value = False
        v.set_frame(0)
        hidden = _screenshot_until(v.url, tmp_path / "hidden.png", lambda img: _blue(img) > 300)
    finally:
        v.close()
    assert shown.shape == (720, 1280, 3)
    assert _orange(shown) > 300, f"only {_orange(shown)} prediction-coloured pixels: the object is not drawn"
    assert _orange(hidden) < 0.05 * _orange(shown)  # those pixels are the prediction's
    assert _blue(hidden) > 300  # the ground truth, drawn where the prediction was


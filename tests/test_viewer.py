"""The particle viewer's static rendering (matplotlib) and its point-cloud helpers (numpy/scipy, no open3d)."""

from __future__ import annotations

import numpy as np
import pytest


def _clouds(T=4, n=300, n_train=3):
    from toolkit.viewer import RunClouds

    rng = np.random.default_rng(0)
    base = rng.random((n, 3)) * 0.1 + [0.0, 0.1, 0.0]
    pred = np.stack([base + [0.02 * t, -0.01 * t, 0.0] for t in range(T)])
    truth = [base + [0.021 * t, -0.01 * t, 0.001] for t in range(T)]
    return RunClouds(predicted=pred, truth=truth, n_train=n_train, name="synthetic")


def test_point_cloud_io_and_nearest_distances(tmp_path):
    from toolkit.viewer import nearest_distances, read_cloud, write_cloud

    pts = np.random.default_rng(1).random((500, 3))
    path = write_cloud(tmp_path / "c.ply", pts, colors=np.full((500, 3), 0.5))
    assert np.allclose(read_cloud(path), pts, atol=1e-6)
    d = nearest_distances(pts, pts + [0.0, 0.0, 0.01])
    assert d.shape == (500,) and d.max() <= 0.01 + 1e-9
    other = np.random.default_rng(2).random((200, 3))
    brute = np.sqrt(((pts[:, None, :] - other[None, :, :]) ** 2).sum(-1)).min(1)  # the slow, obvious twin
    assert np.allclose(nearest_distances(pts, other), brute)
    # colours survive as uchar RGB; other formats need the optional open3d extra
    from toolkit.data.ply import _parse_header

    data = path.read_bytes()
    _, elements, _ = _parse_header(data, path)
    assert [p for p, _ in elements[0][2]] == ["x", "y", "z", "red", "green", "blue"]
    with pytest.raises(ValueError, match="use a .ply suffix"):
        write_cloud(tmp_path / "c.pcd", pts)


def test_static_view_has_a_colour_bar_and_captions_outside_the_plots():
    """The error scale is the 95th percentile of the distances (cm on the bar); the caption band is blank picture-free."""
    import toolkit.viewer as viewer

    clouds = _clouds()
    _, scale = viewer._error_colors(clouds)
    d = np.concatenate([np.sqrt(((p[:, None] - g[None]) ** 2).sum(-1)).min(1) for p, g in zip(clouds.predicted, clouds.truth)])
    assert scale == pytest.approx(np.percentile(d, 95), rel=1e-9)
    (img,), _ = viewer.render_frames(clouds, [3], backend="matplotlib", size=(480, 240))
    right = img[:, int(0.87 * 480):]  # the colour bar: a column of saturated colours
    sat = right.max(-1).astype(int) - right.min(-1).astype(int)
    assert (sat > 100).sum() > 200
    top = img[: int(0.012 * 240) + 1]  # above the caption's text line: nothing drawn
    assert top.min() > 200


def test_matplotlib_render_and_auto_fallback(monkeypatch):
    import toolkit.viewer as viewer

    clouds = _clouds()
    images, backend = viewer.render_frames(clouds, [0, 3], backend="matplotlib", size=(320, 160))
    assert backend == "matplotlib" and len(images) == 2
    assert images[0].shape == (160, 320, 3) and images[0].dtype == np.uint8
    assert not np.array_equal(images[0], images[1])  # the particles moved
    monkeypatch.setattr(viewer, "open3d_offscreen_available", lambda timeout=60.0: False)
    _, backend = viewer.render_frames(clouds, [1], backend="auto", size=(200, 100))
    assert backend == "matplotlib"
    with pytest.raises(RuntimeError, match="offscreen renderer does not work"):
        viewer.render_frames(clouds, [1], backend="open3d")
    with pytest.raises(ValueError, match="out of range"):
        viewer.render_frames(clouds, [9], backend="matplotlib")

"""The particle viewer's offscreen rendering (matplotlib fallback) and its open3d point-cloud helpers."""

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
    from scipy.spatial import cKDTree

    other = np.random.default_rng(2).random((200, 3))
    assert np.allclose(nearest_distances(pts, other), cKDTree(other).query(pts)[0])


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

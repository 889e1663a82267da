"""Does the body fall at g? The frame-time and unit check from stage-0 motion (toolkit.physics.time_scale)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.physics_fixtures import fit_sim, tiny_scene
from toolkit.physics.time_scale import MIN_FRAMES, check_time_scale

G = np.array([0.0, -9.8, 0.0])
FPS = 24.0


def _track(n: int, rng: np.random.Generator, noise: float = 0.0, scale: float = 1.0, height: float = 0.8,
           v0=(0.5, 0.8, -0.2), y_jitter: np.ndarray | None = None) -> list[torch.Tensor]:
    """``n`` frames at 24 fps of 400 points around a centroid thrown from ``height`` m at ``v0`` m/s under g;
    ``noise`` m per point, ``y_jitter`` (n,) m added to each frame's height, lengths times ``scale``."""
    t = np.arange(n) / FPS
    c = np.array([0.0, height, 0.0]) + np.outer(t, v0) + 0.5 * np.outer(t * t, G)
    if y_jitter is not None:
        c[:, 1] += y_jitter
    tpl = np.random.default_rng(7).uniform(-0.04, 0.04, size=(400, 3))
    tpl -= tpl.mean(0)
    return [torch.as_tensor(scale * (ci + tpl + rng.normal(0.0, noise, size=tpl.shape))) for ci in c]


def _slow_vertical_acceleration(surfaces, times) -> float:
    """The obvious twin: the 3x3 normal equations of y = a + b t + c t^2 / 2, solved by Cramer's rule."""
    t = np.asarray(times, dtype=np.float64) - times[0]
    y = np.array([s.double().numpy()[:, 1].mean() for s in surfaces])
    cols = [np.ones_like(t), t, 0.5 * t * t]
    M = np.array([[float((u * w).sum()) for w in cols] for u in cols])
    r = np.array([float((u * y).sum()) for u in cols])
    Mc = M.copy()
    Mc[:, 2] = r
    return float(np.linalg.det(Mc) / np.linalg.det(M))


def test_a_consistent_clip_falls_at_g_and_matches_its_slow_twin():
    """Exact parabola, 8 frames at 24 fps: the ratio is 1 to 1e-9 and the implied frame rate 24 fps;
    with 3 mm noise per point the ratio stays within 0.03 of 1 and the fast fit matches its twin."""
    rng = np.random.default_rng(0)
    times = np.arange(8) / FPS
    exact = check_time_scale(_track(8, rng), times, G)
    assert exact is not None and exact.frames == list(range(8)) and exact.agrees
    assert exact.ratio == pytest.approx(1.0, abs=1e-9) and exact.fps_implied == pytest.approx(FPS, rel=1e-6)
    noisy_surfaces = _track(8, rng, noise=0.003)
    noisy = check_time_scale(noisy_surfaces, times, G)
    assert abs(noisy.ratio - 1.0) < 0.03 and noisy.agrees
    assert -noisy.acceleration[1] / 9.8 == pytest.approx(noisy.ratio, rel=1e-12)
    assert noisy.acceleration[1] == pytest.approx(_slow_vertical_acceleration(noisy_surfaces, times), rel=1e-9)
    assert "consistent" in noisy.to_dict()["message"]


@pytest.mark.parametrize("claimed_over_true", [0.8, 1.25])
def test_a_wrong_frame_rate_is_flagged_with_the_rate_that_fits(claimed_over_true):
    """Times claiming s x the true 24 fps stretch by 1/s: the body falls at s^2 g (0.64, 1.5625), the
    check disagrees and names the claimed rate and the true one (claimed / sqrt(ratio) = 24 fps)."""
    s = claimed_over_true
    times = np.arange(8) / (FPS * s)
    chk = check_time_scale(_track(8, np.random.default_rng(1)), times, G)
    assert chk.ratio == pytest.approx(s * s, rel=1e-9) and not chk.agrees
    assert chk.fps_claimed == pytest.approx(FPS * s) and chk.fps_implied == pytest.approx(FPS, rel=1e-6)
    msg = chk.to_dict()["message"]
    assert f"{FPS * s:.4g} fps" in msg and "24 fps would make it fall at g" in msg


def test_a_world_in_centimetres_is_flagged_as_a_unit_problem():
    chk = check_time_scale(_track(8, np.random.default_rng(2), scale=100.0), np.arange(8) / FPS, G, dx=2.0)
    assert chk.ratio == pytest.approx(100.0, rel=1e-9) and not chk.agrees
    assert "centimetres" in chk.to_dict()["message"]


def test_frames_after_ground_contact_are_left_out_and_too_few_give_none():
    """Thrown from 0.4 m downwards: the lowest point (4 cm below the centroid) enters the 1.5-cell band
    (3 cm at dx 0.02) after frame 4, so frames 0-4 are fitted and the ratio stays 1 although the later
    frames (which would bend the fit) lie on a ground-crossing parabola; from 0.1 m there are fewer than
    MIN_FRAMES free frames and no check; a body on the ground at frame 0 has none either."""
    rng = np.random.default_rng(3)
    times = np.arange(10) / FPS
    surfaces = _track(10, rng, height=0.4, v0=(0.3, -0.5, 0.0))
    for k in range(5, 10):  # from frame 5 on the body rests on the ground
        surfaces[k] = surfaces[k] - torch.tensor([0.0, float(surfaces[k][:, 1].min()), 0.0], dtype=surfaces[k].dtype)
    chk = check_time_scale(surfaces, times, G, dx=0.02)
    assert chk is not None and chk.frames == [0, 1, 2, 3, 4] and chk.ratio == pytest.approx(1.0, abs=1e-9)
    low = _track(10, rng, height=0.12, v0=(0.3, -0.5, 0.0))
    assert check_time_scale(low, times, G, dx=0.02) is None
    assert check_time_scale(surfaces[5:], times[5:], G, dx=0.02) is None
    assert MIN_FRAMES == 4


def test_residuals_widen_the_tolerance_only_with_two_or_more_degrees_of_freedom():
    """A track whose heights jitter by +-1.5 cm, with times claiming 0.85x the true rate (ratio 0.72):
    over 7 frames the residuals give a standard error large enough that the check cannot tell
    (agrees); over the first 4 (one degree of freedom) the residuals say little about the noise and
    the fixed tolerance decides (flagged)."""
    jitter = 0.015 * np.array([1, -1, 1, -1, 1, -1, 1])
    surfaces = _track(7, np.random.default_rng(4), height=1.0, y_jitter=jitter)
    times = np.arange(7) / (FPS * 0.85)
    seven = check_time_scale(surfaces, times, G, ground_height=None)
    assert abs(seven.ratio - 1.0) > 0.2 and 3 * seven.ratio_se > abs(seven.ratio - 1.0) and seven.agrees
    four = check_time_scale(surfaces[:4], times[:4], G, ground_height=None)
    assert abs(four.ratio - 1.0) > 0.2 and not four.agrees


def test_bad_arguments_are_refused_with_what_is_expected():
    s = _track(5, np.random.default_rng(5))
    with pytest.raises(ValueError, match="gravity must be non-zero"):
        check_time_scale(s, np.arange(5) / FPS, (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="one time per frame"):
        check_time_scale(s, [0.0, 0.1], G)
    with pytest.raises(ValueError, match="tolerance must be >= 0"):
        check_time_scale(s, np.arange(5) / FPS, G, tolerance=-1.0)


@pytest.fixture(scope="module")
def thrown_high(tmp_path_factory):
    """The tiny elastic box thrown from 0.6 m (all 5 training frames before contact), as generated and
    as a folder claiming 0.8x the true frame rate (toolkit.synthetic.variants)."""
    from toolkit.synthetic.variants import VariantSpec, make_variant

    root = tmp_path_factory.mktemp("time_scale")
    src = tiny_scene(root / "box", height=0.6)
    slow = make_variant(src, root / "box_fps08", VariantSpec(fps_scale=0.8))
    return src, slow


def test_the_module_and_the_summary_report_a_wrong_frame_rate(thrown_high):
    """Through InversePhysicsModule (the true body, the scene's own times): the generated clip falls
    at g within 5 %; the folder claiming 0.8x the rate falls at 0.64 g within 5 %, and the run's
    terminal summary carries a WARNING naming the frame rate that fits (24 fps within 5 %)."""
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.oracle import oracle_input
    from toolkit.run_summary import format_summary

    kw = dict(curriculum="S:1", sim=fit_sim(), renderer="warp", optimize_params=["E"])
    src, slow = thrown_high
    good = InversePhysicsModule(oracle_input(src, particle_spacing=0.02), **kw).time_scale
    bad = InversePhysicsModule(oracle_input(slow, particle_spacing=0.02), **kw).time_scale
    assert good is not None and good["agrees"] and abs(good["ratio"] - 1.0) < 0.05
    assert bad is not None and not bad["agrees"] and abs(bad["ratio"] - 0.64) < 0.05 * 0.64
    assert bad["fps_implied"] == pytest.approx(FPS, rel=0.05)
    summary = {"material": "neo_hookean", "curriculum": "S:1", "parameters": [], "future": {}, "timings_s": {},
               "time_scale": bad}
    text = format_summary(summary)
    assert "WARNING before ground contact" in text and "would make it fall at g" in text
    assert "WARNING" not in format_summary({**summary, "time_scale": good})

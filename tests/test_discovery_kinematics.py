"""The observed flight's shape and acceleration (toolkit.discovery.kinematics) and its use in the decision.

Analytic tracks at 24 fps with 1 mm of centroid noise (stage-0 centroids at full size move
by 2-3 mm between frames around a straight line): a parabola is "smooth" and its acceleration is
recovered, a straight throw is "straight", a bounce off a wall is a "kink" at the right frame.
The decision takes the preferred kind only among candidates the validation data cannot tell
apart.
"""

from __future__ import annotations

import numpy as np
import pytest

from toolkit.discovery.calibration import Thresholds
from toolkit.discovery.kinematics import (BEND_FACTOR, ObservedMotion, acceleration_start, body_force_partners,
                                          drag_start, fit_motion, loo_errors, preferred_candidates)
from toolkit.discovery.selection import decide

FPS = 24.0
G = np.array([0.0, -9.8, 0.0])


def _track(n: int, v0, extra, noise: float = 1e-3, seed: int = 0, wall_frame=None, rebound: float = -0.3):
    """Centroids (n, 3) of a throw from the origin at v0 (m/s) under gravity plus ``extra``
    (m/s^2); with ``wall_frame``, the horizontal x velocity is multiplied by ``rebound`` from
    that frame's time on (a wall met in flight)."""
    t = np.arange(n) / FPS
    a = G + np.asarray(extra, float)
    c = np.asarray(v0, float)[None] * t[:, None] + 0.5 * a[None] * t[:, None] ** 2
    if wall_frame is not None:
        tw = (wall_frame - 0.5) / FPS
        after = t > tw
        xw = v0[0] * tw + 0.5 * a[0] * tw ** 2
        vw = v0[0] + a[0] * tw
        c[after, 0] = xw + rebound * vw * (t[after] - tw)
    return c + np.random.default_rng(seed).normal(0.0, noise, c.shape), t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_constant_extra_acceleration_is_a_smooth_flight_and_is_measured(seed):
    """(-4, 0, 2) m/s^2 over 6 flight frames: shape "smooth"; the unexplained acceleration within
    0.8 m/s^2 per component and v0 within 0.05 m/s (the noise is 1 mm)."""
    c, t = _track(6, (1.0, 0.4, -0.45), (-4.0, 0.0, 2.0), seed=seed)
    fl = fit_motion(c, t, G)
    assert fl.shape == "smooth", fl.loo
    assert np.abs(fl.extra - [-4.0, 0.0, 2.0]).max() < 0.8, fl.extra
    assert np.abs(fl.v0 - [1.0, 0.4, -0.45]).max() < 0.05
    assert fl.loo["parabola"] * BEND_FACTOR <= fl.loo["line"]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_straight_throw_stays_straight(seed):
    """Gravity alone bends only the height: the horizontal track is "straight", and no
    candidate is preferred."""
    c, t = _track(6, (1.0, 0.4, -0.45), (0.0, 0.0, 0.0), seed=seed)
    fl = fit_motion(c, t, G)
    assert fl.shape == "straight", fl.loo
    assert preferred_candidates(fl, ["wall", "extra_acceleration", "ground_friction"]) == []


def test_a_wall_in_flight_is_a_kink_at_its_frame():
    """The x velocity reverses between frames 3 and 4: shape "kink", placed at frame 3 or 4."""
    c, t = _track(7, (1.5, 0.4, -0.45), (0.0, 0.0, 0.0), wall_frame=4)
    fl = fit_motion(c, t, G)
    assert fl.shape == "kink", fl.loo
    assert fl.kink_frame in (3, 4)
    assert preferred_candidates(fl, ["wall", "extra_acceleration", "ground_friction"]) == ["wall"]


def test_the_report_sentence_states_the_shape_and_the_numbers():
    from toolkit.discovery.kinematics import motion_sentence

    c, t = _track(7, (1.5, 0.4, -0.45), (0.0, 0.0, 0.0), wall_frame=4)
    fl = fit_motion(c, t, G)
    text = motion_sentence(fl.to_dict())
    assert "flight (frames 0-6" in text and f"kink at frame {fl.kink_frame}" in text
    assert f"line {1e3 * fl.loo['line']:.2f} mm" in text


def test_too_few_frames_give_no_flight():
    c, t = _track(4, (1.0, 0.4, -0.45), (-4.0, 0.0, 2.0))
    assert fit_motion(c, t, G) is None


def test_loo_is_zero_for_the_model_that_made_the_data():
    """Without noise the parabola predicts every left-out frame of a parabola (and the line every
    frame of a line) to rounding; the line misses a parabola's by millimetres."""
    t = np.arange(6) / FPS
    par = np.stack([1.0 * t - 2.0 * t ** 2, -0.45 * t + 1.0 * t ** 2], 1)
    e = loo_errors(t, par)
    assert e["parabola"] < 1e-9 and e["line"] > 1e-3
    lin = np.stack([1.0 * t, -0.45 * t], 1)
    assert loo_errors(t, lin)["line"] < 1e-9


def test_a_smooth_bend_prefers_the_forces_that_act_smoothly_in_its_phase():
    """In flight only the body forces act sideways; on a slide ground friction does too. A wall
    bends either abruptly."""
    names = ["wall", "air_drag", "ground_friction", "extra_acceleration"]
    fl = ObservedMotion(frames=[0, 1, 2, 3, 4], acceleration=np.zeros(3), extra=np.zeros(3), v0=np.zeros(3), shape="smooth")
    assert preferred_candidates(fl, names) == ["air_drag", "extra_acceleration"]
    fl.phase = "slide"
    assert preferred_candidates(fl, names) == ["air_drag", "ground_friction", "extra_acceleration"]
    fl.shape = "kink"
    assert preferred_candidates(fl, names) == ["wall"]
    assert preferred_candidates(None, ["wall"]) == []


def _validation(scores: dict[str, float]) -> dict:
    v = {"base": {"validation": 0.0, "fit": 0.0, "worst": 0.0, "control": False}}
    for n, s in scores.items():
        v[n] = {"validation": s, "fit": 0.1, "worst": 0.0, "control": False}
    return v


def test_the_preference_acts_only_among_tied_candidates():
    """Wall 0.169, extra acceleration 0.149 (3 strengths: 0.129 penalized), friction 0.140 (the
    medium extra-acceleration toss): tied. Parsimony alone names the wall; a smooth flight names
    the extra acceleration. A candidate that is not tied is never chosen by the preference."""
    thr = Thresholds(validation=0.06, fit=0.0, camera=0.1, per_parameter=0.01)
    dofs = {"wall": 1, "extra_acceleration": 3, "ground_friction": 1}
    val = _validation({"wall": 0.1688, "extra_acceleration": 0.1486, "ground_friction": 0.1396})
    assert decide(val, dofs, thr)[0] == "wall"
    win, kind, tied = decide(val, dofs, thr, prefer=["extra_acceleration", "air_drag"])
    assert (win, kind) == ("extra_acceleration", "physics") and set(tied) == {"wall", "ground_friction"}
    far = _validation({"wall": 0.2492, "extra_acceleration": 0.0275, "ground_friction": 0.1675})
    assert decide(far, dofs, thr, prefer=["extra_acceleration"])[0] == "wall"


class _Lib:
    """The few library attributes acceleration_start reads."""

    def __init__(self):
        names = ["v0.x", "v0.y", "v0.z", "mat.E", "extra_acceleration.ax", "extra_acceleration.ay",
                 "extra_acceleration.az"]
        self.index_of = {n: i for i, n in enumerate(names)}

    def clip(self, q):
        return np.clip(q, -100.0, 100.0)


def test_the_acceleration_start_is_the_observed_flight():
    """A smooth flight sets the extra acceleration and v0 to what it measured and keeps the
    rest; any other shape gives no start."""
    lib = _Lib()
    q = np.array([0.5, 0.3, -0.2, 4.0, 0.0, 0.0, 0.0])
    fl = ObservedMotion(frames=list(range(6)), acceleration=np.array([-4.0, -9.8, 2.0]), extra=np.array([-4.0, 0.0, 2.0]),
                    v0=np.array([1.0, 0.4, -0.45]), shape="smooth")
    q2 = acceleration_start(lib, q, fl)
    assert q2[:3].tolist() == [1.0, 0.4, -0.45] and q2[4:].tolist() == [-4.0, 0.0, 2.0] and q2[3] == 4.0
    fl.phase = "slide"  # a slide does not show the vertical component: no start
    assert acceleration_start(lib, q, fl) is None
    fl.phase, fl.shape = "flight", "kink"
    assert acceleration_start(lib, q, fl) is None


def test_the_drag_start_is_the_observed_drag_rate():
    """Air drag's second start: the linear rate at the force law's fitted rate, the quadratic at
    0, v0 at the flight's (a slide keeps the base v0); no start without a positive rate or an
    air-drag candidate."""
    lib = _Lib()
    lib.index_of.update({"air_drag.linear": 7, "air_drag.quadratic": 8})
    q = np.array([0.5, 0.3, -0.2, 4.0, 0.0, 0.0, 0.0, 0.0, 0.3])
    fl = ObservedMotion(frames=list(range(6)), acceleration=np.zeros(3), extra=np.zeros(3),
                        v0=np.array([1.0, 0.4, -0.45]), shape="smooth", drag_rate=2.5)
    q2 = drag_start(lib, q, fl)
    assert q2[:3].tolist() == [1.0, 0.4, -0.45] and q2[7] == 2.5 and q2[8] == 0.0 and q2[3] == 4.0
    fl.phase = "slide"
    assert drag_start(lib, q, fl)[:3].tolist() == [0.5, 0.3, -0.2]
    fl.drag_rate = 0.0
    assert drag_start(lib, q, fl) is None
    fl.drag_rate = 2.5
    assert drag_start(_Lib(), q[:7], fl) is None


def test_body_forces_are_confirmed_as_a_family():
    """A refit of one body force brings the other; on a slide ground friction belongs to the
    family too (in a flight it does not act); nothing is added without a member."""
    avail = ["wall", "extra_acceleration", "ground_friction", "air_drag", "timing"]
    assert body_force_partners(["extra_acceleration", "wall"], avail) == ["air_drag"]
    assert body_force_partners(["air_drag"], avail, "flight") == ["extra_acceleration"]
    assert body_force_partners(["air_drag", "extra_acceleration"], avail) == []
    assert body_force_partners(["wall", "ground_friction"], avail) == []
    assert body_force_partners(["extra_acceleration"], ["extra_acceleration", "wall"]) == []
    assert body_force_partners(["extra_acceleration", "wall"], avail, "slide") == ["air_drag", "ground_friction"]
    assert body_force_partners(["ground_friction"], avail, "slide") == ["extra_acceleration", "air_drag"]


@pytest.fixture(scope="module")
def toss_libraries(tmp_path_factory):
    """Library models of three tiny plasticine tosses (generated; oracle surfaces; the base model
    at the true material and throw, unfitted): a hidden extra acceleration (-4, 0, 2) m/s^2,
    nothing hidden, a wall at x = 0.17 m, a linear air drag of 2.5 /s. About 3 s each."""
    from toolkit.discovery.hidden import BASE_MATERIALS, SIZES, THROWS, HiddenScene
    from toolkit.discovery.library import LibraryModel
    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule

    root = tmp_path_factory.mktemp("kinematics")
    fit, base = SIZES["tiny"]["fit"], BASE_MATERIALS["plasticine"]
    out = {}
    for effect, level in (("extra_acceleration", "high"), ("none", "none"), ("wall", "high"), ("air_drag", "high")):
        hs = HiddenScene(effect, level, "plasticine", "toss", "tiny")
        inp = hs.physics_input(hs.generate(root / hs.name))
        module = InversePhysicsModule(inp, material="plasticine", initial_params=dict(base["params"]), optimize_params=[],
                                      v0_init=list(THROWS["toss"]["v0"]), curriculum=fit["curriculum"], renderer="warp",
                                      sim=SimConfig(dx=fit["dx"], substeps=fit["substeps"], auto_dt_halving=True,
                                                    boundary="slip"))
        out[effect] = LibraryModel(module)
    return out


@pytest.mark.usefixtures("one_torch_thread")
def test_observed_motion_of_generated_tosses(toss_libraries):
    """Through the generator, the oracle surfaces and the base prediction's ground contact: the
    tiny toss flies for frames 0-4 of its 6 training frames. The hidden extra acceleration bends
    the flight smoothly and is measured within 0.3 m/s^2 (v0 within 0.05 m/s); the null toss
    flies straight; the wall, met about frame 3, leaves too few frames after it for a kink and
    prefers nothing (the decision then falls back to parsimony)."""
    from toolkit.discovery.kinematics import observed_motion

    libs = toss_libraries
    frames = range(libs["none"].input.n_train)
    ea = observed_motion(libs["extra_acceleration"], libs["extra_acceleration"].q0, frames=frames)
    assert ea.frames == [0, 1, 2, 3, 4] and ea.phase == "flight" and ea.shape == "smooth"
    assert np.abs(ea.extra - [-4.0, 0.0, 2.0]).max() < 0.3, ea.extra
    assert np.abs(ea.v0 - [1.0, 0.4, -0.5]).max() < 0.05
    null = observed_motion(libs["none"], libs["none"].q0, frames=frames)
    assert null.frames == [0, 1, 2, 3, 4] and null.shape == "straight"
    wall = observed_motion(libs["wall"], libs["wall"].q0, frames=frames)
    assert preferred_candidates(wall, ["wall", "extra_acceleration"]) in ([], ["wall"])


@pytest.mark.usefixtures("one_torch_thread")
def test_a_drag_absorbed_by_the_base_fit_is_refitted_from_the_observed_rate(toss_libraries):
    """The tiny toss with a hidden linear drag of 2.5 /s: the observed track measures the rate
    within 0.3 /s. The base fit absorbs part of the drag into the throw, so the refit from the
    ranking's prediction (here no drag at all) stops at about half the rate (1.2 /s), while the
    refit from the observed rate ends nearer the truth. Both lower the objective below the base's.
    The valley is flat: the two ends differ by 0.4-0.5 % in objective, under the 1 % a second
    start needs to replace the first. So where along it the refit from the observed rate stops
    depends on rounding: 2.5 +- 0.5 /s on earlier CPUs, 3.06 on a 2-core Intel Xeon. The test
    asserts what the start is for (ending nearer the truth than the prediction's start, and within
    30 % of it), not a point of the flat valley. The decision between the two starts is the rule's:
    the second replaces the first exactly when it gains more than SECOND_START_MIN_GAIN, and the
    other start's objective is recorded either way."""
    from types import SimpleNamespace

    from toolkit.discovery.confirm import lm_refit
    from toolkit.discovery.kinematics import drag_start, observed_motion
    from toolkit.discovery.refits import SECOND_START_MIN_GAIN, refit_candidate

    lib = toss_libraries["air_drag"]
    motion = observed_motion(lib, lib.q0, frames=range(lib.input.n_train))
    assert motion.phase == "flight" and abs(motion.drag_rate - 2.5) < 0.3, motion.drag_rate
    base = lm_refit(lib, lib.q0, lib.base_names, "base", iterations=8)
    free = lib.base_names + lib.params_of("air_drag")
    lib.assign(base.q)
    from_rate = lm_refit(lib, drag_start(lib, base.q, motion), free, "air_drag", iterations=8)
    lib.assign(base.q)
    from_prediction = lm_refit(lib, base.q, free, "air_drag", iterations=8)  # base.q holds no drag
    assert from_rate.objective < base.objective and from_prediction.objective < base.objective
    rate, predicted_rate = (r.q[lib.index_of["air_drag.linear"]] for r in (from_rate, from_prediction))
    assert abs(rate - 2.5) < abs(predicted_rate - 2.5), (rate, predicted_rate)
    assert abs(rate - 2.5) < 0.3 * 2.5, from_rate.q
    score = SimpleNamespace(name="air_drag", predicted_strength={}, search=None)
    rf = refit_candidate(lib, None, {}, score, base, iterations=8, motion=motion)
    assert rf.objective < base.objective
    kept_second = rf.extra["start"] == "observed_drag_rate"
    first, second = ((rf.extra["other_start_objective"], rf.objective) if kept_second
                     else (rf.objective, rf.extra["other_start_objective"]))
    assert kept_second == (second < (1.0 - SECOND_START_MIN_GAIN) * first), rf.extra
    assert second == pytest.approx(from_rate.objective, rel=1e-6)


# ---------------------------------------------------------------------------- the force law

def _horizontal(n: int, kind: str, strength, v0=(1.5, -0.3), noise: float = 1.5e-3, seed: int = 0):
    """A horizontal centroid track (n, 2), m, at 24 fps: ``kind`` ``"drag"`` (linear, rate
    ``strength`` 1/s) or ``"constant"`` (acceleration ``strength``, m/s^2), with Gaussian noise."""
    t = np.arange(n) / FPS
    v0 = np.asarray(v0, float)
    if kind == "drag":
        y = v0[None] * (-np.expm1(-strength * t) / strength)[:, None]
    else:
        y = v0[None] * t[:, None] + 0.5 * np.asarray(strength, float)[None] * t[:, None] ** 2
    return t, y + np.random.default_rng(seed).normal(0.0, noise, y.shape)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_strong_constant_pull_is_told_from_a_drag(seed):
    """(-4, 2) m/s^2 against a 1.5 m/s slide over 8 frames with 1.5 mm of noise: the speed falls
    from 1.5 to 0.4 m/s, a drag would fade by as much, yet the pull stays constant; the parabola
    predicts left-out frames at least twice as well."""
    from toolkit.discovery.kinematics import force_law

    t, y = _horizontal(8, "constant", (-4.0, 2.0), seed=seed)
    law, loo, _ = force_law(t, y)
    assert law == "constant", loo
    assert loo["constant"] < 3e-3


@pytest.mark.parametrize("rate", [1.0, 2.5])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_drag_is_never_called_a_constant_pull(rate, seed):
    """A linear drag (1 and 2.5 /s, the hidden scenes' strengths) over the same 8 noisy frames:
    never "constant" (over so short a clip a drag may look like either)."""
    from toolkit.discovery.kinematics import force_law

    t, y = _horizontal(8, "drag", rate, seed=seed)
    assert force_law(t, y)[0] != "constant"


def test_a_clean_drag_is_a_drag_and_its_rate_is_measured():
    """Without noise over 12 frames the drag model is exact: law "drag", rate within 3 % of 3 /s
    (the scan's spacing), and the constant model's error is the drag's curvature change."""
    from toolkit.discovery.kinematics import force_law

    t, y = _horizontal(12, "drag", 3.0, noise=0.0)
    law, loo, k = force_law(t, y)
    assert law == "drag" and loo["drag"] < 0.2 * loo["constant"], loo
    assert abs(k - 3.0) < 0.09, k
    assert force_law(t[:4], y[:4])[0] == "either"  # too few frames to judge


def test_the_force_law_narrows_the_smooth_preference():
    """A constant pull drops air drag (friction stays on a slide); a fading one keeps air drag alone."""
    names = ["wall", "air_drag", "ground_friction", "extra_acceleration"]
    fl = ObservedMotion(frames=[0, 1, 2, 3, 4], acceleration=np.zeros(3), extra=np.zeros(3), v0=np.zeros(3),
                        shape="smooth", phase="slide", law="constant")
    assert preferred_candidates(fl, names) == ["ground_friction", "extra_acceleration"]
    fl.phase = "flight"
    assert preferred_candidates(fl, names) == ["extra_acceleration"]
    fl.law = "drag"
    assert preferred_candidates(fl, names) == ["air_drag"]
    fl.shape = "straight"  # the law alone prefers nothing
    assert preferred_candidates(fl, names) == []


def test_a_constant_pull_names_the_extra_acceleration_over_a_tied_drag():
    """The medium-strength slide with an extra acceleration (2026-11-27 record: extra acceleration
    0.19, air drag 0.13, tied): parsimony names air drag (2 strengths against 3); the constant
    pull names the extra acceleration. With law "either" parsimony still decides."""
    thr = Thresholds(validation=0.06, fit=0.0, camera=0.1, per_parameter=0.01)
    dofs = {"air_drag": 2, "extra_acceleration": 3}
    val = _validation({"extra_acceleration": 0.19, "air_drag": 0.13})
    fl = ObservedMotion(frames=list(range(1, 8)), acceleration=np.zeros(3), extra=np.zeros(3), v0=np.zeros(3),
                        shape="smooth", phase="slide")
    assert decide(val, dofs, thr, prefer=preferred_candidates(fl, list(val)))[0] == "air_drag"
    fl.law = "constant"
    win, _, tied = decide(val, dofs, thr, prefer=preferred_candidates(fl, list(val)))
    assert win == "extra_acceleration" and tied == ["air_drag"]


def test_the_law_is_reported():
    from toolkit.discovery.kinematics import fit_motion, force_law, motion_sentence

    t, y = _horizontal(8, "constant", (-4.0, 2.0))
    c = np.stack([y[:, 0], -0.5 * 9.8 * t ** 2, y[:, 1]], 1)
    fl = fit_motion(c, t, G)
    fl.law, fl.law_loo, fl.drag_rate = force_law(t, y)
    fl.law_frames = list(range(8))
    d = fl.to_dict()
    assert d["law"] == "constant" and set(d["law_loo"]) == {"constant", "drag"}
    text = motion_sentence(d)
    assert "frames 0-7" in text and "a constant pull" in text and "linear drag" in text

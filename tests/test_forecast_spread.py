"""The forecast spread (issue #20): how far the prediction moves across the parameters' intervals."""

from __future__ import annotations

import math

import pytest
import torch

from tests.physics_fixtures import TRUTH, V0, tiny_scene
from tests.uncertainty_scenes import toss_module_at_truth
from toolkit.physics.forecast_spread import describe_spread, forecast_spread
from toolkit.physics.oracle import oracle_input


@pytest.fixture(scope="module")
def toss(tmp_path_factory):
    """The falling box of test_physics at its true E and v0 (it reaches the ground at frame 2)."""
    return toss_module_at_truth(oracle_input(tiny_scene(tmp_path_factory.mktemp("toss")), particle_spacing=0.02))


def _state(m):
    return float(m.material_raw["E"].detach()), m.v0.detach().clone()


def test_before_contact_v0_moves_the_body_ballistically_and_the_material_not_at_all(toss):
    """In free flight a v0 changed by dv moves every particle by abs(dv) t (frame 1: t = 1/24 s);
    E moves nothing (within float32 rounding) until the body meets the ground, then tens of millimetres. The module's
    parameters are put back."""
    before = _state(toss)
    dt = float(toss.input.times[1] - toss.input.times[0])
    v = forecast_spread(toss, {"parameters": {"v0_x": {"low": V0[0] - 0.1, "high": V0[0] + 0.1}}})
    assert v["spread_mm"][0] == pytest.approx(0.0, abs=1e-9)
    assert v["spread_mm"][1] == pytest.approx(0.1 * dt * 1e3, rel=1e-4)
    assert v["per_parameter"]["v0_x"][0] > 0 and v["rollouts"] == 2
    e = forecast_spread(toss, {"parameters": {"E": {"low": TRUTH["E"] / 3, "high": TRUTH["E"] * 3}}})
    assert e["spread_mm"][1] == pytest.approx(0.0, abs=1e-3)  # float32 rounding: under a micrometre
    assert e["future_mm"] > 5.0 and e["train_mm"] > 5.0
    assert e["driver"]["parameter"] == "E" and e["driver"]["mm"] == pytest.approx(e["spread_mm"][-1])
    after = _state(toss)
    assert after[0] == before[0] and torch.equal(after[1], before[1])
    # the estimate's prediction handed in (as the pipeline hands in the evaluation's) gives the same spread
    with torch.no_grad():
        _, base = toss.simulate(toss.input.n_frames - 1, frozenset())
    given = forecast_spread(toss, {"parameters": {"v0_x": {"low": V0[0] - 0.1, "high": V0[0] + 0.1}}}, base=base.numpy())
    assert given["spread_mm"] == pytest.approx(v["spread_mm"], abs=1e-6)


def test_a_narrower_interval_spreads_the_future_less(toss):
    """E within a factor 1.5 of the truth moves the last frame less than E within a factor 3."""
    wide = forecast_spread(toss, {"parameters": {"E": {"low": TRUTH["E"] / 3, "high": TRUTH["E"] * 3}}})
    narrow = forecast_spread(toss, {"parameters": {"E": {"low": TRUTH["E"] / 1.5, "high": TRUTH["E"] * 1.5}}})
    assert 0 < narrow["spread_mm"][-1] < wide["spread_mm"][-1]


def test_no_uncertainty_no_spread_and_the_sentence_names_the_driver(toss):
    assert toss.uncertainty_result is None and forecast_spread(toss) is None  # never estimated: nothing to spread
    assert forecast_spread(toss, {"parameters": {}}) is None
    assert describe_spread(None) is None
    s = forecast_spread(toss, {"parameters": {"E": {"low": TRUTH["E"] / 3, "high": TRUTH["E"] * 3},
                                              "v0_x": {"low": V0[0] - 0.1, "high": V0[0] + 0.1}}})
    assert s["rollouts"] == 4 and set(s["per_parameter"]) == {"E", "v0_x"}
    text = describe_spread(s)
    assert f"{s['driver']['parameter']} at its interval's {s['driver']['end']} end" in text
    assert f"{s['future_mm']:.1f} mm" in text and math.isfinite(s["train_mm"])

"""The grid term of the intervals (toolkit.physics.grid_term): a finer grid's trajectory turned into
a parameter offset, the interval widened to cover it, and the grid check reused by the pipeline.

The offset is checked against a case with a known answer: a "finer grid" whose trajectory is the
fit grid's at a stiffer E (10^0.2 times the estimate) must give an offset of -0.2 decades in E (the
fit grid reproduces it 0.2 decades softer, so data fitted by the fit grid at E are fitted by that
"finer grid" at E / 10^0.2) and none in v0."""

from __future__ import annotations

import math

import pytest
import torch

import toolkit.physics.grid_check as grid_check
from tests.physics_fixtures import TRUTH, fit_sim, tiny_scene
from tests.uncertainty_scenes import toss_module_at_truth
from toolkit.physics.oracle import oracle_input
from toolkit.physics.uncertainty import estimate_uncertainty

SHIFT_DECADES = 0.2


@pytest.fixture(scope="module")
def toss_input(tmp_path_factory):
    return oracle_input(tiny_scene(tmp_path_factory.mktemp("toss")), particle_spacing=0.02)


def _stiffer_grid(sim, x0, v0, params, gravity, effect_params, n_frames):
    """Stands in for grid_shift: the "fine" trajectory is the fit grid's with E raised by SHIFT_DECADES."""
    coarse = sim.rollout(x0, v0, params, gravity=gravity, effect_params=effect_params, n_frames=n_frames)
    stiff = params.clone()
    stiff[..., sim.material.param_names.index("E")] *= 10 ** SHIFT_DECADES
    fine = sim.rollout(x0, v0, stiff, gravity=gravity, effect_params=effect_params, n_frames=n_frames)
    per_frame = (fine.positions - coarse.positions).norm(dim=-1).mean(1)
    return {"dx": sim.config.dx, "fine_dx": sim.config.dx / 2, "shift_m": float(per_frame[1:].mean()),
            "shift_per_frame_m": per_frame.tolist(), "substeps": coarse.substeps, "fine_substeps": fine.substeps,
            "positions": coarse.positions, "fine_positions": fine.positions}


def test_offset_of_a_known_shift_and_the_widened_interval(toss_input, monkeypatch):
    monkeypatch.setattr(grid_check, "grid_shift", _stiffer_grid)
    res = estimate_uncertainty(toss_module_at_truth(toss_input), prior_step=False).to_dict()
    E = res["parameters"]["E"]
    assert E["label"] == "determined"
    assert E["grid_offset"] == pytest.approx(-SHIFT_DECADES, abs=0.05)
    assert math.log10(E["grid_value"]) == pytest.approx(math.log10(TRUTH["E"]) - SHIFT_DECADES, abs=0.05)
    for c in "xyz":  # E alone explains the shift: v0 hardly moves (a few mm/s against its interval)
        v = res["parameters"][f"v0_{c}"]
        assert abs(v["grid_offset"]) < 0.25 * (v["data_high"] - v["data_low"])
    # the interval is the union of the data's interval around the estimate and the same one around the offset
    assert E["low"] < E["data_low"] and E["low"] < E["grid_value"] < E["high"]
    assert E["high"] == pytest.approx(E["data_high"], rel=1e-9)
    width = math.log10(E["data_high"]) - math.log10(E["data_low"])
    assert math.log10(E["high"]) - math.log10(E["low"]) == pytest.approx(width + abs(E["grid_offset"]), rel=1e-6)
    assert "half the spacing moves it" in E["note"]
    assert res["grid"]["fine_dx"] == pytest.approx(fit_sim().dx / 2)


def test_the_pipeline_check_reuses_the_uncertainty_grid_run_until_the_estimate_moves(toss_input, monkeypatch):
    m = toss_module_at_truth(toss_input)
    res = estimate_uncertainty(m, prior_step=False).to_dict()
    assert res["grid"]["frames"] == toss_input.n_train - 1 and res["grid"]["shift_m"] > 0

    def no_rollout(*args, **kwargs):
        raise AssertionError("simulated again although the estimate did not move")

    monkeypatch.setattr(grid_check, "grid_shift", no_rollout)
    assert grid_check.grid_convergence(m) == res["grid"]
    with torch.no_grad():
        m.v0[0] += 0.01
    with pytest.raises(AssertionError, match="simulated again"):
        grid_check.grid_convergence(m)


def test_without_the_grid_term_the_interval_is_the_data_one(toss_input):
    res = estimate_uncertainty(toss_module_at_truth(toss_input), prior_step=False, grid_term=False).to_dict()
    E = res["parameters"]["E"]
    assert res["grid"] == {} and E["grid_value"] is None and E["grid_offset"] == 0.0
    assert (E["low"], E["high"]) == (E["data_low"], E["data_high"])


def test_a_fine_grid_that_does_not_fit_leaves_the_data_interval(toss_input, monkeypatch):
    """A device out of memory on the finer grid costs the grid term, not the uncertainty."""
    from toolkit.mpm.config import GridTooLargeError

    for err in (RuntimeError("CUDA out of memory"), GridTooLargeError("grid of 2.1e9 nodes")):
        def fail(*args, err=err, **kwargs):
            raise err

        monkeypatch.setattr(grid_check, "grid_shift", fail)
        res = estimate_uncertainty(toss_module_at_truth(toss_input), prior_step=False).to_dict()
        E = res["parameters"]["E"]
        assert res["grid"]["skipped"].startswith(type(err).__name__)
        assert E["grid_value"] is None and (E["low"], E["high"]) == (E["data_low"], E["data_high"])

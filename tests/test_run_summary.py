"""The run summary lists every fitted quantity beside its truth: material parameters, v0 and the
strengths of fitted effects (a fitted ground friction was missing from the table and from
``summary.json`` until 2026-11-26; only ``physics/estimate.json`` had it)."""

from __future__ import annotations

from types import SimpleNamespace

from toolkit.run_summary import format_summary, run_summary


def _module(effects: dict, true_effects) -> SimpleNamespace:
    est = {"material": "neo_hookean", "params": {"E": 1.59e5, "nu": 0.26}, "v0": [-0.74, -0.19, -0.93],
           "gravity": [0.0, -9.8, 0.0], "effects": effects}
    unc = {"parameters": {"E": {"low": 7.6e4, "high": 9.0e5, "label": "determined"},
                          "ground_friction.mu": {"low": 0.1, "high": 0.5, "label": "weakly determined", "note": "n"}},
           "level": 0.9, "noise_std": 0.01, "dof": 10, "frames": 6, "rollouts": 12, "seconds": 1.0, "prior_step": 1.0}
    gt = {"params": {"E": 7.99e5, "nu": 0.40}, "v0": [-0.73, -0.18, -0.92], "effects": true_effects}
    return SimpleNamespace(
        estimate=lambda: est, uncertainty_result=unc,
        input=SimpleNamespace(ground_truth=gt, meta={}),
        curriculum=SimpleNamespace(schedule_string=lambda name: "XAS:100@3,XASM:150"),
        material=SimpleNamespace(registry_name="neo_hookean"))


def test_fitted_effects_are_rows_with_their_truth_and_interval():
    summary = run_summary(_module({"ground_friction": {"mu": 0.284}}, {"ground_friction": {"mu": 0.3}}), {}, {"physics_s": 1.0}, [])
    rows = {r["parameter"]: r for r in summary["parameters"]}
    assert list(rows) == ["E", "nu", "v0_x", "v0_y", "v0_z", "ground_friction.mu"]
    mu = rows["ground_friction.mu"]
    assert (mu["estimate"], mu["truth"], mu["low"], mu["high"], mu["label"]) == (0.284, 0.3, 0.1, 0.5, "weakly determined")
    assert rows["nu"]["label"] == "fixed (not fitted)"  # no interval for it in this result
    table = format_summary(summary)
    assert "ground_friction.mu" in table and "[0.1, 0.5]" in table


def test_an_effect_the_truth_lacks_has_no_truth():
    summary = run_summary(_module({"air_drag": {"linear": 0.5, "quadratic": 0.0}}, []), {}, {}, [])
    rows = {r["parameter"]: r for r in summary["parameters"]}
    assert rows["air_drag.linear"]["truth"] is None and rows["air_drag.quadratic"]["estimate"] == 0.0
    assert len(summary["parameters"]) == 7


def test_a_camera_the_masks_contradict_is_repeated_at_the_end():
    """The silhouette check's warning comes before stage 0; the closing table repeats it, and says
    nothing when the cameras agree."""
    summary = run_summary(_module({}, {}), {}, {}, [])
    msg = "camera 5's silhouettes disagree with the other fitting cameras'"
    table = format_summary({**summary, "silhouettes": {"disagree": True, "suspect": 5, "message": msg}})
    assert f"WARNING {msg}" in table
    assert "silhouettes" not in format_summary({**summary, "silhouettes": {"disagree": False, "message": "agree"}})


def test_the_starting_v0_and_its_free_flight_frames_are_kept():
    """The stage-0 ballistic estimate v0 started from is in ``summary.json`` with its free-flight frames,
    and the table says over which frames and why it stopped; a run without one says nothing."""
    module = _module({}, {})
    module.v0_estimate = {"v0": [-0.743, -0.219, -0.935], "x0": [0.0, 0.3, 0.0], "frames": [0, 1, 2, 3, 4, 5],
                          "method": "ballistic", "rms_residual": 0.002, "stop_reason": "ground contact at frame 6"}
    summary = run_summary(module, {}, {}, [])
    assert summary["v0_estimate"]["frames"] == [0, 1, 2, 3, 4, 5]
    table = format_summary(summary)
    assert ("v0 started at the stage-0 ballistic estimate (-0.743, -0.219, -0.935) m/s, fitted over frames 0-5 "
            "(6 frames; ground contact at frame 6)") in table
    plain = run_summary(_module({}, {}), {}, {}, [])
    assert plain["v0_estimate"] is None and "v0 started" not in format_summary(plain)


def test_where_v0_started_is_said_when_it_was_not_the_estimate():
    """Without a stage-0 estimate the table says why v0 started at zero and how a ``[S]`` stage
    resolved (the config's ``XA[S]M`` prints as the ``XASM`` it ran); with one, the estimate's line
    says that v0 was held."""
    module = _module({}, {})
    module.v0_origin = {"source": "no estimate", "rule": "fitted"}
    table = format_summary(run_summary(module, {}, {}, []))
    assert ("v0 started at zero: stage 0 gave fewer than 3 usable frames before contact for a ballistic estimate; "
            "the [S] stages fitted it\n") in table
    module.v0_origin = {"source": "given", "rule": None}
    assert "v0 started at the given v0_init\n" in format_summary(run_summary(module, {}, {}, []))
    module.v0_origin = {"source": "estimate", "rule": "held"}
    module.v0_estimate = {"v0": [-0.743, -0.219, -0.935], "x0": [0.0, 0.3, 0.0], "frames": [0, 1, 2, 3], "method": "ballistic",
                          "rms_residual": 0.002, "stop_reason": "ground contact at frame 4"}
    summary = run_summary(module, {}, {}, [])
    assert summary["v0_origin"] == {"source": "estimate", "rule": "held"}
    assert "(4 frames; ground contact at frame 4); the [S] stages held it at stage 1's value" in format_summary(summary)

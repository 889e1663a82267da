"""Holding v0 only when it was measured: ``[S]`` stages and progressive's ``hold_velocity="auto"``
(strategies.base.Stage.velocity_if_unmeasured, toolkit.physics.starting_state.velocity_start_curriculum)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from strategies import Stage, StrategyError, get_strategy
from strategies.schedule import parse_schedule
from tests.physics_fixtures import fit_sim, tiny_scene


@pytest.fixture(scope="module")
def tiny_input(tmp_path_factory):
    from toolkit.physics.oracle import oracle_input

    return oracle_input(tiny_scene(tmp_path_factory.mktemp("tiny_scene")), particle_spacing=0.02)


def test_schedule_string_round_trip_and_resolution():
    """``XA[S]M`` parses to a stage without S that carries the rule, prints back the same, and
    resolves to XAM (measured) or XASM (not); the symbolic strategy stays symbolic."""
    (st,) = parse_schedule("XA[S]M:150/3x20")
    assert st.groups == frozenset("XAM") and st.velocity_if_unmeasured and st.label() == "XA[S]M"
    auto = get_strategy("progressive", hold_velocity="auto")
    assert auto.schedule_string("neo_hookean") == "XAS:100@3/3x3,XA[S]M:150/3x20"
    assert get_strategy(auto.schedule_string("neo_hookean")).describe("neo_hookean") == \
        get_strategy("XAS:100@3/3x3,XA[S]M:150/3x20").describe("neo_hookean")
    held = auto.with_velocity_start(True)
    free = auto.with_velocity_start(False)
    assert held.schedule_string("neo_hookean") == get_strategy("progressive", hold_velocity=True).schedule_string("neo_hookean")
    assert free.schedule_string("neo_hookean") == get_strategy("progressive", hold_velocity=False).schedule_string("neo_hookean")
    assert get_strategy("progressive").schedule_string("neo_hookean") == auto.schedule_string("neo_hookean")  # the default
    assert [s.name for s in held.stages("sand")] == ["stage1:XAS", "stage2:XAM"]
    assert [s.name for s in free.stages("sand")] == ["stage1:XAS", "stage2:XASM"]
    assert auto.has_velocity_rule("sand") and not held.has_velocity_rule("sand") and not free.has_velocity_rule("sand")
    # both per-clip settings compose, in either order
    both = get_strategy("XAS:10@ff,XA[S]M:5")
    assert both.with_free_flight(6).with_velocity_start(False).schedule_string() == "XAS:10@6,XASM:5"
    assert both.with_velocity_start(True).with_free_flight(2).schedule_string() == "XAS:10@3,XAM:5"
    assert Stage.from_dict(parse_schedule("G[S]M:4")[0].to_dict()).velocity_if_unmeasured


@pytest.mark.parametrize("text, said", [
    ("XA[S]SM:5", "both always (S) and only when not measured"),
    ("[S]:5", "needs a parameter group besides '[S]'"),
    ("XA[M]:5", "only v0 can be conditional"),
    ("XA[S][S]M:5", "only v0 can be conditional"),
])
def test_malformed_conditional_velocity_is_named(text, said):
    with pytest.raises(StrategyError, match=said.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[").replace("]", r"\]")):
        parse_schedule(text)


def test_progressive_option_is_checked():
    with pytest.raises(ValueError, match="true, false or 'auto'"):
        get_strategy("progressive", hold_velocity="sometimes")
    with pytest.raises(StrategyError, match="must not also fit it always"):
        Stage(frozenset("XAS"), 3, velocity_if_unmeasured=True)


def test_module_holds_a_measured_v0_and_fits_one_that_starts_at_zero(tiny_input, tmp_path, caplog):
    """On the tiny falling box: with the stage-0 estimate (or a given v0) stage 2 of ``auto`` holds
    v0, which then does not move during it; when stage 0 lost the body after frame 1 (no estimate,
    v0 at zero) stage 2 fits v0 and moves it, and no "held at zero" warning is given. The saved
    hyperparameter keeps ``[S]``, so a resume resolves it again from the same estimate."""
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.fit import fit_physics
    from toolkit.physics.starting_state import velocity_held_after

    kw = dict(curriculum="XAS:1@3/3x2,XA[S]M:2/3x2", sim=fit_sim(), renderer="warp", optimize_params=["E"],
              material_init="given")
    measured = InversePhysicsModule(tiny_input, **kw)
    assert measured.v0_estimate is not None and measured.hparams["curriculum"] == kw["curriculum"]
    assert [s.groups for s in measured.stages] == [frozenset("XAS"), frozenset("XAM")]
    assert velocity_held_after(measured.stages) == 0
    given = InversePhysicsModule(tiny_input, v0_init=[0.5, -0.8, 0.3], **kw)
    assert given.stages[1].groups == frozenset("XAM")
    lost = dataclasses.replace(tiny_input, surfaces=[s if i < 2 else s[:0] for i, s in enumerate(tiny_input.surfaces)])
    with caplog.at_level(logging.INFO, logger="toolkit.physics.starting_state"):
        zero = InversePhysicsModule(lost, **kw)
    said = [r.getMessage() for r in caplog.records]
    assert not [m for m in said if "v0 starts at zero (stage 0 gave" in m]  # nothing to warn: stage 2 fits it
    assert "v0 starts at zero (no stage-0 estimate), so the [S] stages fit it" in said
    assert zero.v0_estimate is None and zero.v0.abs().max() == 0
    assert zero.stages[1].groups == frozenset("XASM") and velocity_held_after(zero.stages) is None
    asked_zero = InversePhysicsModule(tiny_input, v0_init="zero", **kw)
    assert asked_zero.stages[1].groups == frozenset("XASM")  # zero is a guess, not a measurement
    # where v0 started and how [S] resolved, for summary.json and the closing table
    assert [m.v0_origin for m in (measured, given, zero, asked_zero)] == [
        {"source": "estimate", "rule": "held"}, {"source": "given", "rule": "held"},
        {"source": "no estimate", "rule": "fitted"}, {"source": "zero", "rule": "fitted"}]
    assert InversePhysicsModule(lost, **{**kw, "curriculum": "XAS:1@3,XASM:2"}).v0_origin == {"source": "no estimate", "rule": None}

    def v0_through_stage2(m, out):
        fit_physics(m, out, checkpoint_every=0, accelerator="cpu", progress=False)
        v = np.array([[h[f"v0/{c}"] for c in "xyz"] for h in m.history])
        assert [h["stage"] for h in m.history] == [0, 1, 1]
        return v[0], v[-1]

    before, after = v0_through_stage2(measured, tmp_path / "measured")
    np.testing.assert_array_equal(before, after)
    before, after = v0_through_stage2(zero, tmp_path / "zero")
    assert np.abs(after - before).max() > 1e-4
    again = InversePhysicsModule(tiny_input, curriculum=measured.hparams["curriculum"], sim=fit_sim(), renderer="warp",
                                 optimize_params=["E"], material_init="given")
    assert again.curriculum.describe("neo_hookean") == measured.curriculum.describe("neo_hookean")


def test_a_checkpoint_from_before_the_rule_resumes_without_a_curriculum_warning(tiny_input, caplog):
    """Checkpoints written before ``velocity_if_unmeasured`` existed lack the key in their stages;
    resuming one with the same curriculum is not "a different curriculum", another one is."""
    from toolkit.physics import InversePhysicsModule

    m = InversePhysicsModule(tiny_input, curriculum="XAS:2@3,XASM:1", sim=fit_sim(), renderer="warp", optimize_params=["E"],
                             material_init="given")
    ckpt: dict = {}
    m.on_save_checkpoint(ckpt)
    for st in ckpt["projo4d"]["curriculum"]:
        del st["velocity_if_unmeasured"]
    with caplog.at_level(logging.WARNING, logger="toolkit.physics.module"):
        m.on_load_checkpoint(ckpt)
    assert not [r for r in caplog.records if "different curriculum" in r.getMessage()]
    ckpt["projo4d"]["curriculum"][1]["groups"] = "XAM"
    with caplog.at_level(logging.WARNING, logger="toolkit.physics.module"):
        m.on_load_checkpoint(ckpt)
    assert [r for r in caplog.records if "different curriculum" in r.getMessage()]

"""Strategies: the paper's schedules, the schedule-string language, the registry and class_path use."""

from __future__ import annotations

import pytest

from strategies import STRATEGIES, Stage, StrategyError, get_strategy
from strategies.schedule import format_stage, parse_schedule
from toolkit.registry import UnknownNameError


def _active(strategy, material):
    """Per-iteration (groups, window, batch, losses) of a whole curriculum."""
    out = []
    for step in range(strategy.total_iterations(material)):
        s = strategy.stage_at(step, material).stage
        out.append(("".join(g for g in "XASM" if g in s.groups), s.frames, (s.cameras_per_step, s.frames_per_step), s.losses))
    return out


@pytest.mark.parametrize("material,stage2", [("neo_hookean", 150), ("sand", 150), ("newtonian", 250),
                                              ("non_newtonian", 350), ("plasticine", 300)])
def test_progressive_is_projo4d(material, stage2):
    paper = get_strategy("progressive", hold_velocity=False)
    steps = _active(paper, material)
    assert len(steps) == 100 + stage2  # paper appendix: Stage 1 = 100, Stage 2 per material
    assert steps[:100] == [("XAS", 3, (3, 3), ("image", "geometry"))] * 100
    assert steps[100:] == [("XASM", None, (3, 20), ("image", "geometry"))] * stage2
    # the default differs from the paper in one thing: stage 2 holds v0 when stage 0 measured it
    default = get_strategy("progressive")
    assert default.options["hold_velocity"] == "auto" and default.has_velocity_rule(material)
    assert default.schedule_string(material) == f"XAS:100@3/3x3,XA[S]M:{stage2}/3x20"
    assert _active(default.with_velocity_start(False), material) == steps
    assert _active(default.with_velocity_start(True), material) == _active(get_strategy("progressive", hold_velocity=True), material)


def test_progressive_can_hold_v0_after_stage_1():
    held = get_strategy("progressive", hold_velocity=True)
    steps = _active(held, "newtonian")
    assert steps[:100] == [("XAS", 3, (3, 3), ("image", "geometry"))] * 100  # v0 fitted before contact
    assert steps[100:] == [("XAM", None, (3, 20), ("image", "geometry"))] * 250  # then held with the material free
    assert [s.name for s in held.stages("newtonian")] == ["stage1:XAS", "stage2:XAM"]
    # the same curriculum as the schedule string a benchmark could pass by hand
    assert _active(get_strategy("XAS:100@3/3x3,XAM:250/3x20"), "newtonian") == steps
    with pytest.raises(ValueError, match="hold_velocity must be true, false or 'auto' .*, got 'yes'"):
        get_strategy("progressive", hold_velocity="yes")


def test_free_flight_window_is_set_per_clip():
    """``early_frames="free_flight"`` (``@ff``): the window stays symbolic until the fit sets it from
    the clip (at least the paper's 3 frames); the strategy it came from is unchanged."""
    held = get_strategy("progressive", early_frames="free_flight", hold_velocity=True)
    assert held.schedule_string("sand") == "XAS:100@ff/3x3,XAM:150/3x20" and held.has_free_flight_window("sand")
    six = held.with_free_flight(6)
    assert _active(six, "sand")[:100] == [("XAS", 6, (3, 3), ("image", "geometry"))] * 100
    assert six.schedule_string("sand") == "XAS:100@6/3x3,XAM:150/3x20" and not six.has_free_flight_window("sand")
    assert [s.name for s in six.stages("sand")] == ["stage1:XAS", "stage2:XAM"]
    assert held.stages("sand")[0].frames == "free_flight"
    assert held.with_free_flight(2).stages("sand")[0].frames == 3  # never fewer than the paper's first frames
    assert held.with_free_flight(None).stages("sand")[0].frames == 3  # no estimate, or on the ground at frame 0
    # the frames a stage sees of a clip's 14 training frames: a symbolic window counts as all (its upper bound)
    assert [s.window(14) for s in held.stages("sand")] == [14, 14] and [s.window(14) for s in six.stages("sand")] == [6, 14]
    assert six.stages("sand")[0].window(4) == 4
    s = get_strategy("XA:5,S:10@ff/3x3~geo,M:5")
    assert s.schedule_string() == "XA:5,S:10@ff/3x3~geo,M:5" and s.stage_at(5).stage.label() == "S@ff"
    assert s.with_free_flight(7).stage_at(5).stage.frames == 7 and s.with_free_flight(7).stage_at(0).stage.frames is None
    assert get_strategy("sequential", early_frames="free_flight").stages("sand")[0].frames == "free_flight"
    assert [x.label() for x in get_strategy("cyclic", early_frames="free_flight").stages("sand")][:3] == ["XA", "S@ff", "M"]
    with pytest.raises(StrategyError, match="positive integer, None \\(all\\) or 'free_flight', got 'ff'"):
        get_strategy("progressive", early_frames="ff").stages("sand")


def test_sequential_is_gic():
    steps = _active(get_strategy("sequential", appearance_iterations=500), "plasticine")
    assert steps[:100] == [("S", 3, (3, 3), ("geometry",))] * 100  # velocity from the geometric loss, first frames
    assert steps[100:400] == [("M", None, (3, 20), ("image", "geometry"))] * 300  # material, Gaussians frozen
    assert steps[400:] == [("A", None, (1, 1), ("image",))] * 500  # appearance refinement
    assert get_strategy("sequential").stages("plasticine")[-1].iterations == 40_000  # GIC's Stage 3


def test_joint_has_the_same_budget():
    for material in ("neo_hookean", "non_newtonian"):
        joint = _active(get_strategy("joint"), material)
        assert set(joint) == {("XASM", None, (3, 20), ("image", "geometry"))}
        assert len(joint) == get_strategy("progressive").total_iterations(material)


def test_cyclic_patterns_of_table_7():
    a = get_strategy("cyclic")  # (XA-S-M)x4-A
    assert [s.label() for s in a.stages("neo_hookean")] == ["XA", "S@3", "M"] * 4 + ["A"]
    b = get_strategy("cyclic", pattern="XA-(S-M-A)xN")
    assert [s.label() for s in b.stages("neo_hookean")] == ["XA"] + ["S@3", "M", "A"] * 4
    for s in (a, b):  # constant total budget (250 for elastic), split evenly
        assert abs(s.total_iterations("neo_hookean") - 250) < len(s.stages("neo_hookean"))
    with pytest.raises(StrategyError, match="cyclic pattern must be one of"):
        get_strategy("cyclic", pattern="S-M")


def test_schedule_strings_round_trip_and_expand_repeats():
    stages = parse_schedule("SG:100@4, SMG:150")
    assert [format_stage(s) for s in stages] == ["XAS:100@4", "XASM:150"]
    s = get_strategy("XA:50,(S:25@3/3x3~geo,M:25)x2,A:10~img")
    assert s.schedule_string() == "XA:50,S:25@3/3x3~geo,M:25,S:25@3/3x3~geo,M:25,A:10~img"
    assert s.total_iterations() == 160
    assert s.stage_at(0).stage.label() == "XA" and s.stage_at(50).stage.losses == ("geometry",)
    assert s.stage_at(159).stage.losses == ("image",)
    for name in ("progressive", "sequential", "joint", "cyclic"):
        st = get_strategy(name)
        again = get_strategy(st.schedule_string("sand"))
        assert [x.to_dict() | {"name": ""} for x in again.stages()] == [x.to_dict() | {"name": ""} for x in st.stages("sand")]


@pytest.mark.parametrize("text,pattern", [
    ("", "empty schedule string"),
    ("XAQ:10", r"unknown group letter\(s\) \['Q'\]"),
    ("XAS", r"missing ':ITERATIONS'"),
    ("S:0", "needs at least 1 iteration"),
    ("(S:10,M:10)", r"must be followed by a repeat count 'xN'"),
    ("(S:10,M:10", r"missing '\)'"),
    ("(S:10,M:10x2", r"malformed stage 'M:10x2'"),
    ("S:10@0", "frame window must be >= 1"),
    ("S:10@fly", "WINDOW a frame count or 'ff'"),
    ("S:10,,M:5", "malformed stage ''"),
])
def test_malformed_schedules_give_clear_errors(text, pattern):
    with pytest.raises(StrategyError, match=pattern):
        parse_schedule(text)


def test_unknown_names_and_options():
    with pytest.raises(UnknownNameError, match=r"unknown strategy 'progresive'. Did you mean 'progressive'\?"):
        get_strategy("progresive")
    with pytest.raises(TypeError):
        get_strategy("progressive", stage3_iterations=5)
    with pytest.raises(StrategyError, match="unknown parameter group 'Q'"):
        Stage("XQ", 10)
    with pytest.raises(StrategyError, match="iterations >= 1"):
        Stage("X", 0)
    assert set(STRATEGIES.names()) >= {"progressive", "sequential", "joint", "cyclic", "schedule"}


def test_user_strategy_by_class_path_and_lr_progress():
    from tests.custom_strategy import VelocityThenAll

    s = get_strategy(VelocityThenAll, warmup=4, rest=6)
    assert s.schedule_string() == "S:4@2,XASM:6"
    # a group's learning-rate schedule runs over the iterations where it is active
    assert s.group_active_steps("S") == 10 and s.group_active_steps("M") == 6
    assert s.group_progress("M", 7) == 3 and s.group_progress("S", 7) == 7

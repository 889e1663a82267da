"""The coarse global search of material parameters before gradient descent (issue #20)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from materials import get_material
from materials.base import MaterialError, MaterialParam, default_lr
from tests.physics_fixtures import TRUTH, V0, fit_sim, tiny_scene
from toolkit.physics import InversePhysicsModule
from toolkit.physics.coarse_search import coarse_search, score_frames, search_and_apply, search_axis
from toolkit.physics.oracle import oracle_input
from toolkit.physics.rates import observed_speed, velocity_rate


@pytest.fixture(scope="module")
def tiny_input(tmp_path_factory):
    root = tiny_scene(tmp_path_factory.mktemp("search_scene"))
    return oracle_input(root, particle_spacing=0.02)


def _module(inp, **kw):
    kw.setdefault("optimize_params", ["E"])
    kw.setdefault("v0_init", list(V0))
    return InversePhysicsModule(inp, curriculum="XASM:1", sim=fit_sim(), renderer="warp", **kw)


def test_search_axes_and_frames_follow_the_parameters():
    E = get_material("neo_hookean").param("E")
    assert search_axis(E) == (True, 3.5, 6.5, 4)  # one point per decade over 10^3.5 .. 10^6.5 Pa
    log_axis, lo, hi, n = search_axis(get_material("sand").param("friction_angle"))
    assert (log_axis, lo, hi, n) == (False, 10.0, 50.0, 5)
    assert search_axis(MaterialParam("a", 0.5, "tanh", low=0.0, high=1.0, search=(0.1, 0.9)))[1:] == (0.1, 0.9, 5)
    nu = get_material("neo_hookean").param("nu")
    assert search_axis(nu, (0.3, 0.49))[1:] == (0.3, 0.45, 5)  # a narrowed fit range narrows the sweep
    assert search_axis(nu, (0.0, 0.49))[1:] == (0.05, 0.45, 5)  # the default range contains the sweep
    assert search_axis(E, (10**4.5, 1e12))[1:3] == pytest.approx((4.5, 6.5))
    with pytest.raises(ValueError, match="'k' has no search range"):
        search_axis(MaterialParam("k", 100.0, "log10"))  # not searched: keeps its guess
    assert score_frames(9) == [1, 3, 6, 8] and score_frames(5, 4) == [1, 2, 3, 4] and score_frames(1) == [0]
    with pytest.raises(MaterialError, match="search range"):
        MaterialParam("k", 1.0, "log10", search=(10.0, 1.0))


def test_learning_rates_follow_the_transforms():
    """0.1 decade per step for log10 parameters, 1 % of the valid range for bounded ones."""
    for name in ("neo_hookean", "plasticine", "newtonian", "non_newtonian", "sand"):
        for p in get_material(name).params:
            expected = 0.1 if p.transform == "log10" else 0.01 * (p.high - p.low)
            assert p.lr == pytest.approx(expected) == default_lr(p.transform, p.low, p.high), (name, p.name)
    assert get_material("neo_hookean").param("nu").lr == pytest.approx(0.0148)
    assert MaterialParam("x", 1.0, "log10", lr=0.5).lr == 0.5  # an explicit rate wins


def test_velocity_rate_scales_with_the_observed_motion():
    """A centroid moving at 2 m/s for 4 frames of 0.05 s: observed speed 2, rate 0.05 * 2 = 0.1 m/s;
    the same motion 10x slower gets the 0.02 m/s floor."""
    base = torch.rand(50, 3)
    frames = [base + torch.tensor([2.0 * 0.05 * t, 0.0, 0.0]) for t in range(5)]
    assert observed_speed(frames, 0.05, 5) == pytest.approx(2.0, rel=1e-6)
    assert velocity_rate(frames, 0.05, 5) == pytest.approx(0.1, rel=1e-6)
    slow = [base + (f - base) / 10 for f in frames]
    assert velocity_rate(slow, 0.05, 5) == 0.02
    assert observed_speed([base], 0.05, 1) == 0.0


def test_search_matches_a_brute_force_grid_and_starts_the_fit_there(tiny_input, tmp_path):
    """E alone, oracle geometry, true v0: the coarse-to-fine search (4 grid points + 2 halvings)
    lands on the minimum of an exhaustive sweep at its finest step (0.25 decade) over the same
    range, within 0.3 decades of the truth (3e4 Pa) from the default guess 10^5.5 Pa; the module
    then starts there and the uncertainty prior is centred there too."""
    m = _module(tiny_input)
    stage = m.stages[0]
    result = coarse_search(m, stage)
    assert result["start"]["E"] == pytest.approx(10**5.5, rel=1e-5) and result["frames"] == [1, 2, 3, 4]
    assert result["rollouts"] <= 8 and result["best_loss"] <= result["start_loss"]
    best = math.log10(result["best"]["E"])
    assert abs(best - math.log10(TRUTH["E"])) < 0.3

    # the slow, obvious twin: every quarter decade over the range, same loss, pick the smallest
    twin = _module(tiny_input)
    losses = {}
    for c in np.arange(3.5, 6.5 + 1e-9, 0.25):
        raw = twin.material.param("E").to_raw(10.0**c)
        twin.material_raw["E"].data.copy_(raw)
        with torch.no_grad():
            x0 = twin.particles0 + twin.particle_offset
            out = twin.simulator.rollout(x0, twin.v0, twin.material_params(), gravity=twin.gravity,
                                         effect_params=twin.effect_params, n_frames=4)
            twin._cached_positions = (x0, out.positions)
            import dataclasses

            probe = dataclasses.replace(stage, groups=frozenset())
            losses[round(c, 2)] = float(twin.losses(probe, list(twin.input.train_cameras), result["frames"])["total"])
            twin._cached_positions = None
    brute = min(losses, key=losses.get)
    assert best == pytest.approx(brute, abs=1e-6), (losses, result["points"])

    applied = search_and_apply(m, stage, folder=tmp_path)
    assert m.estimate()["params"]["E"] == pytest.approx(applied["best"]["E"], rel=1e-5)
    assert float(m.material_raw_fixed[0]) == pytest.approx(best, abs=1e-5)  # the prior's centre
    saved = json.loads((tmp_path / "material_search.json").read_text())
    assert saved["best"] == pytest.approx(applied["best"]) and len(saved["points"]) == saved["rollouts"]


def test_failed_rollouts_score_inf_and_leave_the_substeps_alone(tiny_input, monkeypatch):
    """A candidate whose rollout fails is recorded with its reason and never chosen; a dt-halving
    floor raised during the search is put back."""
    from toolkit.mpm.config import CFLError

    m = _module(tiny_input)
    sim = m.simulator
    real = sim.rollout

    def rollout(x0, v0, params, **kw):
        sim.substeps_floor = 999
        if float(params[0]) > 1e6:
            raise CFLError("CFL violated (test)")
        return real(x0, v0, params, **kw)

    monkeypatch.setattr(sim, "rollout", rollout)
    result = coarse_search(m, m.stages[0])
    failed = [p for p in result["points"] if p["params"]["E"] > 1e6]
    assert failed and all(p["loss"] is None and "CFLError" in p["note"] for p in failed)
    assert result["best"]["E"] < 1e6 and sim.substeps_floor == 0
    json.dumps(result, allow_nan=False)  # JSON-ready: no inf


def test_search_runs_once_at_the_first_material_iteration(tiny_input, tmp_path):
    """Default material_init='search' runs before the first M step only (not in XAS, not again);
    'given' keeps the guess; a wrong value is refused."""
    from toolkit.physics.fit import fit_physics

    m = InversePhysicsModule(tiny_input, curriculum="XAS:2@3,XASM:2", sim=fit_sim(), renderer="warp",
                             optimize_params=["E"])
    fit_physics(m, tmp_path / "a", checkpoint_every=0, accelerator="cpu", progress=False)
    rec = json.loads((tmp_path / "a" / "material_search.json").read_text())
    assert rec["iteration"] == 2 and m.material_search["best"] == rec["best"]
    assert [h["param/E"] for h in m.history[:2]] == pytest.approx([10**5.5] * 2, rel=1e-5)
    assert abs(math.log10(m.history[2]["param/E"]) - math.log10(rec["best"]["E"])) < 0.11  # one Adam step of 0.1 decade
    g = InversePhysicsModule(tiny_input, curriculum="XASM:1", sim=fit_sim(), renderer="warp", optimize_params=["E"],
                             material_init="given")
    fit_physics(g, tmp_path / "b", checkpoint_every=0, accelerator="cpu", progress=False)
    assert g.material_search is None and not (tmp_path / "b" / "material_search.json").exists()
    with pytest.raises(ValueError, match="material_init must be one of 'search', 'search_joint', 'given'"):
        InversePhysicsModule(tiny_input, material_init="grid")


def test_the_product_grid_starts_paths_at_its_lowest_local_minima():
    """``joint_yield``'s first sweep: every point of the first x yield grid is scored once, and the
    paths start at the lowest 4-neighbour local minima (here two basins, 0.0 at (1, 3) and 0.5 at
    (4, 0)), the other coordinates left as they were."""
    from toolkit.physics.coarse_search import _grid_minima

    def loss(a: float, b: float) -> float:
        return min((a - 1) ** 2 + (b - 3) ** 2, 0.5 + (a - 4) ** 2 + b**2)

    scored = []

    def evaluate(coords: dict, path: int) -> float:
        scored.append((coords["a"], coords["b"], path))
        return loss(coords["a"], coords["b"])

    grid_a, grid_b = np.arange(5.0), np.arange(4.0)
    origins = _grid_minima(evaluate, {"a": 0.0, "b": 0.0, "c": 7.0}, "a", grid_a, "b", grid_b, 2)
    assert origins == [{"a": 1.0, "b": 3.0, "c": 7.0}, {"a": 4.0, "b": 0.0, "c": 7.0}]
    assert sorted(scored) == sorted((a, b, 0) for a in grid_a for b in grid_b)
    assert _grid_minima(evaluate, {"a": 0.0, "b": 0.0, "c": 7.0}, "a", grid_a, "b", grid_b, 1) == origins[:1]


def test_the_joint_yield_option_leaves_a_material_without_a_yield_surface_alone(tiny_input):
    """Elastic E and nu: no yield parameter to pair with, so ``joint_yield`` searches exactly as the
    default does (the same points, the same pick)."""
    m = _module(tiny_input, optimize_params=["E", "nu"])
    plain, joint = coarse_search(m, m.stages[0]), coarse_search(m, m.stages[0], joint_yield=True)
    assert joint["best"] == plain["best"] and [p["params"] for p in joint["points"]] == [p["params"] for p in plain["points"]]


def test_search_joint_sweeps_the_product_grid_of_the_first_and_the_yield_parameter(tiny_input, tmp_path):
    """``material_init="search_joint"`` on a plasticine fit: the search before the first M step scores
    every point of E's grid x (tau_Y's grid plus its guess) at the fitted nu, records
    ``joint_yield``, picks the default's point or a grid path's end that beat it on the window, and
    the fit starts there; ``"search"`` sweeps E at the guess of tau_Y only."""
    from toolkit.physics.coarse_search import search_axis
    from toolkit.physics.fit import fit_physics

    def fit(init: str, folder):
        m = InversePhysicsModule(tiny_input, material="plasticine", curriculum="XASM:1", sim=fit_sim(),
                                 renderer="warp", optimize_params=["E", "yield_stress"], v0_init=list(V0),
                                 material_init=init)
        fit_physics(m, folder, checkpoint_every=0, accelerator="cpu", progress=False)
        return m, json.loads((folder / "material_search.json").read_text())

    def scored_pairs(record) -> set:
        return {(round(math.log10(p["params"]["E"]), 4), round(math.log10(p["params"]["yield_stress"]), 4))
                for p in record["points"]}

    m, rec = fit("search_joint", tmp_path / "joint")
    mat = m.material
    _, e_lo, e_hi, e_n = search_axis(mat.param("E"))
    _, y_lo, y_hi, y_n = search_axis(mat.param("yield_stress"))
    guess = math.log10(mat.param("yield_stress").default)
    rows = np.unique(np.append(np.linspace(y_lo, y_hi, y_n), guess))
    scored = scored_pairs(rec)
    grid = {(round(float(a), 4), round(float(b), 4)) for a in np.linspace(e_lo, e_hi, e_n) for b in rows}
    assert rec["joint_yield"] is True and grid <= scored
    ends = [p["params"] for p in rec["paths"]] + [rec["start"]]
    assert any(all(math.isclose(rec["best"][k], e[k], rel_tol=1e-6) for k in e) for e in ends)
    default_pick = min([rec["start_loss"]] + [p["loss"] for p in rec["paths"] if p["origin"] == "line"])
    grid_window = [p["window_loss"] for p in rec["paths"] if p["origin"] == "grid"]
    if rec["best_loss"] != pytest.approx(default_pick, rel=1e-9):  # a grid path won: by more than 1 % on the window
        assert grid_window and rec["best_window_loss"] == min(grid_window)
    assert abs(math.log10(m.history[0]["param/E"] / rec["best"]["E"])) < 0.11  # the pick, then one Adam step
    _, plain = fit("search", tmp_path / "plain")
    first_sweep = {(a, b) for a, b in grid if b == round(guess, 4)}
    assert plain["joint_yield"] is False and first_sweep <= scored_pairs(plain) and not grid <= scored_pairs(plain)


@pytest.mark.parametrize("raise_ac, pick", [(1.0, (5.5, 3.0)), (0.00995, (5.5, 3.0)), (0.0, (3.5, 1.5))])
def test_the_pick_is_scored_on_the_whole_window_and_joint_keeps_the_defaults_path(tiny_input, monkeypatch, raise_ac, pick):
    """An analytic loss of (log10 E, log10 tau_Y) with three basins: on the search's frames a soft,
    early-yielding one A (0 at (3.5, 1.5)) and a stiff one C (0.005 at (6.5, 4.5)) are the product
    grid's two best minima, and B (0.01 at (5.5, 3.0)) is the minimum of the default's line at
    tau_Y's guess; on every frame of the window A and C cost ``raise_ac`` more. ``joint_yield``
    follows a path from all three (B's marked as the default's) and weighs the grid's against B on
    the window: B when A costs 1 more there (on the search's frames alone A won), B when A is lower
    by less than MIN_GAIN (0.00995 against 0.01), A when A is lower by more. The record keeps the
    pick's search-frame loss; B, A and C are scored once each on the window. Without
    ``joint_yield`` the search picks B on its own frames and scores nothing on the window."""
    import toolkit.physics.coarse_search as cs

    m = _module(tiny_input, material="plasticine", optimize_params=["E", "yield_stress"])
    stage = m.stages[0]
    window = stage.window(m.input.n_train)
    picked, whole = score_frames(window, 2), score_frames(window, window)  # the tiny clip's window: 5 frames
    assert whole != picked and len(whole) == window - 1
    names = list(m.material.param_names)
    window_calls = []

    def loss(module, stage_, params, frames, v0=None):
        e, y = math.log10(float(params[names.index("E")])), math.log10(float(params[names.index("yield_stress")]))
        extra = raise_ac if frames == whole else 0.0
        if frames == whole:
            window_calls.append((round(e, 3), round(y, 3)))
        else:
            assert frames == picked
        return min(0.5 * ((e - 3.5) ** 2 + (y - 1.5) ** 2) + extra, 0.01 + (e - 5.5) ** 2 + (y - 3.0) ** 2,
                   0.005 + (e - 6.5) ** 2 + (y - 4.5) ** 2 + extra)

    monkeypatch.setattr(cs, "candidate_loss", loss)
    rec = coarse_search(m, stage, frames=2, joint_yield=True)
    ends = {(round(math.log10(p["params"]["E"]), 3), round(math.log10(p["params"]["yield_stress"]), 3)): p["origin"]
            for p in rec["paths"]}
    assert ends == {(3.5, 1.5): "grid", (5.5, 3.0): "line", (6.5, 4.5): "grid"}
    assert math.log10(rec["best"]["E"]) == pytest.approx(pick[0], abs=1e-4)
    assert math.log10(rec["best"]["yield_stress"]) == pytest.approx(pick[1], abs=1e-4)
    search_loss = 0.01 if pick == (5.5, 3.0) else 0.0
    assert rec["best_loss"] == pytest.approx(search_loss, abs=1e-6)
    assert rec["best_window_loss"] == pytest.approx(search_loss + (raise_ac if pick == (3.5, 1.5) else 0.0), abs=1e-6)
    assert rec["window_frames"] == whole and len(window_calls) == 3  # the default's pick (B), A and C
    assert rec["rollouts"] == len(rec["points"]) + len(window_calls)
    window_calls.clear()
    plain = coarse_search(m, stage, frames=2)  # the default's paths never reach A's grid point: B, on its frames
    assert math.log10(plain["best"]["E"]) == pytest.approx(5.5, abs=1e-4) and plain["best_loss"] == pytest.approx(0.01)
    assert not window_calls and plain["window_frames"] == picked and plain["rollouts"] == len(plain["points"])

"""Discovery: a hidden effect is named and added, the future gap shrinks, a null scene gets "no missing effect".

The scenes (:mod:`toolkit.discovery.hidden`, size ``tiny``): an elastic box thrown onto a
frictionless (``slip``) ground, 10 cameras at 32 px, 9 frames (6 for fitting, 3 future), the
truth simulated with 16x the particles and 2.7x the substeps of the fit and rendered as a
textured mesh. Each is fitted with the base model (no effect) by the physics trainer, then
:func:`toolkit.discovery.discover` runs with the shipped, null-calibrated thresholds. The
fitted scenes are shared at session scope (each is generated, fitted and discovered once).
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from toolkit.discovery.hidden import HiddenScene, fit_base

#: the base fit (the ``tiny`` size's curriculum) and discovery use the settings the shipped
#: thresholds were calibrated with (``benchmarks/discovery.py --small``); the EMD is skipped
DISCOVER = dict(emd=False)

# one worker builds each scene once: the tests sharing a scene (ground_friction: three, none: two)
# were spread over both workers, and each worker fitted and discovered the scene again
pytestmark = [pytest.mark.xdist_group("discovery"), pytest.mark.usefixtures("one_torch_thread")]


# session scope: a module fixture is torn down (and rebuilt) whenever the worker leaves the module
@pytest.fixture(scope="session")
def runs(tmp_path_factory):
    """``runs(effect)``: the scene hiding ``effect`` at high strength (``"none"``: nothing hidden),
    generated, fitted with the base model and discovered once per test session."""
    from toolkit.discovery import discover

    cache: dict[str, SimpleNamespace] = {}
    root = tmp_path_factory.mktemp("discovery")

    def get(effect: str) -> SimpleNamespace:
        if effect not in cache:
            hs = HiddenScene(effect, "none" if effect == "none" else "high")
            scene = hs.generate(root / "scenes" / hs.name)
            inp = hs.physics_input(scene)
            run = root / "runs" / hs.name
            inp.save(run / "physics_input.pt")
            module = fit_base(inp, run / "physics")
            result = discover(module, run / "discovery", **DISCOVER)
            cache[effect] = SimpleNamespace(scene=hs, module=module, result=result, run=run)
        return cache[effect]

    return get


# ---------------------------------------------------------------------------------------------- end to end
@pytest.mark.slow
@pytest.mark.parametrize("effect", ["ground_friction", "air_drag", "extra_acceleration"])
def test_hidden_effect_is_named_and_the_future_gap_shrinks(runs, effect):
    res = runs(effect).result
    assert res.decision == effect, res.verdict
    assert res.decision_kind == "physics" and res.identified
    # the future-frame Chamfer gap (against the ground-truth clouds) shrinks by at least half
    assert res.gap["cd_future_after"] <= 0.5 * res.gap["cd_future_before"], res.gap
    assert res.gap["cd_shrink"] >= 0.5
    # the held-out cameras see the improvement in the future frames too
    assert res.gap["held_out_loss_future_after"] < res.gap["held_out_loss_future_before"]
    s = res.final.strengths
    if effect == "ground_friction":  # truth mu = 0.6
        assert 0.3 < s["ground_friction.mu"] < 0.9
        lo, hi = res.final.intervals["ground_friction.mu"]
        assert lo <= s["ground_friction.mu"] <= hi
    elif effect == "air_drag":  # truth linear 2.5 1/s
        assert s["air_drag.linear"] + s["air_drag.quadratic"] > 0.5
    else:  # truth (ax, ay, az) = (-4, 0, 2) m/s^2
        assert s["extra_acceleration.ax"] < -2.0 and s["extra_acceleration.az"] > 0.5
    # the ranking put the truth among the confirmed candidates, and the report says so
    assert effect in res.refits
    assert "discovered" in (runs(effect).run / "discovery" / "report.md").read_text()


@pytest.mark.slow
def test_null_scene_has_no_missing_effect(runs):
    res = runs("none").result
    assert res.decision is None and res.decision_kind == "none", res.verdict
    assert res.verdict.startswith("No missing effect")
    assert res.final is None and res.gap["cd_shrink"] == 0.0
    # every confirmed physics candidate stays below the calibrated validation threshold
    for name, v in res.validation.items():
        if name != "base" and not v["control"]:
            assert v["validation"] <= res.thresholds.validation


@pytest.mark.slow
def test_strength_profile_finds_a_hidden_friction_from_its_base_point(runs):
    """The profile of a one-sided strength scores real rollouts. On the scene hiding ground
    friction (mu = 0.6), a friction below 1.5 improves on the base and a far too strong one
    (mu = 10) makes it worse. The best point sits below the truth, because the base parameters
    are refitted only linearly. Each score is the drop of the projected objective."""
    from toolkit.discovery.ranking import PROFILE_MULTIPLES, _perp, _projector, profile_strengths

    lib = runs("ground_friction").result.lib
    q0 = lib.q0.copy()
    lib.assign(q0)
    r0 = lib.residuals(q0)
    Q = _projector(lib.jacobian(q0, lib.base_names, r0))
    r_perp = _perp(Q, r0.numpy())
    points, best = profile_strengths(lib, q0, Q, r_perp, ["ground_friction.mu"])
    values = [p["value"] for p in points]
    assert values == pytest.approx([min(0.05 * m, 10.0) for m in PROFILE_MULTIPLES])  # 15 clipped at the bound
    drop, q_best, rj = best
    mu = q_best[lib.index_of["ground_friction.mu"]]
    assert mu <= 1.5 and drop > 0.0, points
    by_value = {p["value"]: p["score"] for p in points}
    assert by_value[10.0] < 0.0
    assert by_value[mu] == pytest.approx(drop / (0.5 * float(r_perp @ r_perp)))
    assert by_value[mu] == pytest.approx(1.0 - float(rj @ rj) / float(r_perp @ r_perp))


@pytest.mark.slow
def test_ranking_scores_a_clipped_one_sided_candidate_on_its_profile(runs, monkeypatch):
    """When the linear prediction of every candidate is clipped to zero, the one-sided physics
    candidates (friction, drag, damping) take their profile's score and strength, and the others
    (two-sided strengths, controls) keep a zero score and no profile."""
    from toolkit.discovery import ranking as rk

    lib = runs("ground_friction").result.lib
    monkeypatch.setattr(rk, "_bounded_lsq", lambda A, b, lo, hi: np.zeros(A.shape[1]))
    result, _ = rk.rank_candidates(lib, search_wall=False)
    by_name = {s.name: s for s in result.scores}
    friction = by_name["ground_friction"]
    assert friction.profile and friction.score > 0.0
    best = max(friction.profile, key=lambda p: p["score"])
    assert friction.score == pytest.approx(best["score"] * result.base_refit_objective / result.objective)
    assert friction.predicted_strength["ground_friction.mu"] == pytest.approx(best["value"])
    for name in ("air_drag", "internal_damping"):
        assert by_name[name].profile, name
    for name in ("extra_acceleration", "timing", "stiffness_gradient", "density", "camera_pose"):
        assert by_name[name].profile is None and by_name[name].score == 0.0, name


@pytest.mark.slow
def test_library_model_is_the_module_and_density_is_projected_out(runs):
    """At zero strengths the library model moves exactly as the fitted module; density, which
    only rescales E under gravity, has (almost) no score once E's direction is projected out."""
    r = runs("none")
    lib, res = r.result.lib, r.result
    pred = r.module.predict_trajectory()
    mine = lib.predict(lib.q0)
    assert torch.equal(pred["positions"], mine["positions"]) and torch.allclose(pred["means"], mine["means"])
    density = res.ranking.get("density")
    g, pg = density.gradient["density.log_ratio"], density.projected_gradient["density.log_ratio"]
    assert density.score < 1e-3 and abs(pg) < 0.2 * abs(g), (density.score, g, pg)
    loc = res.localization
    assert loc.heat.shape == (r.module.input.n_train, 3) and loc.image.shape == (10, r.module.input.n_train)


@pytest.mark.slow
def test_discover_command_on_a_run_folder(runs, tmp_path):
    """``projo4d discover RUN_DIR`` on the pipeline's run layout (physics_input.pt +
    physics/checkpoints/last.ckpt), and the module rebuilt from it equals the fitted one."""
    from toolkit.cli import main
    from toolkit.discovery import load_fitted_module

    r = runs("ground_friction")
    loaded = load_fitted_module(r.run)
    assert loaded.estimate()["params"] == pytest.approx(r.module.estimate()["params"])
    assert loaded.v0.tolist() == pytest.approx(r.module.v0.tolist())
    out = tmp_path / "disc"
    assert main(["discover", str(r.run), "--out", str(out), "--candidates", "ground_friction", "air_drag", "--top-k", "2",
                 "--iterations", "3", "--final-iterations", "3", "--no-emd"]) == 0
    d = json.loads((out / "discovery.json").read_text())
    assert d["decision"] == "ground_friction" and d["identified"] is True
    assert {s["name"] for s in d["ranking"]["scores"]} == {"ground_friction", "air_drag"}
    for f in ("report.md", "report.html", "residual_heatmap.png", "residual_split.png", "gap.png"):
        assert (out / f).is_file()
    assert "ground_friction" in (out / "report.html").read_text()


@pytest.mark.slow
def test_internal_damping_is_exported_as_the_kelvin_voigt_material(runs):
    """A discovered internal damping becomes the registered ``kelvin_voigt`` material over the base
    one: the exported module, and the module built from the config by name (as ``projo4d fit
    --config`` does), predict what the discovery library (its own augmented material) predicts."""
    from toolkit.discovery.confirm import Refit
    from toolkit.discovery.export import config_of, module_with_effect
    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule

    r = runs("ground_friction")
    lib = r.result.final.lib
    q = r.result.final.q.copy()
    for n in lib.params_of("ground_friction"):
        q[lib.index_of[n]] = 0.0
    q[lib.index_of["internal_damping.eta"]] = 40.0
    refit = Refit(name="internal_damping", q=q, start_objective=0.0, objective=0.0, lib=lib)
    ours = lib.predict(q)["positions"]
    new = module_with_effect(refit)
    assert new.material.registry_name == "kelvin_voigt" and new.material.base.registry_name == "neo_hookean"
    assert new.estimate()["params"]["damping"] == pytest.approx(40.0, rel=1e-5) and "damping" in new.optimized_material
    assert torch.allclose(new.predict_trajectory()["positions"], ours, atol=1e-5)
    # the damping matters here: without it the body moves otherwise
    q0 = q.copy()
    q0[lib.index_of["internal_damping.eta"]] = 0.0
    assert float((lib.predict(q0)["positions"] - ours).abs().max()) > 1e-3
    cfg = config_of(refit)
    model = dict(cfg["model"])
    assert model["material"] == "kelvin_voigt" and model["material_options"]["base"] == "neo_hookean"
    model["sim"] = SimConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in model["sim"].items()})
    replay = InversePhysicsModule(r.module.input, **model)
    # the geometry is not carried by the config (it comes from the run): neither the base fit's
    # particle offsets (this tiny scene's curriculum fits X) nor the refit's rigid shift (m); with
    # both put back, the replay starts where the library's body starts
    shift = torch.tensor(lib.physical(q)["shift"], dtype=torch.float32)
    with torch.no_grad():
        replay.particle_offset.copy_(r.module.particle_offset.detach().cpu() + shift)
    assert torch.allclose(replay.predict_trajectory()["positions"], ours, atol=1e-5)


@pytest.mark.slow
def test_discovered_effect_as_a_module(runs):
    """The decision exported as an InversePhysicsModule with the effect predicts what the
    discovery's final refit predicts."""
    res = runs("ground_friction").result
    new = res.to_module()
    assert new.estimate()["effects"]["ground_friction"]["mu"] == pytest.approx(res.final.strengths["ground_friction.mu"], rel=1e-5)
    ours = res.final.lib.predict(res.final.q)["positions"]
    theirs = new.predict_trajectory()["positions"]
    assert torch.allclose(ours, theirs, atol=1e-5)


# ---------------------------------------------------------------------------------------------- units
def test_augmented_material_is_exact_at_zero_and_density_rescales_stress():
    from toolkit.discovery.materials import AugmentedMaterial
    from toolkit.mpm import MPMSimulator, SimConfig

    ijk = torch.stack(torch.meshgrid(*[torch.arange(3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x0 = ijk.float() * 0.02 + torch.tensor([0.0, 0.1, 0.0])
    cfg = SimConfig(dx=0.04, substeps=20, boundary="slip")
    v0 = torch.tensor([1.0, -0.5, 0.0])
    plain = MPMSimulator("neo_hookean", cfg).rollout(x0, v0, torch.tensor([3e4, 0.3]), n_frames=3).positions
    aug = AugmentedMaterial("neo_hookean")
    assert aug.param_names == ["E", "nu", "damping", "log_density_ratio"]
    sim = MPMSimulator(aug, cfg)
    same = sim.rollout(x0, v0, aug.pack({"E": 3e4, "nu": 0.3}), n_frames=3).positions
    assert torch.equal(plain, same)
    # twice the density = half the stress: E twice as large moves the same way
    dense = sim.rollout(x0, v0, aug.pack({"E": 6e4, "nu": 0.3, "log_density_ratio": math.log(2.0)}), n_frames=3).positions
    assert torch.allclose(plain, dense, atol=1e-6)
    damped = sim.rollout(x0, v0, aug.pack({"E": 3e4, "nu": 0.3, "damping": 30.0}), n_frames=3).positions
    assert (damped - plain).abs().max() > 1e-4


def test_hermite_interpolation_hits_frames_and_follows_velocity():
    from toolkit.discovery.library import _hermite

    t = torch.linspace(0, 3, 4)
    pos = (0.5 * t**2).reshape(4, 1, 1).repeat(1, 2, 3)  # x = t^2 / 2 in frames, frame_dt = 1
    vel = t.reshape(4, 1, 1).repeat(1, 2, 3)
    assert torch.allclose(_hermite(pos, vel, torch.tensor([0.0, 1.0, 2.0]), 1.0), pos[:3])
    assert torch.allclose(_hermite(pos, vel, torch.tensor([1.5]), 1.0), torch.full((1, 2, 3), 0.5 * 1.5**2))
    s = torch.tensor([1.0], requires_grad=True)
    _hermite(pos, vel, s, 1.0)[0, 0, 0].backward()
    assert s.grad.item() == pytest.approx(1.0)  # dx/dt = v(1) = 1


def test_candidate_library():
    from toolkit.discovery.candidates import LIBRARY, candidate, library

    names = [c.name for c in LIBRARY]
    assert names == ["ground_friction", "air_drag", "extra_acceleration", "wall", "internal_damping", "plastic_yield", "timing",
                     "stiffness_gradient", "density", "camera_pose"]
    assert {c.name for c in LIBRARY if c.control} == {"density", "camera_pose"}
    assert {c.name for c in LIBRARY if c.search} == {"wall", "plastic_yield"}
    assert candidate("plastic_yield").applicable("neo_hookean") and not candidate("plastic_yield").applicable("plasticine")
    assert not candidate("air_drag").applicable("neo_hookean", ["air_drag"])
    assert candidate("camera_pose").parameter_names(2) == [f"camera_pose.c{c}.{a}" for c in range(2) for a in "xyz"]
    with pytest.raises(ValueError, match="unknown discovery candidate"):
        library(["friction"])


def test_thresholds_calibration_and_decision_rule(tmp_path):
    from toolkit.discovery.calibration import DEFAULT_THRESHOLDS, Thresholds, calibrate, null_statistics
    from toolkit.discovery.workflow import decide

    assert DEFAULT_THRESHOLDS.n_null > 0 and "null" in DEFAULT_THRESHOLDS.source
    def v(val, fit=0.01, control=False, worst=0.0):
        return {"validation": val, "fit": fit, "control": control, "worst": worst}

    nulls = [{"validation": {"base": v(0.0), "air_drag": v(0.01), "camera_pose": v(0.03, 0.03, True)}},
             {"validation": {"base": v(0.0), "timing": v(-0.02), "camera_pose": v(0.002, 0.5, True)}},  # not reported anyway
             {"validation": {"base": v(0.0), "camera_pose": v(0.2, 0.5, True, worst=-0.3)}}]  # hurts a component: idem
    stats = [null_statistics(n) for n in nulls]
    assert stats[0] == {"validation": 0.01, "fit": 0.01, "camera": 0.03, "camera_validation": 0.03, "camera_worst": 0.0,
                        "camera_concentration": 0.0}
    thr = calibrate(stats)
    assert thr.validation == pytest.approx(1.25 * 0.01 + 0.01) and thr.camera == pytest.approx(1.25 * 0.03 + 0.05)
    assert Thresholds.load(thr.save(tmp_path / "t.json")) == thr
    dofs = {"ground_friction": 1, "air_drag": 2, "extra_acceleration": 3, "camera_pose": 9}
    # within 20 % of the best: the fewest strength parameters wins, the others are indistinguishable
    val = {"base": v(0.0), "extra_acceleration": v(0.40), "ground_friction": v(0.36), "air_drag": v(0.20)}
    assert decide(val, dofs, thr) == ("ground_friction", "physics", ["extra_acceleration"])
    # a candidate that makes one validation component much worse does not pass
    val["ground_friction"] = v(0.36, worst=-0.5)
    assert decide(val, dofs, thr)[0] == "extra_acceleration"
    # nothing passes, but the camera-pose control explains the fit and the other views: an observation error
    val = {"base": v(0.0), "air_drag": v(0.001), "camera_pose": v(0.1, 0.3, True)}
    assert decide(val, dofs, thr) == ("camera_pose", "observation", [])
    for cam in (v(0.1, 0.01, True), v(0.0, 0.3, True)):  # too small a fit gain, or no help on held-out data
        val["camera_pose"] = cam
        assert decide(val, dofs, thr) == (None, "none", [])


def test_run_folder_errors(tmp_path):
    from toolkit.discovery import load_fitted_module

    with pytest.raises(FileNotFoundError, match="physics_input.pt does not exist"):
        load_fitted_module(tmp_path)
    with pytest.raises(ValueError, match="give a run folder"):
        load_fitted_module(input_path=tmp_path / "x.pt")


def test_discover_command_names_bad_input(tmp_path):
    from toolkit.cli import main

    def error(*argv):
        with pytest.raises(SystemExit) as exc:
            main(["discover", *map(str, argv)])
        return str(exc.value)

    assert "is not a folder" in error(tmp_path / "missing")
    run = tmp_path / "run"
    run.mkdir()
    assert "has no physics_input.pt" in error(run)
    (run / "physics_input.pt").write_bytes(b"")
    assert "has no physics/checkpoints/last.ckpt (fit it first)" in error(run)
    (run / "physics" / "checkpoints").mkdir(parents=True)
    (run / "physics" / "checkpoints" / "last.ckpt").write_bytes(b"")
    msg = error(run, "--candidates", "ground_friction", "magnetism")
    assert "--candidates" in msg and "magnetism" in msg and "air_drag" in msg
    bad = tmp_path / "thr.json"
    bad.write_text("{not json")
    assert f"--thresholds {bad}" in error(run, "--thresholds", bad)
    assert "--top-k must be >= 1" in error(run, "--top-k", "0")


def test_discovery_benchmark_refuses_a_bad_device_before_any_work(tmp_path, capsys):
    """``benchmarks/discovery.py --stage0-device gpu`` stops with exit status 2 naming the option and
    the value, and writes nothing."""
    bench = _bench_module("discovery")
    out = tmp_path / "D"
    for option in ("--device", "--stage0-device"):
        with pytest.raises(SystemExit) as exc:
            bench.main([option, "gpu", "--report-only", "--out", str(out)])
        assert exc.value.code == 2
        assert f"{option} must be cpu, cuda or cuda:N; got 'gpu'" in capsys.readouterr().err
    assert not out.exists()


def test_discovery_benchmark_refuses_bad_fitting_cameras_before_any_work(tmp_path, capsys):
    """``--cameras`` picks stage 0's fitting cameras: with the true body (no stage 0), with one camera, a
    repeated one or one the scenes do not have, the benchmark stops with exit status 2 naming the option, and writes nothing."""
    bench = _bench_module("discovery")
    out = tmp_path / "D"
    cases = [(["--cameras", "1", "5", "9", "2"], "use it with --geometry stage0"),
             (["--geometry", "stage0", "--cameras", "1"], "two or more distinct 0-based camera indices, got [1]"),
             (["--geometry", "stage0", "--cameras", "1", "5", "5"], "got [1, 5, 5]"),
             (["--geometry", "stage0", "--cameras", "1", "5", "10"], "got [1, 5, 10]; the scenes have 10 cameras (0-9)")]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exc:
            bench.main(argv + ["--report-only", "--out", str(out)])
        assert exc.value.code == 2 and message in capsys.readouterr().err
    assert not out.exists()


def _bench_module(name: str):
    from tests.bench_helpers import load_benchmark_script

    return load_benchmark_script(name)


def test_discovery_record_keeps_the_start_each_refit_kept():
    """A scene's record carries each confirmation refit's objective and strengths, and for a
    candidate refitted from two starts which one was kept and the other's objective; a refit
    without a second start carries no start."""
    bench = _bench_module("discovery")
    refits = {"base": {"objective": 2.0, "strengths": {}, "extra": {}},
              "air_drag": {"objective": 1.5, "strengths": {"air_drag.linear": 2.4},
                           "extra": {"start": "observed_drag_rate", "other_start_objective": 1.8}},
              "wall": {"objective": 1.9, "strengths": {"wall.strength": 1.0}, "extra": {"offset": 0.1}}}
    out = bench._refit_summary(refits)
    assert out["air_drag"] == {"objective": 1.5, "strengths": {"air_drag.linear": 2.4}, "start": "observed_drag_rate",
                               "other_start_objective": 1.8}
    assert "start" not in out["wall"] and out["base"]["objective"] == 2.0


def test_refit_frames_hold_out_the_last_quarter_and_keep_two_for_the_refits():
    """The confirmation's split: the last quarter of the training frames held out (at least 1 from
    4 frames on, none below), an explicit count clipped so that 2 frames stay for the refits."""
    from toolkit.discovery.workflow import refit_frames

    assert refit_frames(10) == (list(range(8)), [8, 9])
    assert refit_frames(14) == (list(range(10)), [10, 11, 12, 13])
    assert refit_frames(4) == ([0, 1, 2], [3])
    assert refit_frames(3) == ([0, 1, 2], [])
    assert refit_frames(6, holdout_frames=9) == ([0, 1], [2, 3, 4, 5])
    assert refit_frames(6, holdout_frames=-1) == (list(range(6)), [])


def test_discovery_table_title_names_where_stage0_and_the_fits_ran():
    """The full-size table's title says where the fits and stage 0 ran (a CPU run was once titled
    "GPU run"), and makes no claim when it only tabulates stored records."""
    from types import SimpleNamespace

    bench = _bench_module("discovery")

    def title(device, stage0_device=None, geometry="stage0", report_only=False):
        return bench._full_size_title(SimpleNamespace(device=device, stage0_device=stage0_device, geometry=geometry,
                                                      report_only=report_only))

    assert title("cpu") == "CPU run (full-size scenes)"
    assert title("cuda:0") == "GPU run (full-size scenes)"
    assert title("cpu", "cuda") == "CPU fits, stage 0 on GPU (full-size scenes)"
    assert title("cpu", "cuda", geometry="oracle") == "CPU run (full-size scenes)"
    assert title("cuda", report_only=True) == "Full-size scenes"


def test_discovery_summary_counts_a_truth_named_among_the_tied():
    """On the scenes whose effect the data show, top-1 counts the decision alone; "named or tied"
    also counts a truth the report names as tied with the decision, never one it left out."""
    from toolkit.discovery.calibration import Thresholds

    bench = _bench_module("discovery")

    def rec(effect, decision, tied, truth_cd):
        return {"scene": f"{effect}-{decision}", "effect": effect, "expected": effect, "decision": decision,
                "correct": decision == effect, "indistinguishable": tied, "top3": [decision], "cd_before": 1.0,
                "cd_after": 0.2, "cd_truth_effect": truth_cd, "cd_shrink": 0.8, "validation": {}, "truth_strengths": {}}

    records = [rec("air_drag", "air_drag", [], 0.2), rec("air_drag", "ground_friction", ["air_drag"], 0.2),
               rec("wall", "extra_acceleration", ["ground_friction"], 0.3),
               rec("timing", None, [], 0.9)]  # the data hardly show it: left out
    obs = bench.summarize(records, Thresholds(validation=0.06, fit=0.0, camera=0.1))["observable"]
    assert obs["n"] == 3 and obs["top1"] == pytest.approx(1 / 3) and obs["named_or_tied"] == pytest.approx(2 / 3)
    assert "named first or among the tied candidates the report names, on those | 67 %" in bench.markdown(
        bench.summarize(records, Thresholds(validation=0.06, fit=0.0, camera=0.1)), "t")


def test_discovery_runs_counts_a_scene_as_named_only_when_every_run_names_it():
    """Two runs of the same scenes: the stable rate counts a scene whose effect the data show in
    both runs as named only if both runs name it; a null scene flagged once is listed; a scene that
    shows its effect in one run only, or ran in one run only, is left out of the stable rate."""
    runs_mod = _bench_module("discovery_runs")

    def rec(scene, effect, decision, truth_shrink):
        return {"scene": scene, "effect": effect, "expected": None if effect == "none" else effect, "decision": decision,
                "shrink": truth_shrink}

    a = [rec("drag", "air_drag", "air_drag", 0.9), rec("wall", "wall", "wall", 0.8), rec("null", "none", None, None),
         rec("weak", "internal_damping", None, 0.6), rec("once", "wall", "wall", 0.9)]
    b = [rec("drag", "air_drag", "ground_friction", 0.9), rec("wall", "wall", "wall", 0.7), rec("null", "none", "wall", None),
         rec("weak", "internal_damping", None, 0.1)]
    cmp = runs_mod.compare({"A": a, "B": b}, lambda r: r["shrink"])
    assert cmp["in_every_run"] == 4 and cmp["observable_every_run"] == ["drag", "wall"]
    assert cmp["named_every_run"] == 0.5 and cmp["named_some_run"] == 1.0
    assert cmp["named_every_run_scenes"] == ["wall"]
    assert cmp["unstable"] == ["drag", "null"]
    assert cmp["null_scenes"] == 1 and cmp["null_flagged_any"] == ["null"]


def test_discovery_benchmark_refuses_to_mix_stage0_seeds_in_one_folder(tmp_path, capsys):
    """A run folder holds one stage-0 seed: resuming it with another seed stops before any work,
    naming the file, the scene and both seeds."""
    bench = _bench_module("discovery")
    out = tmp_path / "D"
    out.mkdir()
    (out / "results.jsonl").write_text(json.dumps({"scene": "none-none-neo_hookean-slide-s0", "effect": "none",
                                                   "stage0_seed": 0}) + "\n")
    with pytest.raises(SystemExit) as exc:
        bench.main(["--geometry", "stage0", "--stage0-seed", "1", "--null", "1", "--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "results.jsonl" in err and "none-none-neo_hookean-slide-s0" in err and "--stage0-seed 0, not 1" in err
    assert sorted(p.name for p in out.iterdir()) == ["results.jsonl"]


def test_discovery_report_decides_a_tie_as_the_run_did_with_its_observed_motion():
    """A stored record whose tie the observed motion settled: the benchmark's report decides it the
    same way (the smooth, constant pull prefers the extra acceleration over the wall, which
    parsimony alone would pick), and the motion survives a round trip through its dict."""
    from toolkit.discovery.calibration import Thresholds
    from toolkit.discovery.kinematics import ObservedMotion

    bench = _bench_module("discovery")
    motion = ObservedMotion(frames=[1, 2, 3, 4, 5], acceleration=np.array([-4.0, -9.8, 2.0]), extra=np.array([-4.0, 0.0, 2.0]),
                            v0=np.array([1.5, 0.0, 0.3]), shape="smooth", loo={"line": 0.01, "parabola": 0.001, "segments": 0.004},
                            phase="slide", law="constant", law_loo={"constant": 0.0014, "drag": 0.016}, drag_rate=3.0,
                            law_frames=[1, 2, 3, 4, 5, 6, 7])
    back = ObservedMotion.from_dict(json.loads(json.dumps(motion.to_dict())))
    assert back.to_dict() == motion.to_dict()

    def v(val):
        return {"validation": val, "fit": 0.05, "control": False, "worst": 0.0}

    thr = Thresholds(validation=0.06, fit=0.0, camera=0.1, source="test")
    rec = {"validation": {"base": v(0.0), "extra_acceleration": v(0.30), "wall": v(0.29)},
           "dofs": {"extra_acceleration": 3, "wall": 2}, "noise": None, "single_camera": None}
    assert bench.decide_record({**rec, "motion": None}, thr)[0] == "wall"  # parsimony alone
    assert bench.decide_record({**rec, "motion": motion.to_dict()}, thr)[:2] == ("extra_acceleration", "physics")
    old = {k: v for k, v in motion.to_dict().items() if k not in ("law", "law_loo", "drag_rate", "law_frames")}
    assert ObservedMotion.from_dict(old).law == "either"  # a record from before the force law


def test_consensus_of_several_runs():
    """All runs agree: that name (with the candidates any run tied to it); one run names an effect
    and another none: not named; different names: not named, with the counts."""
    from toolkit.discovery.consensus import consensus, consensus_markdown

    a = {"decision": "ground_friction", "indistinguishable": ["air_drag"],
         "separation": [{"sentence": "a longer clip would separate them"}]}
    b = {"decision": "ground_friction", "indistinguishable": [], "separation": []}
    c = consensus([a, b], ["A", "B"])
    assert c.agreed and c.decision == "ground_friction" and c.counts == {"ground_friction": 2}
    assert c.tied == ["air_drag"] and c.separation == ["a longer clip would separate them"]
    assert c.sentence.startswith("All 2 runs name ground_friction") and "air_drag" in c.sentence
    none = {"decision": None}
    c = consensus([a, none, b], ["A", "N", "B"])
    assert not c.agreed and c.decision is None and c.counts == {"ground_friction": 2, "none": 1}
    assert "named in 2 of 3 runs" in c.sentence and "not named" in c.sentence
    c = consensus([a, {"decision": "wall"}], ["A", "W"])
    assert not c.agreed and c.decision is None and "disagree" in c.sentence and "wall (1 of 2 runs)" in c.sentence
    assert consensus([none, none], ["A", "B"]).sentence == "No run finds a missing effect (2 runs)."
    md = consensus_markdown(c, ["verdict A", "verdict W"])
    assert "| W | wall |" in md and "- `A`: verdict A" in md
    with pytest.raises(ValueError, match="at least two runs"):
        consensus([a], ["A"])


def test_discover_command_on_two_runs_of_one_scene(runs, tmp_path):
    """``projo4d discover A B`` on two copies of one run: each gets its discovery, and the consensus
    names the effect both name; runs of different scenes and a folder given twice are refused
    before any work."""
    import shutil

    from toolkit.cli import main

    r = runs("ground_friction")
    a, b = tmp_path / "A", tmp_path / "B"
    for d in (a, b):
        shutil.copytree(r.run, d, ignore=shutil.ignore_patterns("discovery*"))
    opts = ["--candidates", "ground_friction", "air_drag", "--top-k", "2", "--iterations", "3", "--final-iterations", "3",
            "--no-emd"]
    assert main(["discover", str(a), str(b), *opts]) == 0
    c = json.loads((a / "discovery_consensus" / "consensus.json").read_text())
    assert c["agreed"] and c["decision"] == "ground_friction" and c["decisions"] == ["ground_friction"] * 2
    for d in (a, b):
        assert json.loads((d / "discovery" / "discovery.json").read_text())["decision"] == "ground_friction"

    def error(*argv):
        with pytest.raises(SystemExit) as exc:
            main(["discover", *map(str, argv), *opts])
        return str(exc.value)

    (a / "run.json").write_text(json.dumps({"scene": "/data/one", "scene_fingerprint": "aaa"}))
    (b / "run.json").write_text(json.dumps({"scene": "/data/two", "scene_fingerprint": "bbb"}))
    assert "runs of different scenes (/data/one and /data/two)" in error(a, b)
    assert "given twice" in error(a, a)
    assert "has no physics_input.pt" in error(a, tmp_path)


def test_discovery_from_images_script_refuses_bad_settings_before_any_work(tmp_path):
    """``benchmarks/discovery_from_images.sh`` stops with exit status 2 on a bad ``RANGE`` or a
    missing ``THRESHOLDS`` file, naming it, and writes nothing."""
    import os
    import subprocess
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "discovery_from_images.sh"
    out = tmp_path / "D"
    for env, text in (({"RANGE": "5:2"}, "RANGE=5:2: expected A:B with 0 <= A < B <= 60"),
                      ({"RANGE": "0:61"}, "RANGE=0:61"),
                      ({"THRESHOLDS": str(tmp_path / "none.json")}, "no such file (expected a thresholds JSON)")):
        p = subprocess.run(["bash", str(script), str(out), "60"], env={**os.environ, **env}, capture_output=True, text=True)
        assert p.returncode == 2 and text in p.stderr
    assert not out.exists()

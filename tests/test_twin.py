"""Digital twins: export of a fitted run, the twin file, re-simulation under new conditions, rendering."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.physics_fixtures import tiny_scene
from toolkit.cli import main


@pytest.fixture(scope="module")
def fitted_run(tmp_path_factory):
    """A tiny oracle run (144 particles, 6 frames at 32 px, 8 iterations), fitted once for the module."""
    scene = tiny_scene(tmp_path_factory.mktemp("twin_scene"))
    out = tmp_path_factory.mktemp("twin_run") / "run"
    args = ["run", str(scene), "--out", str(out), "--geometry", "oracle", "--config", "configs/demo.yaml",
            "--sim", '{"dx": 0.04, "substeps": 30}', "--curriculum", "XAS:4@3,XASM:4", "--device", "cpu"]
    assert main(args) == 0
    return out


@pytest.fixture(scope="module")
def exported(fitted_run):
    from toolkit.twin.export import export_run

    return export_run(fitted_run)


def test_export_writes_refined_gaussians_sequence_and_twin(fitted_run, exported):
    from toolkit.scene.export import load_ply
    from toolkit.data.ply import read_ply_points
    from toolkit.pipeline import load_fitted_module
    from toolkit.twin import DigitalTwin

    twin = DigitalTwin.load(exported["twin"])
    module = load_fitted_module(fitted_run)
    # the physics-refined Gaussians (X and A groups), not stage 0's: means0 + fitted offset
    g = load_ply(exported["gaussians"])
    refined = (module.gaussian_means0 + module.gaussian_offset).detach().numpy()
    assert np.array_equal(g.means.numpy(), refined)
    assert g.sh.shape[1] == 16  # INRIA layout: degree-3 SH, 45 f_rest values
    assert np.allclose(0.28209479 * g.sh[:, 0].numpy() + 0.5, module.colors.detach().numpy(), atol=1e-5)
    # the twin holds what the estimate says
    est = json.loads((fitted_run / "physics" / "estimate.json").read_text())
    for k, v in twin.params.items():
        assert v == pytest.approx(est["params"][k] if "params" in est else est[k], rel=1e-6)
    assert twin.meta["format"] == "projo4d-twin" and twin.meta["version"] == 1
    assert twin.meta["units"]["length"] == "m" and twin.meta["world"]["ground_height"] == 0.0
    assert twin.meta["sim"]["dx"] == 0.04 and twin.meta["sim"]["frame_dt"] == pytest.approx(1 / 24, rel=1e-6)
    assert np.array_equal(twin.arrays["particles"], (module.particles0 + module.particle_offset).detach().numpy())
    # per-frame sequence: the run's prediction
    pred = np.load(fitted_run / "evaluation" / "prediction.npz")
    T = pred["positions"].shape[0]
    assert exported["sequence_files"] == 2 * T
    for t in (0, T - 1):
        assert np.array_equal(read_ply_points(exported["sequence"] / f"particles_{t:03d}.ply"), pred["positions"][t])
        assert np.array_equal(load_ply(exported["sequence"] / f"gaussians_{t:03d}.ply").means.numpy(), pred["means"][t])
    schema = json.loads((exported["twin"].parent / "twin.schema.json").read_text())
    assert set(schema["required"]) <= set(twin.meta)


def test_twin_round_trip_reproduces_the_prediction(fitted_run, exported, device):
    """Simulating the twin with the fitted v0 gives the run's (CPU) prediction: bit for bit on CPU,
    to float32 round-off on CUDA (atomics); rendering works on the same device."""
    from toolkit.twin import DigitalTwin, orbit_cameras, render_trajectory, simulate_twin

    twin = DigitalTwin.load(exported["twin"])
    traj = simulate_twin(twin, device=device)
    pred = np.load(fitted_run / "evaluation" / "prediction.npz")
    assert traj.positions.shape == pred["positions"].shape
    tol = 0.0 if device == "cpu" else 1e-5  # metres
    np.testing.assert_allclose(traj.positions.numpy(), pred["positions"], rtol=0, atol=tol)
    np.testing.assert_allclose(traj.means.numpy(), pred["means"], rtol=0, atol=tol)
    frames = render_trajectory(twin, traj, orbit_cameras(twin, n=1, width=32, height=32), device=device)
    assert frames.shape == (len(pred["positions"]), 1, 32, 32, 3) and frames[:, :, 12:20, 12:20].mean() > 0.05


def test_new_throw_follows_the_ballistic_path(exported):
    """An elastic body in free flight: its centre of mass moves as x0 + v0 t + g t^2 / 2, whatever E is."""
    from toolkit.twin import DigitalTwin, simulate_twin

    twin = DigitalTwin.load(exported["twin"])
    v0 = np.array([-0.4, 1.0, 0.2])
    g = np.array(twin.meta["gravity"])
    for E in (1e4, 1e5):
        traj = simulate_twin(twin, v0=v0.tolist(), params={"E": E}, n_frames=6)
        assert traj.positions.shape == (7, len(twin.arrays["particles"]), 3)
        c = traj.positions.numpy().astype(np.float64).mean(1)
        t = traj.times[:, None]
        assert traj.positions.numpy()[:, :, 1].min() > 0.04  # stays clear of the ground (contact starts at frame 7)
        np.testing.assert_allclose(c, c[0] + v0 * t + 0.5 * g * t ** 2, atol=2e-3)
        assert traj.conditions["params"]["E"] == pytest.approx(E, rel=1e-6)
    with pytest.raises(ValueError, match=r"params \['G'\] are not parameters of 'neo_hookean'"):
        simulate_twin(twin, params={"G": 1.0})
    with pytest.raises(ValueError, match="v0 must be 3 finite numbers"):
        simulate_twin(twin, v0=[1.0, 2.0])


def test_twin_file_is_versioned_and_checked(exported, tmp_path):
    from toolkit.twin import DigitalTwin, TwinFormatError

    twin = DigitalTwin.load(exported["twin"])
    newer = DigitalTwin(meta={**twin.meta, "version": 99}, arrays=twin.arrays)
    with pytest.raises(TwinFormatError, match="version 99 is newer than this projo4d reads"):
        newer.save(tmp_path / "newer.npz")
    broken = DigitalTwin(meta=twin.meta, arrays={k: v for k, v in twin.arrays.items() if k != "embed_index"})
    with pytest.raises(TwinFormatError, match="the array 'embed_index' is missing"):
        broken.validate("x.npz")
    assert "deform_index" in twin.arrays  # fitted with the default deformed shapes
    half = DigitalTwin(meta=twin.meta, arrays={k: v for k, v in twin.arrays.items() if k != "deform_gradient"})
    with pytest.raises(TwinFormatError, match="deform_index and deform_gradient come together"):
        half.validate("x.npz")
    bad = DigitalTwin(meta=twin.meta, arrays={**twin.arrays, "deform_gradient": twin.arrays["deform_gradient"][:, :, :2]})
    with pytest.raises(TwinFormatError, match=r"x.npz: deform_index/deform_gradient must have shapes \(G="):
        bad.validate("x.npz")
    outside = DigitalTwin(meta=twin.meta, arrays={**twin.arrays, "deform_index": twin.arrays["deform_index"] + 10**6})
    with pytest.raises(TwinFormatError, match="deform_index must index the"):
        outside.validate("x.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(TwinFormatError, match="junk.npz: not a readable .npz twin file"):
        DigitalTwin.load(tmp_path / "junk.npz")
    again = DigitalTwin.load(twin.save(tmp_path / "copy.npz"))
    assert again.meta == twin.meta and all(np.array_equal(again.arrays[k], v) for k, v in twin.arrays.items())


def test_orbit_cameras_look_at_the_object(exported):
    from toolkit.twin import DigitalTwin, orbit_cameras

    twin = DigitalTwin.load(exported["twin"])
    cams = orbit_cameras(twin, n=4, width=48, height=32)
    centre = torch.as_tensor(twin.arrays["particles"].mean(0), dtype=torch.float32)
    uv, depth = cams.project(centre.expand(4, 1, 3))
    np.testing.assert_allclose(uv.reshape(4, 2).numpy(), np.tile([24.0, 16.0], (4, 1)), atol=1e-3)
    assert (depth > 0).all()


def test_simulate_command_renders_a_new_throw(exported, tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(exported["twin"]), "--out", str(out), "--v0", "-0.3,0.8,0", "--params", '{"E": 5e4}',
                 "--frames", "3", "--orbit", "2", "--size", "40", "32"]) == 0
    printed = capsys.readouterr().out
    assert "simulated 3 frames" in printed and "E = 5e+04" in printed
    d = np.load(out / "particles.npz")
    assert d["positions"].shape[0] == 4 and np.allclose(d["times"], np.arange(4) / 24, atol=1e-6)
    import imageio.v3 as iio

    video = next(out.glob("video.*"))
    frames = iio.imread(video)
    assert frames.shape[0] == 4 and frames.shape[2] == 80  # two 40 px cameras side by side, caption band below
    assert frames.shape[1] >= 32 + 14 - 1
    assert frames[:, :32].max() > 40  # the object is drawn
    with pytest.raises(SystemExit, match="not parameters of") as exc:
        main(["simulate", str(exported["twin"]), "--params", '{"G": 1}', "--no-video"])
    assert exc.value.code == 2


def test_export_command(fitted_run, tmp_path, capsys):
    assert main(["export", str(fitted_run), "--out", str(tmp_path / "e"), "--no-sequence"]) == 0
    printed = capsys.readouterr().out
    assert "twin:" in printed and "neo_hookean" in printed
    assert (tmp_path / "e" / "twin.npz").is_file() and not (tmp_path / "e" / "sequence").exists()
    with pytest.raises(SystemExit, match="holds no fitted model") as exc:
        main(["export", str(tmp_path)])
    assert exc.value.code == 2


def test_deformed_gaussians_travel_with_the_twin(tmp_path):
    """A fit whose Gaussians deform (gaussian_shape='deformed') exports its deformation
    coefficients; the twin's rollout gives the module's deformations and renders the module's
    images, and the per-frame PLY files hold the deformed covariances as plain scales and rotations."""
    from renderers.torch_reference import covariance_3d
    from tests.physics_fixtures import fit_sim
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.oracle import oracle_input
    from toolkit.scene.export import load_ply
    from toolkit.twin import DigitalTwin, render_trajectory, simulate_twin
    from toolkit.twin.export import twin_from_module, write_sequence

    inp = oracle_input(tiny_scene(tmp_path / "scene"), particle_spacing=0.02)
    module = InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", material_init="given", gaussian_shape="deformed",
                                  initial_params={"E": 3e3})  # soft: it squashes on landing
    pred = module.predict_trajectory()
    twin = DigitalTwin.load(twin_from_module(module).save(tmp_path / "twin.npz"))
    assert twin.arrays["deform_gradient"].shape == module.deform_gradient.shape
    traj = simulate_twin(twin)
    np.testing.assert_allclose(traj.deformations.numpy(), pred["deformations"].numpy(), rtol=0, atol=1e-5)
    last = pred["deformations"][-1]
    assert float((last - torch.eye(3)).abs().max()) > 0.05  # the body did deform: the check is not vacuous
    cams = module.input.cameras[[0]]
    frames = render_trajectory(twin, traj, cams)
    expected = module.render_frames(pred["means"], [0], pred["deformations"]).numpy()
    np.testing.assert_allclose(frames, expected, rtol=0, atol=1e-4)
    write_sequence(tmp_path / "seq", twin, traj.positions.numpy(), traj.means.numpy(), traj.deformations.numpy())
    T = len(traj.positions) - 1
    ply = load_ply(tmp_path / "seq" / f"gaussians_{T:03d}.ply")
    want = covariance_3d(module.log_scales.detach(), module.quats.detach(), last)
    torch.testing.assert_close(covariance_3d(ply.log_scales, ply.quats), want, atol=1e-7, rtol=1e-3)


def test_a_kept_stage_end_reloads_the_fit_as_it_stood_and_reruns_its_search(fitted_run):
    """``load_fitted_module(checkpoint=...)`` gives the fit at a kept stage end: at the end of stage
    1 (iteration 4, before the material was fitted) the coarse search, run again on the stage that
    fits ``M``, picks exactly what the run's own search picked (what benchmarks/search_check.py
    relies on); a name that is not kept raises an error naming the path."""
    from toolkit.physics.coarse_search import coarse_search
    from toolkit.pipeline import load_fitted_module

    record = json.loads((fitted_run / "physics" / "material_search.json").read_text())
    early = load_fitted_module(fitted_run, checkpoint="stage_00_end.ckpt")
    last = load_fitted_module(fitted_run)
    assert early.curriculum_step == record["iteration"] == 4 and last.curriculum_step == 8
    again = coarse_search(early, next(s for s in early.stages if "M" in s.groups))
    assert again["start"] == pytest.approx(record["start"], rel=1e-6)
    assert again["best"] == pytest.approx(record["best"], rel=1e-6)
    assert again["best_loss"] == pytest.approx(record["best_loss"], rel=1e-5)
    # one candidate scored alone gives the search's own number for it
    from toolkit.physics.coarse_search import candidate_loss

    stage = next(s for s in early.stages if "M" in s.groups)
    params = early.material_params().detach().clone()
    for j, name in enumerate(early.material.param_names):
        params[j] = record["best"].get(name, float(params[j]))
    assert candidate_loss(early, stage, params, record["frames"]) == pytest.approx(record["best_loss"], rel=1e-5)
    assert not torch.equal(early.particle_offset, last.particle_offset)  # the body moved on after the stage end
    with pytest.raises(FileNotFoundError, match="stage_07_end.ckpt does not exist"):
        load_fitted_module(fitted_run, checkpoint="stage_07_end.ckpt")

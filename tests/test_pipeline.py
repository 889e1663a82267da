"""`projo4d run`: every step of the pipeline writes its outputs; reruns resume instead of restarting."""

from __future__ import annotations

import json
import math

import pytest

from tests.physics_fixtures import tiny_scene
from toolkit.cli import main


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return tiny_scene(tmp_path_factory.mktemp("pipeline_scene"))


def test_run_with_oracle_geometry_writes_everything_and_resumes(scene, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["run", str(scene), "--out", str(out), "--geometry", "oracle", "--config", "configs/demo.yaml",
            "--sim", '{"dx": 0.04, "substeps": 30}', "--curriculum", "XAS:4@3,XASM:4", "--device", "cpu"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "parameter" in printed and "truth" in printed and "future frames: CD" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["curriculum"] == "XAS:4@3,XASM:4"
    assert {r["parameter"] for r in summary["parameters"]} >= {"E", "nu", "v0_x", "v0_y", "v0_z"}
    assert next(r for r in summary["parameters"] if r["parameter"] == "E")["truth"] == pytest.approx(3e4)
    for key in ("cd", "emd", "psnr", "ssim"):
        assert math.isfinite(summary["future"][key]) and math.isfinite(summary["train"][key])
    # the grid check: the estimate on a grid of half the spacing, over the 4 training frames after the first
    grid = summary["grid_check"]
    assert (grid["dx"], grid["fine_dx"], grid["frames"]) == (0.04, 0.02, 4)
    assert grid["shift_m"] > 0 and grid["residual_m"] > 0 and grid["converged"] == (grid["shift_m"] <= grid["residual_m"])
    # oracle geometry: the first frame's particles are the observed cloud (up to the fitted offsets),
    # so the misfit there is the floor the later frames are judged against
    assert 0 <= grid["first_frame_residual_m"] < grid["residual_m"]
    assert "grid check: halving dx (0.04 -> 0.02 m)" in printed and "grid_check_s" in summary["timings_s"]
    ev = json.loads((out / "evaluation" / "evaluation.json").read_text())
    assert len(ev["geometry"]["cd_per_frame"]) == 6 and ev["n_train"] == 5
    # how far the prediction moves across the parameters' intervals: every frame, none at frame 0, printed
    spread = summary["forecast_spread"]
    assert len(spread["spread_mm"]) == 6 and spread["spread_mm"][0] == pytest.approx(0.0, abs=1e-3)
    assert spread["rollouts"] >= 2 and max(spread["spread_mm"]) > 0 and spread["n_train"] == 5
    assert "across the parameters' intervals the prediction moves" in printed
    assert "forecast_spread_s" in summary["timings_s"]
    assert set(ev["images"]) == {"all_cameras", "fitted_cameras", "held_out_cameras"}
    for name in ("trajectories.png", "per_frame.png", "prediction_vs_truth_future.png", "grid_check.png"):
        assert (out / "report" / name).stat().st_size > 1000
    est = json.loads((out / "physics" / "estimate.json").read_text())
    assert est["iterations"] == 8
    # the fitting cameras' masks were checked against their poses before anything was trained
    silhouettes = json.loads((out / "silhouettes.json").read_text())
    assert silhouettes["cameras"] == [1, 5, 9] and silhouettes["suspect"] is None and "message" in silhouettes
    assert summary["silhouettes"] == silhouettes and "silhouettes disagree" not in printed
    # a rerun finds the finished fit and does not train again
    mtime = (out / "physics" / "checkpoints" / "last.ckpt").stat().st_mtime
    assert main(args) == 0
    assert json.loads((out / "physics" / "estimate.json").read_text())["iterations"] == 8
    assert (out / "physics" / "checkpoints" / "last.ckpt").stat().st_mtime == mtime


def test_run_rejects_bad_settings(scene, tmp_path):
    """More cases, with exit codes and nothing written, in tests/test_run_safety.py."""
    with pytest.raises(SystemExit, match="unknown field"):
        bad = tmp_path / "bad.yaml"
        bad.write_text("scene: x\nspeed: 3\n")
        main(["run", "--config", str(bad)])
    with pytest.raises(SystemExit, match="scene = .*missing.*: this folder does not exist") as exc:
        main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    from toolkit.pipeline import RunSettings, run_pipeline
    from toolkit.run_validation import SettingsError

    with pytest.raises(SettingsError, match="geometry = 'lidar': expected 'stage0' or 'oracle'"):
        run_pipeline(RunSettings(scene=str(scene), out=str(tmp_path / "o2"), geometry="lidar"))
    assert not (tmp_path / "o").exists() and not (tmp_path / "o2").exists()

"""``projo4d stage0``: stage 0 alone, in a run folder a later ``projo4d run`` reuses (issue #19).

The stage-0 folder has the same identity rules as a run (refused on other stage-0 settings, nothing
written on a bad setting); a whole run with the same stage-0 settings takes it over without training
stage 0 again and finishes with the numbers of a run that did everything in one go.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from tests.physics_fixtures import tiny_scene
from toolkit.cli import main
from toolkit.pipeline import RunSettings, run_pipeline

pytestmark = pytest.mark.xdist_group("run_safety")

#: the 60-iteration stage 0 of tests/test_run_safety.py (densifies, logs once at iteration 50)
STAGE0 = {"preset": "tiny", "iterations": 60, "warmup": 10, "densify_from": 10, "densify_until": 40, "densify_interval": 10,
          "position_lr_max_steps": 60, "deform_lr_max_steps": 60}
SIM = {"dx": 0.04, "substeps": 30}
CURRICULUM = "XAS:2,XASM:2"


def _flags(scene: Path, out: Path, **over) -> list[str]:
    flags = {"--out": str(out), "--stage0": json.dumps(STAGE0), "--sim": json.dumps(SIM), "--curriculum": CURRICULUM,
             "--device": "cpu", **over}
    return [str(scene)] + [x for k, v in flags.items() for x in (k, v)]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return tiny_scene(tmp_path_factory.mktemp("stage0_cmd_scene"))


@pytest.fixture(scope="module")
def stage0_run(tmp_path_factory, scene):
    """``projo4d stage0`` into a fresh folder; returns the folder and what it printed."""
    out = tmp_path_factory.mktemp("stage0_cmd") / "run"
    assert main(["stage0", *_flags(scene, out)]) == 0
    return out


def test_stage0_alone_writes_its_artifacts_and_a_stage0_identity(stage0_run):
    out = stage0_run
    summary = json.loads((out / "stage0" / "summary.json").read_text())
    assert summary["iterations"] == 60 and summary["n_gaussians"] >= 100
    assert (out / "stage0" / "last.ckpt").is_file() and (out / "stage0" / "gaussians.ply").is_file()
    assert [float(summary["last_logged"]["train/iteration"])] == [50.0]  # the tiny schedule logs every 50
    assert summary["last_logged"]["train/psnr"] > 0
    coverage = summary["coverage"]  # how much of each training frame's masks the Gaussians cover
    assert coverage == json.loads((out / "stage0" / "coverage.json").read_text())
    assert coverage["cameras"] == 3 and len(coverage["per_frame_min"]) >= 2 and coverage["per_frame_min"][0] > 0.5
    assert coverage["lost_frames"] == [i for i, c in enumerate(coverage["per_frame_min"]) if c < coverage["threshold"]]
    identity = json.loads((out / "run.json").read_text())
    assert identity["stage"] == "stage0"
    assert sorted(identity["settings"]) == ["cameras", "downscale", "geometry", "n_train", "renderer", "seed", "stage0"]
    assert identity["settings"]["stage0"] == STAGE0
    # only stage 0 ran
    assert not any((out / name).exists() for name in ("continuum", "physics_input.pt", "physics", "summary.json"))


def test_rerunning_stage0_resumes_without_training(stage0_run, scene, monkeypatch, capsys):
    from toolkit.scene.stage0 import Gaussians4DModule

    def no_training(*args, **kwargs):
        raise AssertionError("stage 0 trained again")

    monkeypatch.setattr(Gaussians4DModule, "training_step", no_training)
    before = (stage0_run / "stage0" / "gaussians.ply").read_bytes()
    assert main(["stage0", *_flags(scene, stage0_run)]) == 0
    assert "stage 0: 60 iterations" in capsys.readouterr().out
    assert (stage0_run / "stage0" / "gaussians.ply").read_bytes() == before


def test_other_stage0_settings_are_refused_and_nothing_is_written(stage0_run, scene, capsys):
    before = {p: p.stat().st_mtime_ns for p in stage0_run.rglob("*") if p.is_file()}
    for command in ("stage0", "run"):
        with pytest.raises(SystemExit) as exc:
            main([command, *_flags(scene, stage0_run, **{"--seed": "3"})])
        err = capsys.readouterr().err.strip()
        assert exc.value.code == 2 and len(err.splitlines()) == 1, err
        assert "holds another stage 0" in err and "seed: 0 in the folder, 3 asked" in err, err
        assert f"projo4d {command} --resume" in err and "--overwrite" in err, err
    assert {p: p.stat().st_mtime_ns for p in stage0_run.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize("flags,message", [
    ({"--stage0": "small"}, "stage0 = 'small': expected 'full', 'tiny'"),
    ({"--material": "jelly"}, "unknown material"),
    ({"--geometry": "oracle"}, "'oracle' geometry has none"),
], ids=["stage0", "material", "oracle"])
def test_bad_settings_fail_in_one_line_before_any_work(scene, tmp_path, capsys, flags, message):
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        main(["stage0", *_flags(scene, out, **flags)])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and err.startswith("projo4d stage0: ") and len(err.splitlines()) == 1, err
    assert message in err, err
    assert not out.exists()


def test_the_run_config_is_read_and_unknown_keys_are_refused(scene, tmp_path, capsys):
    config = tmp_path / "run.yaml"
    config.write_text(f"run:\n  stage0: {json.dumps(STAGE0)}\n  stage0_iterations: 5\n")
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        main(["stage0", str(scene), "--config", str(config), "--out", str(out), "--device", "cpu"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and "run.stage0_iterations" in err and "valid keys" in err, err
    assert not out.exists()


def test_a_later_run_reuses_stage0_and_matches_a_run_done_in_one_go(stage0_run, scene, tmp_path, monkeypatch):
    """The headline contract: ``stage0`` then ``run`` == ``run`` alone, and stage 0 is not trained twice."""
    import shutil

    from toolkit.scene.stage0 import Gaussians4DModule

    out = tmp_path / "run"
    shutil.copytree(stage0_run, out)
    calls = []
    original = Gaussians4DModule.training_step
    monkeypatch.setattr(Gaussians4DModule, "training_step", lambda self, *a, **k: calls.append(1) or original(self, *a, **k))
    assert main(["run", *_flags(scene, out)]) == 0
    assert calls == []  # stage 0 was reused
    identity = json.loads((out / "run.json").read_text())
    assert "stage" not in identity and identity["settings"]["curriculum"] == CURRICULUM  # the whole run took it over
    monkeypatch.undo()

    straight = tmp_path / "straight"
    s = RunSettings(scene=str(scene), out=str(straight), stage0=STAGE0, sim=SIM, curriculum=CURRICULUM, device="cpu")
    run_pipeline(s)
    a, b = (json.loads((p / "summary.json").read_text()) for p in (out, straight))
    assert a["parameters"] == b["parameters"] and a["future"] == b["future"] and a["train"] == b["train"]
    ia, ib = (torch.load(p / "physics_input.pt", weights_only=True) for p in (out, straight))
    assert torch.equal(ia["particles"], ib["particles"]) and torch.equal(ia["gaussians"]["means"], ib["gaussians"]["means"])
    # this short stage 0 loses the object in its later frames: their surfaces are no measurement, so
    # they are left out of the geometric loss (empty), and the summary names them
    lost = json.loads((out / "stage0" / "coverage.json").read_text())["lost_frames"]
    assert lost and a["stage0_coverage"]["lost_frames"] == lost
    assert [f for f, sf in enumerate(ia["surfaces"][:len(a["stage0_coverage"]["per_frame_min"])]) if len(sf) == 0] == [f for f in lost if f > 0]

    # stage 0 into the folder of the whole run: checked on the stage-0 settings, the run's records kept
    before = (out / "run.json").read_text(), (out / "settings.json").read_text()
    assert main(["stage0", *_flags(scene, out, **{"--material": "sand"})]) == 0
    assert ((out / "run.json").read_text(), (out / "settings.json").read_text()) == before

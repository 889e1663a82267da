"""A stage 0 whose Gaussians leave the continuum empty stops with a message that says why and what
to do, not with a shape error from deep inside (seen on a full-size GPU run whose shortened stage 0
ended at PSNR 17 dB)."""

from __future__ import annotations

import json

import pytest
import yaml

from tests.physics_fixtures import tiny_scene
from toolkit.cli import main

STAGE0 = {"preset": "tiny", "iterations": 30, "warmup": 10, "densify_from": 10, "densify_until": 20, "densify_interval": 10}


def test_an_empty_continuum_gives_a_clear_error(tmp_path, capsys):
    """No voxel reaches the interior threshold (a density above any stage 0 can give), so the
    continuum is empty: the run stops there, in one line that names stage 0's quality and the fix."""
    scene = tiny_scene(tmp_path / "tiny")
    config = tmp_path / "run.yaml"
    config.write_text(yaml.safe_dump({"run": {"continuum": {"density_min": 2.0}}}))
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        main(["run", str(scene), "--out", str(out), "--config", str(config), "--stage0", json.dumps(STAGE0),
              "--sim", json.dumps({"dx": 0.04, "substeps": 30}), "--curriculum", "XAS:1", "--device", "cpu"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2
    message = err[-1]
    assert message.startswith("projo4d run: the continuum found no particles") and "3 training views" in message, message
    assert "PSNR" in message and "train it longer" in message and str(out / "stage0" / "logs") in message, message
    assert "density_min 2.0" in message and str(out / "continuum" / "stats.json") in message, message  # the step that emptied it
    assert json.loads((out / "continuum" / "stats.json").read_text())["n_particles"] == 0
    assert not (out / "physics_input.pt").exists()  # nothing half-built left behind

"""The command line: the demo recovers what it simulated; the info command lists the registries."""

from __future__ import annotations

import json
import math

from toolkit.cli import main


def test_materials_json(capsys):
    assert main(["materials", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert set(info["materials"]) >= {"neo_hookean", "neo_hookean_simplicits", "newtonian", "non_newtonian", "plasticine", "sand"}
    assert {"air_drag", "ground_friction", "extra_acceleration", "wall"} <= set(info["effects"])
    assert "torch" in info["renderers"] and "warp" in info["renderers"]
    nu = next(p for p in info["materials"]["neo_hookean"] if p["name"] == "nu")
    assert nu["transform"] == "tanh" and nu["range"] == [-0.99, 0.49]


def test_demo_recovers_parameters(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--frames", "8", "--iterations", "25", "--size", "32", "--device", "cpu"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    # E starts 0.8 decades off and v0 at zero; both are recovered through the simulator
    assert summary["log10_E_error"] < 0.2
    assert summary["v0_mae"] < 0.1
    assert (tmp_path / "strip.png").stat().st_size > 1000
    assert any(name.startswith("simulation.") for name in summary["outputs"])
    assert math.isfinite(summary["final_loss"])


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "demo" in capsys.readouterr().out

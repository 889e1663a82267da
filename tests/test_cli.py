"""The command line: the demo recovers what it simulated; the info command lists the registries."""

from __future__ import annotations

import json

from toolkit.cli import main


def test_materials_json(capsys):
    assert main(["materials", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert set(info["materials"]) >= {"neo_hookean", "neo_hookean_simplicits", "newtonian", "non_newtonian", "plasticine", "sand"}
    assert {"air_drag", "ground_friction", "extra_acceleration", "wall"} <= set(info["effects"])
    assert "torch" in info["renderers"] and "warp" in info["renderers"]
    nu = next(p for p in info["materials"]["neo_hookean"] if p["name"] == "nu")
    assert nu["transform"] == "tanh" and nu["range"] == [-0.99, 0.49] and nu["fit_range"] == [0.0, 0.49]


def test_demo_settings_match_the_config_file():
    """configs/demo.yaml documents the demo's run settings: they must not drift apart."""
    import argparse
    from pathlib import Path

    from toolkit.commands.demo import DEMO_RUN
    from toolkit.commands.run import configure, settings_from_args

    p = argparse.ArgumentParser()
    configure(p)
    root = Path(__file__).resolve().parents[1]
    s = settings_from_args(p.parse_args(["some/scene", "--config", str(root / "configs" / "demo.yaml")]))
    for key, value in DEMO_RUN.items():
        assert getattr(s, key) == value, key


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "demo" in capsys.readouterr().out

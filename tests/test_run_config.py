"""One config system: ``projo4d run --config`` carries every key of configs/ (or refuses it in one
line), ``run --help`` shows defaults, and ``projo4d fit`` keeps the user's loggers and callbacks."""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path

import pytest
import yaml

from toolkit.cli import main
from toolkit.commands.run import configure, settings_from_args
from toolkit.pipeline import RunSettings
from toolkit.run_config import MODULE_OPTIONS, RUN_MODEL_KEYS, TRAINER_KEYS

CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))
_DEVICE = {"auto": "auto", "cpu": "cpu", "gpu": "cuda", "cuda": "cuda"}


def _settings(*argv: str) -> RunSettings:
    parser = argparse.ArgumentParser()
    configure(parser)
    return settings_from_args(parser.parse_args(list(argv)))


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.yaml"
    path.write_text(text)
    return path


def test_the_model_keys_are_exactly_the_module_arguments():
    """RUN_MODEL_KEYS + MODULE_OPTIONS + input_path = InversePhysicsModule's arguments, so a new
    module argument cannot be silently dropped by `projo4d run` (this test fails until it is mapped)."""
    from toolkit.physics import InversePhysicsModule

    params = set(inspect.signature(InversePhysicsModule.__init__).parameters) - {"self"}
    assert set(RUN_MODEL_KEYS) | set(MODULE_OPTIONS) | {"input_path"} == params
    assert set(RUN_MODEL_KEYS) <= set(RunSettings.__dataclass_fields__)
    assert not set(MODULE_OPTIONS) & set(RunSettings.__dataclass_fields__)


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: p.stem)
def test_every_shipped_config_loads_with_no_key_dropped(config, tmp_path):
    cfg = yaml.safe_load(config.read_text())
    s = _settings(str(tmp_path / "scene"), "--config", str(config))
    for key, value in (cfg.get("run") or {}).items():
        assert getattr(s, key) == value, f"run.{key}"
    for key, value in (cfg.get("model") or {}).items():
        if key == "curriculum" and isinstance(value, dict):
            assert (s.curriculum, s.curriculum_options) == (value["class_path"], value.get("init_args") or {})
        elif key in MODULE_OPTIONS:
            assert s.model_options[key] == value, f"model.{key}"
        else:
            assert getattr(s, key) == value, f"model.{key}"
    trainer = cfg.get("trainer") or {}
    assert set(trainer) <= set(TRAINER_KEYS)
    if "accelerator" in trainer:
        assert s.device == _DEVICE[trainer["accelerator"]]
    # the run folder: runs/<scene name> (trainer.default_root_dir is projo4d fit's folder)
    assert s.out == str(Path("runs") / "scene")


def test_every_module_argument_reaches_the_module(tmp_path):
    """A config with every InversePhysicsModule argument: each lands in RunSettings and, through
    make_physics_module, in the module (values chosen away from the defaults)."""
    from tests.physics_fixtures import tiny_scene
    from toolkit.physics.oracle import oracle_input
    from toolkit.pipeline import make_physics_module

    path = tmp_path / "physics_input.pt"
    oracle_input(tiny_scene(tmp_path / "scene"), particle_spacing=0.04).save(path)
    config = _write(tmp_path, """
model:
  material: neo_hookean
  initial_params: {E: 20000.0, nu: 0.3}
  optimize_params: [E]
  curriculum: "S:2"
  renderer: torch
  sim: {dx: 0.04, substeps: 30}
  seed: 3
  lambda_geometry: 0.5
  learning_rates: {velocity: 0.2}
  optimize_gravity: true
  effects: {air_drag: {linear: 0.5}}
  v0_init: [0.1, -0.2, 0.3]
  lambda_image: 0.25
  ssim_weight: 0.4
  warmup_fraction: 0.3
  embedding_neighbours: 4
  embedding: affine
trainer: {accelerator: cpu, default_root_dir: RUN}
""")
    s = _settings(str(tmp_path / "scene"), "--config", str(config), "--seed", "7")
    assert s.model_options == {"effects": {"air_drag": {"linear": 0.5}}, "v0_init": [0.1, -0.2, 0.3],
                               "lambda_image": 0.25, "ssim_weight": 0.4, "warmup_fraction": 0.3, "embedding_neighbours": 4,
                               "embedding": "affine"}
    assert (s.seed, s.device, s.optimize_gravity, s.lambda_geometry) == (7, "cpu", True, 0.5)  # the flag wins
    assert s.out == str(Path("runs") / "scene")  # not trainer.default_root_dir (projo4d fit's folder)
    m = make_physics_module(s, path)
    assert (m.lambda_image, m.ssim_weight, m.warmup_fraction, m.lambda_geometry) == (0.25, 0.4, 0.3, 0.5)
    assert m.effect_init == {"air_drag": {"linear": 0.5}} and m.optimize_gravity is True
    assert m.v0.detach().tolist() == pytest.approx([0.1, -0.2, 0.3])
    assert m.embed_index.shape[-1] == 24 and m.seed == 7  # affine: at least 24 neighbours, whatever was asked


@pytest.mark.parametrize("text, where, key", [
    ("model: {material: sand, ssim_wieght: 0.3}\n", "model", "ssim_wieght"),
    ("trainer: {accelerator: cpu, max_epochs: 3}\n", "trainer", "max_epochs"),
    ("run: {cameras: all, stage_0: tiny}\n", "run", "stage_0"),
    ("model: {material: sand}\noptimizer: {lr: 0.1}\n", "section", "optimizer"),
])
def test_an_unknown_key_fails_in_one_line_naming_it_and_the_valid_ones(tmp_path, capsys, text, where, key):
    err = _config_error(tmp_path, capsys, text)
    assert f"{where}.{key}" in err and "unknown key" in err and "valid keys" in err
    valid = {"model": "ssim_weight", "trainer": "default_root_dir", "run": "stage0", "section": "trainer"}[where]
    assert valid in err


@pytest.mark.parametrize("text, field, message", [
    ("model: {ssim_weight: 2.0}\n", "model_options.ssim_weight", "[0.0, 1.0]"),
    ("model: {effects: {air_drag: {linaer: 1.0}}}\n", "model_options.effects.air_drag.linaer", "quadratic"),
    ("model: {effects: {wind: {speed: 1.0}}}\n", "model_options.effects", "air_drag"),
    ("model: {v0_init: [1, 2]}\n", "model_options.v0_init", "3 finite numbers"),
    ("model: {material_init: grid}\n", "model_options.material_init", "'search_joint'"),
    ("model: {embedding_neighbours: 0}\n", "model_options.embedding_neighbours", ">= 1"),
    ("model: {embedding: nearest}\n", "model_options.embedding", "'idw'"),
    ("model: {gaussian_shape: soft}\n", "model_options.gaussian_shape", "'deformed'"),
    ("model: {body_shift: [0.01, .nan, 0]}\n", "model_options.body_shift", "3 finite numbers"),
    ("model: {body_shift: 0.01}\n", "model_options.body_shift", "rigid translation"),
    ("model: {uncertainty_options: {fine_gaurd: true}}\n", "model_options.uncertainty_options", "fine_guard"),
    ("model: {uncertainty_options: {fine_guard: 1}}\n", "model_options.uncertainty_options", "true or false"),
    ("model: {uncertainty_options: {level: 1.5}}\n", "model_options.uncertainty_options", "(0, 1)"),
    ("model: {input_path: x.pt}\n", "model.input_path", "writes the physics input itself"),
    ("trainer: {accelerator: tpu}\n", "trainer.accelerator", "auto, cpu, gpu, cuda"),
    ("foo: 1\n", "foo", "unknown field"),
])
def test_bad_values_fail_before_any_work(tmp_path, capsys, text, field, message):
    err = _config_error(tmp_path, capsys, text)
    assert field in err and message in err, err


def _config_error(tmp_path, capsys, text: str) -> str:
    """``projo4d run --config`` with ``text``: exit 2, one line on stderr (returned), nothing written."""
    config = _write(tmp_path, text)
    with pytest.raises(SystemExit) as exc:
        main(["run", str(tmp_path / "no_scene"), "--config", str(config), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out").exists()
    return err


def test_run_folders_recorded_before_model_options_keep_their_identity():
    """model_options defaults to None, so a run.json written without the field still matches."""
    from dataclasses import asdict

    from toolkit.run_folder import NEUTRAL_SETTINGS, _differences

    s = RunSettings(scene="s")
    new = {"scene_fingerprint": "x", "scene": "s",
           "settings": {k: v for k, v in asdict(s).items() if k not in NEUTRAL_SETTINGS}}
    old = {**new, "settings": {k: v for k, v in new["settings"].items() if k != "model_options"}}
    assert _differences(old, new) == []
    changed = {**new, "settings": {**new["settings"], "model_options": {"ssim_weight": 0.4}}}
    assert _differences(new, changed) == ["model_options: None in the folder, {'ssim_weight': 0.4} asked"]


def test_run_help_shows_every_default(capsys):
    parser = argparse.ArgumentParser()
    configure(parser)
    d = RunSettings.__dataclass_fields__
    for action in parser._actions:
        if action.option_strings and action.option_strings[0] not in ("-h", "--config", "--resume", "--overwrite"):
            assert action.help and "default" in action.help, action.option_strings
    with pytest.raises(SystemExit) as exc:
        main(["run", "--help"])
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert exc.value.code == 0
    for flag, shown in [("--seed", f"(default: {d['seed'].default})"), ("--downscale", f"(default: {d['downscale'].default})"),
                        ("--device", f"(default: {d['device'].default})"), ("--material", f"(default: {d['material'].default})"),
                        ("--n-train", "(default: the scene's recorded split")]:
        assert flag in out and shown in out, flag


# ------------------------------------------------------------------ projo4d fit: the user's loggers and callbacks
@pytest.fixture(scope="module")
def fit_input(tmp_path_factory) -> Path:
    from tests.physics_fixtures import tiny_scene
    from toolkit.physics.oracle import oracle_input

    root = tmp_path_factory.mktemp("fit_input")
    path = root / "physics_input.pt"
    oracle_input(tiny_scene(root / "scene"), particle_spacing=0.04).save(path)
    return path


def _fit(fit_input: Path, out: Path, *extra: str) -> dict:
    import json

    assert main(["fit", "--model.input_path", str(fit_input), "--model.curriculum", "XAS:2,XASM:2",
                 "--model.renderer", "torch", "--model.sim.dx", "0.04", "--model.sim.substeps", "30",
                 "--trainer.accelerator", "cpu", "--trainer.enable_progress_bar", "false",
                 "--trainer.default_root_dir", str(out), *extra]) == 0
    return json.loads((out / "estimate.json").read_text())


def test_fit_keeps_a_logger_the_user_configures(fit_input, tmp_path):
    import csv
    import json

    logs = tmp_path / "my_logs"
    est = _fit(fit_input, tmp_path / "run", "--trainer.logger", "CSVLogger", "--trainer.logger.save_dir", str(logs),
               "--trainer.logger.name", "mine")
    assert est["iterations"] == 4
    rows = {int(r["step"]): r for r in csv.DictReader((logs / "mine" / "version_0" / "metrics.csv").open())}
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    # every iteration's loss is in the user's logger, equal to the run's own history
    assert [float(rows[i]["loss/total"]) for i in range(4)] == pytest.approx([h["loss/total"] for h in history])
    assert not (tmp_path / "run" / "logs").exists()  # ours did not replace it
    assert (logs / "mine" / "version_0" / "config.yaml").is_file()  # the resolved config sits with the user's logs
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()  # our checkpoints are still written


def test_fit_default_loggers_and_a_model_checkpoint_beside_ours(fit_input, tmp_path):
    import json

    import torch

    ckpts = tmp_path / "mc"
    est = _fit(fit_input, tmp_path / "run", "--trainer.callbacks+=ModelCheckpoint",
               "--trainer.callbacks.dirpath", str(ckpts), "--trainer.callbacks.filename", "final")
    assert est["iterations"] == 4
    assert (tmp_path / "run" / "logs" / "version_0" / "metrics.csv").is_file()  # default CSV logger
    saved = torch.load(ckpts / "final.ckpt", map_location="cpu", weights_only=True)  # Lightning's ModelCheckpoint
    assert saved["projo4d"]["curriculum_step"] == 4  # it saved the finished curriculum (at the epoch's end) ...
    last = json.loads((tmp_path / "run" / "history.json").read_text())[-1]
    assert saved["state_dict"]["v0"].tolist() == pytest.approx([last["v0/x"], last["v0/y"], last["v0/z"]])  # ... its v0
    ours = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ours["projo4d"]["curriculum_step"] == 4  # and ours is still written (after the uncertainty's prior step)


def test_fit_refuses_an_unknown_run_key_and_reads_the_same_file_as_run(fit_input, tmp_path, capsys):
    """One config file for `fit`, `run` and `stage0`: `fit` checks the `run:` keys the same way (issue #19)."""
    import yaml

    config = tmp_path / "c.yaml"
    config.write_text(yaml.safe_dump({"run": {"stage0": "tiny", "stage0_iterations": 5}, "model": {"input_path": str(fit_input)}}))
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(config), "--trainer.accelerator", "cpu", "--trainer.default_root_dir", str(tmp_path / "f")])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1, err
    assert "run.stage0_iterations" in err and "valid keys:" in err and ", stage0, " in err, err
    assert not (tmp_path / "f").exists()  # refused before any work
    # a shipped config's run: section passes fit's check (and is what `projo4d run` reads)
    from toolkit import find_config
    from toolkit.run_config import check_run_section, settings_from_sections

    cfg = yaml.safe_load(find_config("synthetic_elastic").read_text())
    check_run_section(cfg["run"], "synthetic_elastic.yaml")
    assert settings_from_sections(cfg, "synthetic_elastic.yaml")["stage0"] == cfg["run"]["stage0"]


def test_stage0_iterations_compress_gics_schedule(tmp_path):
    """`projo4d run --stage0-iterations N` is GIC's schedule with every iteration count scaled to N
    (Stage0Schedule.compressed), the same mapping `projo4d benchmark --stage0-iterations` writes;
    it refuses to be combined with --stage0 and counts below 100, naming the flag."""
    from toolkit.benchmark.plan import scaled_stage0
    from toolkit.run_validation import SettingsError
    from toolkit.scene.stage0 import Stage0Schedule

    s = _settings(str(tmp_path / "scene"), "--stage0-iterations", "5000")
    assert s.stage0 == scaled_stage0(5000)
    schedule = Stage0Schedule.from_dict({k: v for k, v in s.stage0.items() if k != "preset"})
    assert schedule == Stage0Schedule.compressed(5000)
    assert (schedule.iterations, schedule.warmup, schedule.densify_until, schedule.densify_interval) == (5000, 375, 1875, 12)
    with pytest.raises(SettingsError, match="--stage0-iterations.*not both"):
        _settings(str(tmp_path / "scene"), "--stage0-iterations", "5000", "--stage0", "tiny")
    with pytest.raises(SettingsError, match="--stage0-iterations.*>= 100"):
        _settings(str(tmp_path / "scene"), "--stage0-iterations", "50")

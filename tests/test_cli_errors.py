"""The CLI's error boundary, quiet output and progress bars (issue 15, items 6-8).

Each mistake gives one line ``projo4d <command>: ...`` on stderr, the documented exit status
(2: input, 1: failure, 130: interrupted), and leaves nothing half-written; ``--debug`` gives the
traceback. Values starting with ``-`` parse; Warp's and Lightning's chatter is hidden unless
``--verbose``; the bars count the module's own iterations against the right total.
"""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest

from toolkit.cli import join_negative_values, main, split_global_flags

ROOT = Path(__file__).resolve().parents[1]


def _cli(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``projo4d ARGV`` in a fresh process, as a user runs it (no terminal: no bars)."""
    env = {**os.environ, "PYTHONWARNINGS": "default"}
    env.pop("PROJO4D_VERBOSE", None)
    return subprocess.run([sys.executable, "-m", "toolkit.cli", *argv], capture_output=True, text=True, cwd=ROOT,
                          timeout=timeout, env=env)


def _one_line(text: str) -> str:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("Warp CUDA warning")]
    assert len(lines) == 1, text
    return lines[0]


# ------------------------------------------------------------------------ ordinary mistakes, real processes


def test_run_with_a_missing_scene_is_one_line_and_writes_nothing(tmp_path):
    out = tmp_path / "out"
    res = _cli("run", str(tmp_path / "no_such_scene"), "--out", str(out), "--device", "cpu")
    assert res.returncode == 2
    line = _one_line(res.stderr)
    assert line.startswith("projo4d run: ") and "no_such_scene" in line and "does not exist" in line
    assert "Traceback" not in res.stderr and res.stdout == ""
    assert not out.exists()


_NO_TORCH_YET = r"""
import sys
from toolkit.cli import main
try:
    main(sys.argv[1:])
except SystemExit as exc:
    print("status", exc.code)
print("loaded", sorted(m for m in ("torch", "pytorch_lightning", "toolkit.pipeline", "toolkit.data") if m in sys.modules))
"""


@pytest.mark.parametrize("command", ["run", "stage0"])
def test_a_settings_mistake_is_reported_before_torch_loads(tmp_path, command):
    """A missing scene folder or a bad plain field needs neither torch nor the scene's contents:
    the message comes before the heavy imports (about 1 s instead of 9)."""
    for args, field in (([str(tmp_path / "no_such_scene")], "scene = "),
                        ([str(tmp_path), "--downscale", "0"], "downscale = 0")):
        res = subprocess.run([sys.executable, "-c", _NO_TORCH_YET, command, *args, "--out", str(tmp_path / "out")],
                             capture_output=True, text=True, cwd=ROOT, timeout=120)
        assert res.stdout.splitlines()[-2:] == ["status 2", "loaded []"], res.stdout + res.stderr
        assert f"projo4d {command}: {field}" in res.stderr
    assert not (tmp_path / "out").exists()


def test_generate_with_an_unknown_material_is_one_line(tmp_path):
    out = tmp_path / "scene"
    res = _cli("generate", "scene", "--out", str(out), "--material", "jelly")
    assert res.returncode == 2
    line = _one_line(res.stderr)
    assert line.startswith("projo4d generate scene: argument --material: invalid choice: 'jelly'")
    assert "neo_hookean" in line and "--help" in line
    assert not out.exists()


def _mistake(capsys, *argv: str) -> str:
    """Run ``projo4d ARGV`` in process; it must exit with status 2 after printing exactly one line."""
    with pytest.raises(SystemExit) as exc:
        main(list(argv))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err == str(exc.value) + "\n" and err.count("\n") == 1, err
    return err.strip()


def test_bad_numbers_json_and_unknown_flags_are_one_line(tmp_path, capsys):
    out = tmp_path / "out"
    assert "expected 3 comma-separated numbers" in _mistake(capsys, "generate", "scene", "--out", str(out), "--v0", "1,0")
    line = _mistake(capsys, "run", "some/scene", "--out", str(out), "--sim", '{"dx": 0.02,')
    assert line.startswith("projo4d run: argument --sim: not valid JSON: '{\"dx\": 0.02,'")
    assert _mistake(capsys, "demo", "--out", str(out), "--speed", "3") == (
        "projo4d: unrecognized arguments: --speed 3 (see `projo4d --help`)")
    assert "invalid int value: 'two'" in _mistake(capsys, "run", "s", "--out", str(out), "--n-train", "two")
    assert not out.exists()


def test_demo_into_a_file_is_one_line(tmp_path, capsys):
    """An output folder that is a file: the OS error names the path (status 2), no traceback."""
    blocker = tmp_path / "taken"
    blocker.write_text("not a folder")
    line = _mistake(capsys, "demo", "--out", str(blocker), "--device", "cpu")
    assert line.startswith("projo4d demo: ") and "taken" in line
    assert blocker.read_text() == "not a folder"


def test_debug_shows_the_traceback_anywhere_on_the_line(tmp_path):
    res = _cli("run", str(tmp_path / "no_such_scene"), "--out", str(tmp_path / "o"), "--debug")
    assert res.returncode == 1  # the exception propagates: Python prints it and exits with 1
    assert "Traceback (most recent call last)" in res.stderr and "no_such_scene" in res.stderr
    assert not (tmp_path / "o").exists()


def test_fit_goes_through_the_same_boundary(tmp_path):
    res = _cli("fit", "--model.bogus", "3", "--trainer.default_root_dir", str(tmp_path / "fit"))
    assert res.returncode == 2
    assert _one_line(res.stderr) == "projo4d fit: unrecognized arguments: --model.bogus 3 (see `projo4d fit --help`)"
    assert not (tmp_path / "fit").exists()


# ------------------------------------------------------------------------ the boundary's rules, in process


@pytest.fixture
def fake_command(monkeypatch):
    """Register a command ``boom`` whose ``run`` raises what the test puts in ``box["error"]``."""
    from toolkit import cli

    box: dict = {}
    mod = types.ModuleType("_boom_command")
    mod.configure = lambda parser: parser.add_argument("--x")

    def run(args):
        raise box["error"]

    mod.run = run
    monkeypatch.setitem(sys.modules, "_boom_command", mod)
    monkeypatch.setitem(cli.COMMANDS, "boom", ("_boom_command", "raise an error"))
    return box


@pytest.mark.parametrize("error, code, text", [
    (ValueError("material = 'jelly': unknown"), 2, "projo4d boom: material = 'jelly': unknown"),
    (FileNotFoundError(2, "No such file or directory", "/x/y.pt"), 2, "projo4d boom: [Errno 2] No such file or directory: '/x/y.pt'"),
    (SystemExit("projo4d boom: the scene has 3 cameras"), 2, "projo4d boom: the scene has 3 cameras"),
    (RuntimeError("PytorchStreamReader failed"), 1,
     "projo4d boom: RuntimeError: PytorchStreamReader failed (run with --debug for the traceback)"),
    (KeyboardInterrupt(), 130, "projo4d boom: interrupted; rerun the same command to resume"),
])
def test_error_classes_map_to_status_and_one_line(fake_command, capsys, error, code, text):
    fake_command["error"] = error
    with pytest.raises(SystemExit) as exc:
        main(["boom"])
    assert exc.value.code == code
    assert str(exc.value) == text
    assert capsys.readouterr().err == text + "\n"


def test_interrupt_after_a_checkpoint_names_it(fake_command, capsys):
    from toolkit.checkpointing import RunInterrupted

    fake_command["error"] = RunInterrupted("physics fit stopped at iteration 7 of 40; saved run/physics/checkpoints/last.ckpt")
    with pytest.raises(SystemExit) as exc:
        main(["boom"])
    assert exc.value.code == 130
    assert capsys.readouterr().err == ("projo4d boom: interrupted (physics fit stopped at iteration 7 of 40; saved "
                                       "run/physics/checkpoints/last.ckpt); rerun the same command to resume\n")


def test_lightning_exit_on_ctrl_c_counts_as_interrupted(fake_command, capsys):
    def lightning_like():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemExit(1)  # what Trainer.fit does after a Ctrl-C it did not expect

    sys.modules["_boom_command"].run = lambda args: lightning_like()
    with pytest.raises(SystemExit) as exc:
        main(["boom"])
    assert exc.value.code == 130
    assert capsys.readouterr().err == "projo4d boom: interrupted; rerun the same command to resume\n"


def test_unexpected_errors_show_only_their_first_line(fake_command, capsys):
    fake_command["error"] = RuntimeError("kernel failed\n  File x.py, line 3\n    y = 1 / 0")
    with pytest.raises(SystemExit) as exc:
        main(["boom"])
    assert exc.value.code == 1
    assert capsys.readouterr().err == "projo4d boom: RuntimeError: kernel failed (run with --debug for the traceback)\n"


def test_debug_lets_the_exception_through(fake_command):
    fake_command["error"] = RuntimeError("boom")
    with pytest.raises(RuntimeError, match="boom"):
        main(["boom", "--x", "1", "--debug"])
    with pytest.raises(RuntimeError, match="boom"):
        main(["--debug", "boom"])


def test_global_flags_are_taken_anywhere_before_a_double_dash():
    assert split_global_flags(["run", "s", "--debug", "--out", "o", "--verbose"]) == (["run", "s", "--out", "o"],
                                                                                     {"--debug", "--verbose"})
    assert split_global_flags(["fit", "--", "--debug"]) == (["fit", "--", "--debug"], set())


# ------------------------------------------------------------------------ values starting with a minus sign


def test_negative_values_are_joined_only_after_options_that_take_one():
    opts = {"--v0", "--cameras"}
    assert join_negative_values(["--v0", "-0.5,0,0.4", "--cameras", "-1,2", "--flag", "-3"], opts) == [
        "--v0=-0.5,0,0.4", "--cameras=-1,2", "--flag", "-3"]
    assert join_negative_values(["--v0", "-x"], opts) == ["--v0", "-x"]  # an option, not a number: argparse decides
    assert join_negative_values(["--", "--v0", "-1"], opts) == ["--", "--v0", "-1"]


def test_generate_parses_negative_vectors():
    from toolkit.cli import _build_parser_for, _value_options
    from toolkit.synthetic.commands import spec_from_args

    argv = ["generate", "scene", "--out", "x", "--v0", "-0.5,0,0.4", "--position", "-0.1,0.3,0", "--rotation", "-20,0,0",
            "--gravity", "0,-9.8,0"]
    parser = _build_parser_for(argv)
    args = parser.parse_args(join_negative_values(argv, _value_options(parser)))
    assert args.v0 == (-0.5, 0.0, 0.4) and args.position == (-0.1, 0.3, 0.0) and args.rotation == (-20.0, 0.0, 0.0)
    spec = spec_from_args(args)
    assert tuple(spec.v0) == (-0.5, 0.0, 0.4) and tuple(spec.position) == (-0.1, 0.3, 0.0)


def test_run_parses_negative_camera_indices(tmp_path, capsys):
    from toolkit.cli import _build_parser_for, _value_options

    argv = ["run", "scene", "--cameras", "-1,2", "--param", "E=1e4"]
    parser = _build_parser_for(argv)
    assert parser.parse_args(join_negative_values(argv, _value_options(parser))).cameras == "-1,2"
    # end to end it reaches the run's own checks (an argparse error would say "expected one argument")
    with pytest.raises(SystemExit) as exc:
        main(["run", str(tmp_path / "missing"), "--cameras", "-1,2", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2 and "expected one argument" not in str(exc.value)
    assert "expected one argument" not in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------ quiet by default


def test_quiet_hides_lightning_info_but_not_warnings(monkeypatch):
    from toolkit.verbosity import configure_output

    root = logging.getLogger()
    try:
        for verbose in (False, True):
            configure_output(verbose=verbose)
            stream = io.StringIO()
            monkeypatch.setattr(sys, "stderr", stream)  # the handler writes to the stderr of the moment
            for name, level, msg in [("pytorch_lightning.utilities.rank_zero", logging.INFO, "GPU available: False"),
                                     ("pytorch_lightning.trainer.connectors.checkpoint_connector", logging.INFO,
                                      "`weights_only` was not set, defaulting to `False`."),
                                     ("lightning_fabric.utilities.seed", logging.WARNING, "seed warning"),
                                     ("toolkit.pipeline", logging.WARNING, "our warning")]:
                lg = logging.getLogger(name)
                for part in (name, name.split(".")[0]):  # Lightning imported first keeps its own handler
                    monkeypatch.setattr(logging.getLogger(part), "propagate", True)
                    monkeypatch.setattr(logging.getLogger(part), "handlers", [])
                lg.handle(lg.makeRecord(name, level, __file__, 0, msg, (), None))
            text = stream.getvalue()
            assert ("GPU available" in text) is verbose and ("weights_only" in text) is verbose
            assert "seed warning" in text and "our warning" in text
            assert os.environ["PROJO4D_VERBOSE"] == ("1" if verbose else "0")
    finally:
        configure_output(verbose=False)
        for h in [h for h in root.handlers if type(h).__name__ == "_Handler"]:
            root.removeHandler(h)


_WARP_SCRIPT = """
import sys
from toolkit.verbosity import configure_output
configure_output(verbose=sys.argv[1] == "1")
import warp as wp

@wp.kernel
def twice(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = 2.0 * a[i]

a = wp.ones(4, dtype=float, device="cpu")
wp.launch(twice, dim=4, inputs=[a], device="cpu")
print(a.numpy().sum())
"""


def test_warp_module_load_lines_only_when_verbose(tmp_path):
    script = tmp_path / "warp_quiet.py"  # Warp kernels need a source file
    script.write_text(_WARP_SCRIPT)
    for verbose in ("0", "1"):
        res = subprocess.run([sys.executable, str(script), verbose], capture_output=True, text=True, cwd=ROOT, timeout=120)
        assert res.returncode == 0, res.stderr
        assert res.stdout.strip().splitlines()[-1] == "8.0"
        printed = res.stdout + res.stderr
        assert ("load on device 'cpu'" in printed) is (verbose == "1"), printed


# ------------------------------------------------------------------------ progress bars


def test_bars_are_off_without_a_terminal_or_when_asked(monkeypatch):
    from toolkit.progress import bars_enabled

    assert not bars_enabled()  # pytest captures stdout: not a terminal
    tty = types.SimpleNamespace(isatty=lambda: True, write=lambda s: None, flush=lambda: None)
    monkeypatch.setattr(sys, "stdout", tty)
    monkeypatch.setattr(sys, "stderr", tty)
    assert bars_enabled() and not bars_enabled(progress=False)
    monkeypatch.setenv("PROJO4D_PROGRESS", "0")
    assert not bars_enabled()


def _console():
    from rich.console import Console

    return Console(file=io.StringIO(), force_terminal=True, width=160, color_system=None)


def _physics_module(schedule: str):
    from strategies import get_strategy

    strategy = get_strategy(schedule)
    return types.SimpleNamespace(curriculum=strategy, material=types.SimpleNamespace(registry_name="neo_hookean"),
                                 stages=strategy.stages("neo_hookean"), total_iterations=strategy.total_iterations("neo_hookean"),
                                 curriculum_step=0)


def test_physics_bar_counts_the_curriculum_not_lightning_batches():
    """Old bar: "Epoch 0/0", one ahead. Now: after k iterations it reads k/total and names the stage running."""
    from toolkit.physics.callbacks import _physics_position, curriculum_progress_bar

    module = _physics_module("XAS:4@3,XASM:6")
    seen = []
    for k in range(11):
        module.curriculum_step = k
        seen.append(_physics_position(None, module))
    assert seen[0] == ("physics 1/2 XAS@3", 0, 10)
    assert seen[3] == ("physics 1/2 XAS@3", 3, 10) and seen[4] == ("physics 2/2 XASM", 4, 10)
    assert seen[10] == ("physics 2/2 XASM", 10, 10)

    console = _console()
    bar = curriculum_progress_bar(enabled=True, console=console)
    trainer = types.SimpleNamespace(loggers=[], progress_bar_metrics={"loss/total": 0.123456})
    module.curriculum_step = 3  # a resumed fit starts at its restored iteration
    bar.on_train_start(trainer, module)
    for k in range(4, 11):
        module.curriculum_step = k
        bar.on_train_batch_end(trainer, module, None, None, k)
    bar.on_train_end(trainer, module)
    text = console.file.getvalue()
    assert "physics 2/2 XASM" in text and "10/10" in text and "loss 0.1235" in text and "eta" in text
    assert "Epoch" not in text and "11/10" not in text


def test_stage0_bar_has_a_total_and_a_phase():
    from toolkit.progress import _stage0_position, stage0_progress_bar

    module = types.SimpleNamespace(schedule=types.SimpleNamespace(iterations=600, warmup=80), step=0, stop_at=None)
    assert _stage0_position(None, module) == ("stage 0 (static warm-up)", 0, 600)
    module.step = 80
    assert _stage0_position(None, module) == ("stage 0 (dynamic)", 80, 600)
    module.stop_at = 200  # a run told to stop early counts to where it stops
    assert _stage0_position(None, module)[1:] == (80, 200)

    console = _console()
    bar = stage0_progress_bar(enabled=True, console=console)
    trainer = types.SimpleNamespace(loggers=[], progress_bar_metrics={"train/loss": 0.5, "train/n_gaussians": 1234.0})
    bar.on_train_start(trainer, module)
    module.step = 200
    bar.on_train_batch_end(trainer, module, None, None, 0)
    bar.on_train_end(trainer, module)
    text = console.file.getvalue()
    assert "stage 0 (dynamic)" in text and "200/200" in text and "loss 0.5" in text and "n_gaussians 1234" in text
    assert "/--" not in text


def test_disabled_bars_draw_nothing():
    from toolkit.physics.callbacks import curriculum_progress_bar
    from toolkit.progress import step_progress

    console = _console()
    bar = curriculum_progress_bar(enabled=False, console=console)
    module = _physics_module("XAS:2")
    bar.on_train_start(types.SimpleNamespace(loggers=[], progress_bar_metrics={}), module)
    with step_progress("evaluation", 3, progress=False, console=console) as steps:
        steps.advance("x")
    assert console.file.getvalue() == "" and steps.completed == 1


def test_evaluation_bar_counts_its_steps():
    from toolkit.progress import step_progress

    console = _console()
    with step_progress("evaluation", 5, console=console) as bar:
        bar.describe("predicting 2 frames")
        for what in ("CD and EMD, frame 1", "CD and EMD, frame 2", "rendering frame 1", "rendering frame 2", "done"):
            bar.advance(what)
    text = console.file.getvalue()
    assert "5/5" in text and "evaluation: done" in text and bar.completed == 5


def test_per_frame_geometry_equals_the_sequence_metrics():
    """The slow twin: evaluation computes CD/EMD frame by frame (for its bar) exactly as the sequence functions."""
    import numpy as np

    from toolkit.evaluation import geometry_per_frame
    from toolkit.metrics import chamfer_sequence, emd_sequence

    rng = np.random.default_rng(3)
    preds = [rng.normal(size=(300, 3)) * 0.1 + t * 0.01 for t in range(4)]
    gts = [rng.normal(size=(250 + 10 * t, 3)) * 0.1 for t in range(4)]
    ticks = []
    cd, emd = geometry_per_frame(preds, gts, on_frame=ticks.append)
    assert ticks == [0, 1, 2, 3]
    assert cd == chamfer_sequence(preds, gts)[1] and emd == emd_sequence(preds, gts)[1]
    with pytest.raises(ValueError, match="4 predicted frames but 3 ground-truth clouds"):
        geometry_per_frame(preds, gts[:3])


# ------------------------------------------------------------------------ a real run: quiet, and Ctrl-C


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from tests.physics_fixtures import tiny_scene

    return tiny_scene(tmp_path_factory.mktemp("cli_errors_scene"))


def _run_args(scene: Path, out: Path, curriculum: str) -> list[str]:
    return ["run", str(scene), "--out", str(out), "--geometry", "oracle", "--config", "configs/demo.yaml",
            "--sim", '{"dx": 0.04, "substeps": 30}', "--curriculum", curriculum, "--device", "cpu"]


@pytest.mark.slow
def test_a_run_prints_its_results_and_no_chatter(tiny, tmp_path):
    res = _cli(*_run_args(tiny, tmp_path / "run", "XAS:2@3,XASM:2"), timeout=300)
    assert res.returncode == 0, res.stderr
    assert "future frames: CD" in res.stdout
    for noise in ("load on device", "Warp 1.19", "weights_only", "Tip:", "GPU available", "LeafSpec", "Epoch", "LightningCLI"):
        assert noise not in res.stdout + res.stderr, noise
    assert [ln for ln in res.stderr.splitlines() if ln.strip() and not ln.startswith("Warp CUDA warning")] == []


@pytest.mark.slow
def test_ctrl_c_is_one_line_with_status_130(tiny, tmp_path):
    import signal
    import time

    out = tmp_path / "run"
    env = {**os.environ}
    env.pop("PROJO4D_VERBOSE", None)
    proc = subprocess.Popen([sys.executable, "-m", "toolkit.cli", *_run_args(tiny, out, "XAS:400@3")], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not (out / "physics" / "logs").exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(1.0)  # a few iterations in
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    lines = [ln for ln in stderr.splitlines() if ln.startswith("projo4d run:")]
    assert len(lines) == 1 and lines[0].startswith("projo4d run: interrupted")
    assert lines[0].endswith("rerun the same command to resume")
    assert "Traceback" not in stderr and "future frames" not in stdout


def test_a_script_device_option_is_resolved_or_refused_with_its_value(capsys):
    """``parse_device_option``: ``cpu`` and ``auto`` resolve; a malformed name and (without a GPU)
    ``cuda`` end the script through ``parser.error`` (exit status 2) with the value and what is
    expected."""
    import argparse

    import torch

    from toolkit.run_validation import parse_device_option

    ap = argparse.ArgumentParser(prog="script.py")
    assert parse_device_option(ap, "cpu") == "cpu"
    assert parse_device_option(ap, "auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    expected = {"gpu0": "expected 'auto', 'cpu', 'cuda' or 'cuda:N'", "cuda:99": "CUDA device"}
    if not torch.cuda.is_available():
        expected = {**expected, "cuda": "use 'cpu' or 'auto'", "cuda:99": "use 'cpu' or 'auto'"}
    for name, why in expected.items():
        with pytest.raises(SystemExit) as stop:
            parse_device_option(ap, name)
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert f"script.py: error: device = {name!r}" in err and why in err, err

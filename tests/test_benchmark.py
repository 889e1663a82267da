"""`projo4d benchmark`, `projo4d evaluate`, `projo4d view` and the periodic evaluation (CPU, tiny).

One small benchmark (2 generated elastic scenes x 2 strategies, oracle geometry, 32 px, a few
iterations, 2 worker processes) is run once for the module and inspected by several tests.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest

from toolkit.cli import main

pytestmark = pytest.mark.xdist_group("benchmark")
ROOT = Path(__file__).resolve().parents[1]

SUITE_OVERRIDES = dict(width=32, height=32, n_frames=6, n_train_frames=5, dx=0.04, particle_spacing=0.01, substeps=80,
                       supersample=1, ground_plane=False)
FAST = ["--size", "small", "--geometry", "oracle", "--sim", '{"dx": 0.04, "substeps": 30}', "--stage1-iterations", "3",
        "--stage2-iterations", "4", "--appearance-iterations", "2", "--device", "cpu", "--periodic-eval", "2"]


def _events(text: str) -> list[dict]:
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("{") and '"event"' in line:
            out.append(json.loads(line))
    return out


@pytest.fixture(scope="module")
def suite(tmp_path_factory) -> Path:
    from toolkit.synthetic import generate_suite

    root = tmp_path_factory.mktemp("bench_suite")
    generate_suite(root, families=["neo_hookean"], scenes_per_family=2, seed=0, size="small", progress=False,
                   spec_overrides=SUITE_OVERRIDES)
    return root


@pytest.fixture(scope="module")
def bench(suite, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "b"
    args = ["benchmark", "--suite", str(suite), "--out", str(out), "--strategies", "sequential", "progressive",
            "--workers", "2", *FAST]
    t = time.perf_counter()
    rc = main(args)
    return {"out": out, "args": args, "rc": rc, "wall_s": time.perf_counter() - t}


# ------------------------------------------------------------------------------------ planning
def test_plan_shares_stage0_across_strategies(suite):
    from toolkit.benchmark import BenchmarkSpec, plan_benchmark, scenes_from_suite

    scenes = scenes_from_suite(suite)
    spec = BenchmarkSpec(scenes, ["sequential", "joint", "progressive"], cameras=[3, 2], size="small",
                         overrides={"geometry": "oracle"})
    jobs = plan_benchmark(spec, "/tmp/plan_only")
    prepares = [j for j in jobs if j.kind == "prepare"]
    fits = [j for j in jobs if j.kind == "fit"]
    assert len(prepares) == 2 * 2 and len(fits) == 2 * 2 * 3
    for f in fits:
        (dep,) = f.depends
        prep = next(p for p in prepares if p.id == dep)
        assert (prep.scene, prep.cameras) == (f.scene, f.cameras)
        assert f.extra["physics_input"] == str(Path(prep.folder) / "physics_input.pt")
    # every strategy of a scene and camera count reads the same file
    shared = {(f.scene, f.cameras): set() for f in fits}
    for f in fits:
        shared[(f.scene, f.cameras)].add(f.extra["physics_input"])
    assert all(len(v) == 1 for v in shared.values())
    # the stage-0 job does not depend on the strategies or their iterations; the fits do
    other = BenchmarkSpec(scenes, ["progressive"], cameras=[3, 2], size="small", overrides={"geometry": "oracle"},
                          iterations={"stage2_iterations": 7})
    jobs2 = {j.id: j for j in plan_benchmark(other, "/tmp/plan_only")}
    for p in prepares:
        assert jobs2[p.id].fingerprint == p.fingerprint
    f1 = next(j for j in fits if j.strategy == "progressive")
    assert jobs2[f1.id].fingerprint != f1.fingerprint
    assert jobs2[f1.id].settings["curriculum_options"]["stage2_iterations"] == 7
    # 3 views are the sparse protocol; 2 views a nested subset
    assert next(p for p in prepares if p.cameras == 3).settings["cameras"] == "sparse"
    assert next(p for p in prepares if p.cameras == 2).settings["cameras"] == [1, 5]


def test_camera_subsets_and_strategy_parsing():
    from toolkit.benchmark import BenchmarkError, BenchmarkSpec, SceneEntry, camera_subset, parse_strategy
    from toolkit.benchmark.plan import strategy_options

    assert camera_subset(3, 11) == "sparse" and camera_subset(10, 10) == "all" and camera_subset(1, 11) == [1]
    four = camera_subset(4, 11)
    assert len(four) == 4 and {1, 5, 9} <= set(four)
    e = parse_strategy("xas=XAS:100@3,XASM:150")
    assert (e.label, e.spec) == ("xas", "XAS:100@3,XASM:150")
    assert parse_strategy("XAS:5,XASM:5").label == "XAS_5_XASM_5"
    its = {"stage1_iterations": 10, "stage2_iterations": 20, "appearance_iterations": 0}
    assert strategy_options(parse_strategy("sequential"), its, "sand") == its
    assert strategy_options(parse_strategy("joint"), its, "sand") == {"iterations": 30}
    assert strategy_options(parse_strategy("progressive"), its, "sand") == {"stage1_iterations": 10, "stage2_iterations": 20}
    with pytest.raises(BenchmarkError, match="unique"):
        BenchmarkSpec([SceneEntry("a", "/x", "sand")], ["progressive", "progressive"])
    with pytest.raises(BenchmarkError, match="no option"):
        strategy_options(parse_strategy("joint", {"cycles": 2}), {}, "sand")
    # a bad option value is refused when the plan is made, before any scene or stage 0 runs
    with pytest.raises(BenchmarkError, match="strategy held .progressive.*hold_velocity must be true, false or 'auto'.*got 'yes'"):
        strategy_options(parse_strategy("held=progressive", {"hold_velocity": "yes"}), {}, "sand")
    assert strategy_options(parse_strategy("held=progressive", {"hold_velocity": True}), {}, "sand") == {"hold_velocity": True}


def test_gpus_option_reads_ids_a_single_id_and_a_count():
    from toolkit.benchmark.commands import _gpus

    assert _gpus("0,2") == ["0", "2"] and _gpus("3,") == ["3"] and _gpus(" 1 , 3 ") == ["1", "3"]
    assert _gpus("3") == ["0", "1", "2"]


def test_substeps_keep_the_configs_courant_number_on_the_final_grid():
    """The config (synthetic elastic: dx 0.02 m, 100 substeps) scaled to the final grid: the small
    preset's 0.04 m halves the substeps; an override back to 0.02 m restores them; explicit
    substeps win."""
    from toolkit.benchmark import BenchmarkSpec, SceneEntry
    from toolkit.benchmark.plan import _load_config, config_for, scene_settings

    scene = SceneEntry("a", "/x", "neo_hookean")
    cfg = _load_config(config_for("synthetic", "neo_hookean"))["sim"]
    assert cfg["dx"] == 0.02

    def sim(size, overrides):
        return scene_settings(scene, BenchmarkSpec([scene], ["progressive"], size=size, overrides=overrides))[0]["sim"]

    assert sim("full", {}) == {**sim("full", {}), "dx": 0.02, "substeps": cfg["substeps"]}
    assert (sim("small", {})["dx"], sim("small", {})["substeps"]) == (0.04, round(cfg["substeps"] / 2))
    assert (sim("small", {"sim": {"dx": 0.02}})["dx"], sim("small", {"sim": {"dx": 0.02}})["substeps"]) == (0.02, cfg["substeps"])
    assert sim("full", {"sim": {"dx": 0.01}})["substeps"] == 2 * cfg["substeps"]
    assert sim("small", {"sim": {"dx": 0.02, "substeps": 7}})["substeps"] == 7


def test_model_options_override_merges_into_the_configs():
    """--model-options reaches every job merged key by key over its config's module options (the
    non-Newtonian config's own keep theirs), and a bad value is refused with the field's name."""
    from toolkit.benchmark import BenchmarkSpec, SceneEntry
    from toolkit.benchmark.plan import _load_config, config_for, scene_settings
    from toolkit.pipeline import RunSettings
    from toolkit.run_validation import SettingsError

    for material in ("neo_hookean", "non_newtonian"):
        scene = SceneEntry("a", "/x", material)
        base = _load_config(config_for("synthetic", material)).get("model_options") or {}
        spec = BenchmarkSpec([scene], ["progressive"], size="small", overrides={"model_options": {"gaussian_shape": "deformed"}})
        got = scene_settings(scene, spec)[0]["model_options"]
        assert got == {**base, "gaussian_shape": "deformed"}
    with pytest.raises(SettingsError, match="model_options.gaussian_shape"):
        RunSettings(scene="/x", model_options={"gaussian_shape": "soft"}).validate()


def test_continuum_override_reaches_the_prepare_jobs():
    """--continuum is merged into every scene's continuum settings (a prepare field, so a stage-0
    job with other continuum settings is another job), key by key over the config's."""
    from toolkit.benchmark import BenchmarkSpec, SceneEntry
    from toolkit.benchmark.plan import PREPARE_FIELDS, scene_settings

    scene = SceneEntry("a", "/x", "neo_hookean")
    over = {"centre_stamp": "ellipsoid", "carve_depth": "opaque"}
    got = scene_settings(scene, BenchmarkSpec([scene], ["progressive"], size="small", overrides={"continuum": over}))[0]
    plain = scene_settings(scene, BenchmarkSpec([scene], ["progressive"], size="small"))[0]
    assert got["continuum"] == {**(plain.get("continuum") or {}), **over} and "continuum" in PREPARE_FIELDS


def test_bad_model_options_stop_the_benchmark_before_any_work(tmp_path, capsys):
    from toolkit.cli import main

    args = ["benchmark", "--suite", str(tmp_path / "suite"), "--generate", "--families", "newtonian", "--per-family", "1",
            "--size", "small", "--out", str(tmp_path / "bench"), "--model-options", '{"gaussian_shape": "soft"}']
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2
    assert "model_options.gaussian_shape = 'soft'" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    for bad, said in (('{"carve_depth": "median"}', "carve_depth must be 'expected' or 'opaque', got 'median'"),
                      ('{"stamp": 1}', "unknown continuum settings ['stamp']")):
        args[-2:] = ["--continuum", bad]
        with pytest.raises(SystemExit) as stop:
            main(args)
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert "--continuum" in err and said in err, err
        assert list(tmp_path.iterdir()) == []


def test_only_keeps_the_named_scenes_and_refuses_unknown_names(tmp_path, capsys):
    """--only picks scenes out of a generated suite's draws (the same draws as without it), and a
    name outside them stops the benchmark before anything is written."""
    from toolkit.benchmark.plan import BenchmarkError
    from toolkit.benchmark.scenes import only_scenes, scenes_to_generate
    from toolkit.cli import main

    every = scenes_to_generate(tmp_path / "suite", ["newtonian", "sand"], 5, size="small")
    picked = only_scenes(every, ["sand/002", "newtonian/004"])
    assert [s.name for s in picked] == ["newtonian/004", "sand/002"]
    assert [s.generate["spec"] for s in picked] == [s.generate["spec"] for s in every if s.name in ("newtonian/004", "sand/002")]
    with pytest.raises(BenchmarkError, match=r"\['sand/005'\]"):
        only_scenes(every, ["sand/005"])
    args = ["benchmark", "--suite", str(tmp_path / "suite"), "--generate", "--families", "sand", "--per-family", "2",
            "--size", "small", "--out", str(tmp_path / "bench"), "--only", "sand/002"]
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2 and "sand/002" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------ tables
def _rec(scene, strategy, cd, emd, e_err, cams=3, material="neo_hookean"):
    return {"scene": scene, "material": material, "strategy": strategy, "cameras": cams, "curriculum": "X",
            "metrics": {"cd": cd, "emd": emd, "psnr": 20.0 + cd, "ssim": 0.9, "init_cd": cd / 10},
            "errors": {"E": e_err, "nu": 0.1, "v0": 0.01, "friction_angle": 3.0}, "optimized": ["E", "nu"]}


def test_tables_mean_std_of_known_numbers():
    from toolkit.benchmark.tables import build_tables, tables_markdown

    records = [_rec("s0", "progressive", 1.0, 0.04, 0.1), _rec("s1", "progressive", 2.0, 0.06, 0.3),
               _rec("s0", "sequential", 4.0, 0.10, 0.5), _rec("s1", "sequential", 6.0, None, 0.7),
               _rec("s0", "progressive", 3.0, 0.05, 0.2, cams=1)]
    t = build_tables(records, strategies=["sequential", "progressive"])
    main3 = next(x for x in t["tables"] if x["cameras"] == 3)
    assert [r["strategy"] for r in main3["rows"]] == ["sequential", "progressive"]
    prog = next(r for r in main3["rows"] if r["strategy"] == "progressive")["values"]
    assert prog["cd"] == {"mean": 1.5, "std": 0.5, "n": 2}
    assert prog["emd"]["mean"] == pytest.approx(0.05) and prog["emd"]["std"] == pytest.approx(0.01)
    assert prog["mae:E"]["mean"] == pytest.approx(0.2) and prog["mae:E"]["std"] == pytest.approx(0.1)
    seq = next(r for r in main3["rows"] if r["strategy"] == "sequential")["values"]
    assert seq["emd"] == {"mean": 0.10, "std": 0.0, "n": 1}  # the missing value is left out
    # columns: the optimized parameters and v0, not fixed ones (friction angle of a non-sand fit)
    assert [c["key"] for c in main3["columns"]] == ["cd", "emd", "psnr", "ssim", "mae:v0", "mae:E", "mae:nu"]
    claims = [c for c in t["claims"] if c["metric"] == "cd" and c["cameras"] == 3]
    assert claims[0]["a_better"] and claims[0]["scene_wins_a"] == 2 and claims[0]["scenes"] == 2
    # paired: sequential has no EMD on s1, so both EMD means are over s0 alone
    (emd,) = [c for c in t["claims"] if c["metric"] == "emd" and c["cameras"] == 3]
    assert (emd["scenes"], emd["mean_a"], emd["mean_b"]) == (1, pytest.approx(0.04), pytest.approx(0.10))
    (abl,) = t["ablation"]
    assert abl["cameras"] == [1, 3] and abl["cells"]["progressive|1"]["init_cd"]["mean"] == pytest.approx(0.3)
    md = tables_markdown(t)
    assert "| progressive | 2 | **1.500 ± 0.500** |" in md and "Stage 0 lost" not in md
    # a fit whose stage 0 lost the object in some frames is counted and named
    records[2]["stage0_lost_frames"] = [7, 8, 9]
    lost = tables_markdown(build_tables(records, strategies=["sequential", "progressive"]))
    assert "| sequential | 2 (1 with lost stage-0 frames) |" in lost and "- neo_hookean s0 3 views, sequential: frames 7-9" in lost
    assert "| sequential | 2 | 5.000 ± 1.000 |" in md
    assert "number of cameras" in md and "Pairwise comparisons" in md


def test_tables_count_only_the_fits_of_the_current_plan(tmp_path):
    """A folder that still holds fits of an earlier, larger plan: the tables of a smaller plan
    count its own fits only, so "n/planned" never reads 5/2."""
    from toolkit.benchmark.tables import collect_records, write_tables

    for scene, cd in (("neo_hookean/000", 1.0), ("neo_hookean/001", 3.0), ("neo_hookean/004", 100.0)):
        run = tmp_path / "runs" / scene / "cams3" / "progressive"
        run.mkdir(parents=True)
        (run / "job.json").write_text(json.dumps({"kind": "fit", "status": "done", "scene": scene, "strategy": "progressive",
                                                 "cameras": 3, "material": "neo_hookean", "wall_s_total": 1.0}))
        (run / "summary.json").write_text(json.dumps({"material": "neo_hookean", "future": {"cd": cd}, "errors": {}}))
    assert len(collect_records(tmp_path)[0]) == 3
    plan = {("neo_hookean/000", "progressive", 3), ("neo_hookean/001", "progressive", 3)}
    _, _, t = write_tables(tmp_path, planned={"neo_hookean|3|progressive": 2}, only=plan)
    (row,) = t["tables"][0]["rows"]
    assert row["values"]["cd"] == {"mean": 2.0, "std": 1.0, "n": 2} and row["planned"] == 2
    assert "| progressive | 2/2 |" in (tmp_path / "tables" / "tables.md").read_text()


def test_strip_video_of_more_than_ten_frames(tmp_path):
    """Frame labels change width at t=10 ("t=9" / "t=10"); every video frame must keep one size."""
    import imageio.v3 as iio
    import numpy as np

    from toolkit.benchmark.plots import comparison_strip, comparison_strip_video

    rng = np.random.default_rng(0)
    gt = rng.integers(0, 255, (12, 16, 20, 3), dtype=np.uint8)
    preds = {"joint": gt[:, ::-1].copy(), "progressive": gt.copy()}
    png = comparison_strip(gt, preds, [9, 10, 11], tmp_path / "strip.png", n_train=9)
    video = comparison_strip_video(gt, preds, 9, tmp_path / "strip.mp4")
    assert iio.imread(png).shape[0] > 3 * 16
    frames = iio.imread(video, index=None) if video.suffix == ".gif" else np.stack(list(iio.imiter(video)))
    assert frames.shape[0] == 12 and frames.shape[-1] == 3


# ------------------------------------------------------------------------------------ executors
def test_local_executor_time_limit_stops_jobs_gracefully(tmp_path):
    from toolkit.benchmark.runner import LocalExecutor, run_jobs

    events = []

    def emit(event, **fields):
        events.append({"event": event, **fields})
        return events[-1]

    jobs = [{"id": f"j{i}", "kind": "fit", "folder": str(tmp_path / f"j{i}"), "fingerprint": "x", "seconds": s, "depends": []}
            for i, s in enumerate([0.2, 60.0, 60.0])]
    ex = LocalExecutor(2, fn="tests.bench_helpers:sleepy_job")
    try:
        t = time.time()
        counts = run_jobs(jobs, ex, emit, deadline=time.time() + 8.0, grace=3.0, heartbeat=100, min_start_s=0)
        took = time.time() - t
    finally:
        ex.shutdown()
    assert took < 12
    assert counts["done"] == 1 and counts["remaining"] == 2
    finished = {e["job"]: e for e in events if e["event"] in ("done", "interrupted")}
    assert finished["j0"]["event"] == "done"
    # the long jobs were asked to stop (SIGTERM) and returned on their own, each in its own process
    assert {finished[j]["event"] for j in ("j1", "j2") if j in finished} <= {"interrupted"}
    pids = {e.get("pid") for e in events if e["event"] in ("done", "interrupted") and e.get("pid")}
    assert len(pids) == 3
    assert any(e["event"] == "stopping" for e in events)


def test_start_limit_stops_starting_jobs_but_lets_running_ones_finish(tmp_path):
    """One worker; jobs of 0.2, 3 and 3 s; no job starts after 1 s. The second job starts at about
    0.2 s and finishes its 3 s (a hard time limit would have stopped it); the third never starts
    and stays to be run again, and nothing is interrupted."""
    from toolkit.benchmark.runner import LocalExecutor, run_jobs

    events = []
    jobs = [{"id": f"j{i}", "kind": "fit", "folder": str(tmp_path / f"j{i}"), "fingerprint": "x", "seconds": s, "depends": []}
            for i, s in enumerate([0.2, 3.0, 3.0])]
    ex = LocalExecutor(1, fn="tests.bench_helpers:sleepy_job")
    try:
        t = time.time()
        counts = run_jobs(jobs, ex, lambda e, **f: events.append({"event": e, **f}), heartbeat=100, min_start_s=0,
                          start_deadline=time.time() + 1.0)
        took = time.time() - t
    finally:
        ex.shutdown()
    assert counts["done"] == 2 and counts["remaining"] == 1
    done = {e["job"]: e for e in events if e["event"] == "done"}
    assert set(done) == {"j0", "j1"} and done["j1"]["wall_s"] >= 2.9
    assert not [e for e in events if e["event"] == "interrupted"]
    assert [e["job"] for e in events if e["event"] == "start"] == ["j0", "j1"]
    limit = [e for e in events if e["event"] == "start_limit"]
    assert len(limit) == 1 and limit[0]["running"] == ["j1"] and limit[0]["not_started"] == 1
    assert 3.0 <= took < 8.0


def test_local_executor_gives_each_job_the_least_busy_gpu(tmp_path):
    from toolkit.benchmark.runner import LocalExecutor, run_jobs

    events = []

    def emit(event, **fields):
        events.append({"event": event, **fields})
        return events[-1]

    # two slots on each of two GPUs, listed GPU by GPU as make_executor lists them: two jobs at a
    # time must run on different GPUs, not both on the first one
    jobs = [{"id": f"j{i}", "kind": "fit", "folder": str(tmp_path / f"j{i}"), "fingerprint": "x", "seconds": 1.0, "depends": []}
            for i in range(4)]
    ex = LocalExecutor(2, ["g0", "g0", "g1", "g1"], fn="tests.bench_helpers:sleepy_job")
    try:
        counts = run_jobs(jobs, ex, emit, heartbeat=100)
    finally:
        ex.shutdown()
    assert counts["done"] == 4
    done = [e for e in events if e["event"] == "done"]
    assert sorted(e["gpu"] for e in done) == ["g0", "g0", "g1", "g1"]
    assert len({e["pid"] for e in done}) == 4
    with pytest.raises(ValueError, match="at least one GPU"):
        LocalExecutor(1, [])


def test_least_loaded_gpu_spreads_the_longest_jobs():
    from toolkit.benchmark.executors import least_loaded_gpu

    gpus, slots = ["g0", "g1"], {"g0": 2, "g1": 2}
    # jobs of 1000, 100, 1000, 100 s arriving in that order: counting jobs alone puts both long
    # ones on g0 (g0, g1, g0, g1); by estimated work left they go to different GPUs
    running: list = []
    for est in (1000.0, 100.0, 1000.0, 100.0):
        g = least_loaded_gpu(gpus, slots, running, now=0.0)
        running.append((g, 0.0, est))
    per_gpu = {g: sorted(e for gg, _, e in running if gg == g) for g in gpus}
    assert per_gpu == {"g0": [100.0, 1000.0], "g1": [100.0, 1000.0]}
    # a full GPU is not chosen however light its jobs; elapsed time counts against the estimate,
    # down to a tenth of it for a job past its estimate
    assert least_loaded_gpu(gpus, {"g0": 1, "g1": 2}, [("g0", 0.0, 1.0), ("g1", 0.0, 500.0)], now=0.0) == "g1"
    busy = [("g0", 800.0, 400.0), ("g1", 0.0, 1000.0)]
    assert least_loaded_gpu(gpus, slots, busy, now=800.0) == "g1"  # 400 s left on g0, 200 s on g1
    assert least_loaded_gpu(gpus, slots, busy, now=1200.0) == "g0"  # 40 s (a tenth) against 100 s
    # ties go to the first listed
    assert least_loaded_gpu(gpus, slots, [], now=0.0) == "g0"


_NOT_PYTHON_MAIN = r"""
import json, sys, types
from pathlib import Path
main = types.ModuleType("__main__")
main.__file__ = sys.argv[1]          # a page that is not Python, as the docs test runs tutorials
sys.modules["__main__"] = main
from toolkit.benchmark.runner import LocalExecutor, run_jobs
tmp = Path(sys.argv[2])
jobs = [{"id": f"j{i}", "kind": "fit", "folder": str(tmp / f"j{i}"), "fingerprint": "x", "seconds": 0.3 * (i % 3),
         "depends": []} for i in range(7)]
events = []
ex = LocalExecutor(2, fn="tests.bench_helpers:sleepy_job")
try:
    counts = run_jobs(jobs, ex, lambda event, **f: events.append({"event": event, **f}), heartbeat=100)
finally:
    ex.shutdown()
print(json.dumps({"counts": counts, "pids": sorted({e["pid"] for e in events if e["event"] == "done"})}))
"""


def test_local_executor_starts_every_worker_when_main_is_not_python(tmp_path):
    """Workers are spawned for every job, also after the first ones finished, with a ``__main__``
    file that spawn cannot re-run (a documentation page): none of them may die at start."""
    page = tmp_path / "page.md"
    page.write_text("# A page\n\nstage 0 (4D Gaussians) is not Python.\n")
    proc = subprocess.run([sys.executable, "-c", _NOT_PYTHON_MAIN, str(page), str(tmp_path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=240,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "CUDA_VISIBLE_DEVICES": ""})
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "SyntaxError" not in proc.stderr, proc.stderr[-4000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["counts"]["done"] == 7 and out["counts"]["remaining"] == 0
    assert len(out["pids"]) == 7  # a fresh process per job


# ------------------------------------------------------------------------------------ the benchmark
def test_benchmark_runs_jobs_in_parallel_processes_and_rerun_skips_them(bench, capsys):
    out = bench["out"]
    assert bench["rc"] == 0
    markers = [json.loads(p.read_text()) for p in sorted(out.rglob("job.json"))]
    assert len(markers) == 2 + 4 and all(m["status"] == "done" for m in markers)
    pids = [a["pid"] for m in markers for a in m["attempts"]]
    assert len(set(pids)) == len(pids) == 6  # every job ran in a fresh worker process
    # each strategy's run folder links the scene's one physics_input.pt
    for run in sorted((out / "runs").glob("neo_hookean/*/cams3/*")):
        link = run / "physics_input.pt"
        assert link.is_symlink() and link.resolve() == (out / "scenes" / run.relative_to(out / "runs").parent / "physics_input.pt").resolve()
    tables = json.loads((out / "tables" / "tables.json").read_text())
    (t,) = tables["tables"]
    assert {r["strategy"]: r["n"] for r in t["rows"]} == {"sequential": 2, "progressive": 2}
    assert math.isfinite(t["rows"][0]["values"]["cd"]["mean"]) and t["rows"][0]["values"]["cd"]["n"] == 2
    assert (out / "tables" / "tables.md").read_text().count("| progressive |") >= 1
    assert list((out / "tables").glob("strip_*.png")) and list((out / "tables").glob("trajectories_*.png"))
    # a rerun finds everything done and trains nothing
    ckpts = {p: p.stat().st_mtime for p in out.rglob("last.ckpt")}
    capsys.readouterr()
    assert main(bench["args"]) == 0
    events = _events(capsys.readouterr().out)
    plan = next(e for e in events if e["event"] == "plan")
    assert plan["to_run"] == 0
    assert not [e for e in events if e["event"] == "start"]
    assert {p: p.stat().st_mtime for p in out.rglob("last.ckpt")} == ckpts


def test_periodic_evaluation_records_emd_and_psnr_into_history(bench):
    from toolkit.physics.periodic_eval import evaluation_steps

    run = next((bench["out"] / "runs").glob("neo_hookean/000/cams3/progressive"))
    history = json.loads((run / "physics" / "history.json").read_text())
    boundaries = [0, 3, 7]
    expected = evaluation_steps(boundaries, per_stage=2)
    assert expected == [1, 2, 3, 5, 7]
    got = [h["step"] for h in history if "eval/emd_future" in h]
    assert got == expected
    for h in history:
        if "eval/emd_future" in h:
            assert h["eval/emd_future"] > 0 and math.isfinite(h["eval/psnr_future"]) and h["eval/camera"] == 0
            assert h["eval/emd_x0"] < h["eval/emd_future"]
    assert (run / "report" / "evaluation_trajectories.png").stat().st_size > 1000


def test_interrupted_fit_resumes_where_it_stopped(suite, tmp_path):
    from toolkit.benchmark import BenchmarkSpec, run_benchmark, scenes_from_suite

    spec = BenchmarkSpec(scenes_from_suite(suite)[:1], ["progressive"], size="small",
                         overrides={"geometry": "oracle", "sim": {"dx": 0.04, "substeps": 30}, "device": "cpu"},
                         iterations={"stage1_iterations": 3, "stage2_iterations": 4}, periodic_eval=None, checkpoint_every=50)
    events = []
    first = run_benchmark(spec, tmp_path / "b", workers=1, interrupt_at_step=4, echo=events.append, figures=False)
    assert not first["complete"] and first["counts"]["remaining"] == 1
    run = tmp_path / "b" / "runs" / "neo_hookean" / "000" / "cams3" / "progressive"
    marker = json.loads((run / "job.json").read_text())
    assert marker["status"] == "interrupted"
    import torch

    ckpt = torch.load(run / "physics" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["projo4d"]["curriculum_step"] == 4
    # the marker keeps where the fit stopped (a lent machine takes the checkpoint with it)
    stopped = marker["result"]["stopped_at"]
    last = ckpt["projo4d"]["history"][-1]
    assert stopped["iteration"] == 4 and stopped["of"] == 7 and stopped["stage"] == last["stage_name"]
    assert stopped["errors"]["E"] == pytest.approx(last["error/E"]) and stopped["errors"]["E"] > 0
    assert stopped["parameters"]["param/E"] == pytest.approx(last["param/E"])
    assert stopped["material_final"] is False  # stopped in a stage that still fits the material
    assert next(e for e in events if e["event"] == "interrupted")["stopped_at"]["iteration"] == 4
    second = run_benchmark(spec, tmp_path / "b", workers=1, echo=events.append, figures=False)
    assert second["complete"]
    assert [e["job"] for e in events if e["event"] == "start"] == [
        "prepare:neo_hookean/000:cams3", "fit:neo_hookean/000:cams3:progressive", "fit:neo_hookean/000:cams3:progressive"]
    history = json.loads((run / "physics" / "history.json").read_text())
    assert [h["step"] for h in history] == list(range(1, 8))
    marker = json.loads((run / "job.json").read_text())
    assert marker["status"] == "done" and [a["status"] for a in marker["attempts"]] == ["interrupted", "done"]


def test_stopped_fit_state_says_whether_the_material_was_final(tmp_path):
    """A sequential fit stopped in its appearance stage has its final parameters: only ``A`` is
    left. Stopped in the material stage, it has not."""
    import torch

    from toolkit.benchmark.jobs import stopped_fit_state

    stages = [{"name": "S@3", "groups": "S", "end": 3}, {"name": "M", "groups": "M", "end": 8},
              {"name": "A", "groups": "A", "end": 20}]

    def state(step: int) -> dict:
        history = [{"step": k, "stage_name": "M" if k <= 8 else "A", "param/E": 1e4 + k, "error/E": 0.1 * k,
                    **({"eval/cd_future": 2.0 / k, "eval/emd_future": 0.01} if k in (3, 8) else {})} for k in range(1, step + 1)]
        path = tmp_path / f"s{step}.ckpt"
        torch.save({"projo4d": {"history": history, "curriculum": stages}}, path)
        return stopped_fit_state(path)

    in_appearance, in_material = state(12), state(6)
    assert in_appearance["material_final"] is True and in_appearance["stage"] == "A"
    assert in_appearance["iteration"] == 12 and in_appearance["of"] == 20
    assert in_appearance["errors"] == {"E": pytest.approx(1.2)} and in_appearance["parameters"] == {"param/E": 10012}
    assert in_appearance["evaluation"] == {"step": 8, "cd_future": 0.25, "emd_future": 0.01}
    assert in_material["material_final"] is False and in_material["evaluation"]["step"] == 3
    assert state(8)["material_final"] is True  # the material stage's last iteration was done
    assert stopped_fit_state(tmp_path / "missing.ckpt") is None


def test_a_refined_benchmark_fit_is_recorded_by_its_refined_result(suite, tmp_path):
    """refine_grid in a benchmark fit: the refined run is fitted in the fit's folder, and the table's
    record is the refined result with the first fit's kept under ``coarse``."""
    from toolkit.benchmark import BenchmarkSpec, run_benchmark, scenes_from_suite
    from toolkit.benchmark.tables import record_from_run

    # the verdict is the fit's (shift against misfit); a 7-iteration fit's is not at stake here, so the
    # refit is asked for whatever the check finds ("always"); the refined run is not refined again
    spec = BenchmarkSpec(scenes_from_suite(suite)[:1], ["progressive"], size="small",
                         overrides={"geometry": "oracle", "sim": {"dx": 0.08, "substeps": 15}, "device": "cpu",
                                    "refine_grid": "always"},
                         iterations={"stage1_iterations": 3, "stage2_iterations": 4}, periodic_eval=None)
    done = run_benchmark(spec, tmp_path / "b", executor="inline", echo=lambda e: None, figures=False)
    assert done["complete"]
    run = tmp_path / "b" / "runs" / "neo_hookean" / "000" / "cams3" / "progressive"
    parent = json.loads((run / "summary.json").read_text())
    child = json.loads((run / "refined" / "summary.json").read_text())
    assert child["grid_check"]["dx"] == pytest.approx(0.04) and parent["timings_s"]["refine_s"] > 0
    assert not (run / "refined" / "stage0").exists()  # oracle geometry: no stage 0 to share (linking: test_grid_refinement)
    rec = record_from_run(run)
    assert rec["errors"]["E"] == pytest.approx(child["errors"]["error/E"])
    assert rec["coarse"]["errors"]["E"] != rec["errors"]["E"]
    assert rec["strategy"] == "progressive" and rec["run_dir"] == str(run) and rec["optimized"] == ["E", "nu"]
    marker = json.loads((run / "job.json").read_text())  # the event log's result names both fits
    assert marker["result"]["refined"]["errors"]["E"] == pytest.approx(rec["errors"]["E"])
    assert marker["result"]["errors"]["E"] == pytest.approx(rec["coarse"]["errors"]["E"])


def test_changed_settings_are_refused_unless_redone(bench, capsys):
    args = [a for a in bench["args"]]
    i = args.index("--stage2-iterations")
    args[i + 1] = "5"
    with pytest.raises(SystemExit, match="other settings"):
        main(args + ["--dry-run"])


def test_a_scene_generated_from_another_spec_makes_its_stage0_and_fits_stale(tmp_path):
    """Another --suite-seed, --suite-overrides or --shape-set in the same --out regenerates a scene;
    its stage 0 and fits (whose fingerprints do not hold the scene's spec) must not be reused."""
    from toolkit.benchmark.plan import BenchmarkError
    from toolkit.benchmark.runner import _check_changed
    from toolkit.synthetic.scene import GENERATOR_VERSION

    def scene(name: str, made_from: "str | None", wanted: str) -> list[dict]:
        folder = tmp_path / "suite" / name
        if made_from is not None:
            folder.mkdir(parents=True)
            (folder / "ground_truth.json").write_text(json.dumps(
                {"generator": {"spec": {"shape": made_from, "size": [0.1, 0.2]}, "version": GENERATOR_VERSION}}))
        jobs = [{"id": f"generate:{name}", "kind": "generate", "folder": str(folder), "fingerprint": "g", "scene": name,
                 "settings": {"spec": {"shape": wanted, "size": (0.1, 0.2)}}, "depends": []}]
        for kind, dep in (("prepare", f"generate:{name}"), ("fit", f"prepare:{name}")):
            job_dir = tmp_path / kind / name
            job_dir.mkdir(parents=True)
            (job_dir / "job.json").write_text(json.dumps({"status": "done", "fingerprint": kind}))
            jobs.append({"id": f"{kind}:{name}", "kind": kind, "folder": str(job_dir), "fingerprint": kind, "depends": [dep]})
        return jobs

    jobs = scene("a", "box", "apple") + scene("b", "torus", "torus") + scene("c", None, "cream")
    with pytest.raises(BenchmarkError, match=r"3 job folder\(s\).*\(generate:a, prepare:a, fit:a\); scene\(s\) a hold a scene "
                                             r"generated from another spec"):
        _check_changed(jobs, False, lambda *a, **k: None)
    redone = []
    _check_changed(jobs, True, lambda event, **k: redone.append(k["job"]))
    assert redone == ["generate:a", "prepare:a", "fit:a"]
    assert not (tmp_path / "suite" / "a").exists() and not (tmp_path / "prepare" / "a").exists()
    assert (tmp_path / "prepare" / "b" / "job.json").is_file() and (tmp_path / "fit" / "c" / "job.json").is_file()


# ------------------------------------------------------------------------------------ evaluate and view
def test_evaluate_command_re_evaluates_a_run_folder(bench, capsys):
    run = bench["out"] / "runs" / "neo_hookean" / "001" / "cams3" / "sequential"
    before = json.loads((run / "evaluation" / "evaluation.json").read_text())
    grid_before = json.loads((run / "summary.json").read_text())["grid_check"]
    import shutil

    shutil.rmtree(run / "evaluation")
    shutil.rmtree(run / "report")
    assert main(["evaluate", str(run), "--no-render", "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert "Chamfer distance" in printed and "not rendered" in printed and "E" in printed
    ev = json.loads((run / "evaluation" / "evaluation.json").read_text())
    assert "images" not in ev and ev["geometry"]["cd_future"] == pytest.approx(before["geometry"]["cd_future"], rel=1e-5)
    assert (run / "report" / "per_frame.png").is_file() and (run / "report" / "evaluation_trajectories.png").is_file()
    # the fit's grid check is kept (not re-run) and drawn again
    assert (run / "report" / "grid_check.png").is_file()
    assert json.loads((run / "summary.json").read_text())["grid_check"] == grid_before
    assert main(["evaluate", str(run), "--json", "--device", "cpu"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["images"]["held_out_cameras"]["psnr_future"] == pytest.approx(before["images"]["held_out_cameras"]["psnr_future"],
                                                                             rel=1e-4)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["benchmark"]["strategy"] == "sequential" and summary["future"]["psnr"] is not None


def test_view_writes_png_and_mp4_with_the_matplotlib_fallback(bench, capsys):
    from toolkit.viewer import open3d_offscreen_available

    run = bench["out"] / "runs" / "neo_hookean" / "000" / "cams3" / "progressive"
    out = run / "view_test"
    assert main(["view", str(run), "--offscreen", "--out", str(out), "--size", "320x160", "--frames", "0", "5"]) == 0
    info = json.loads((out / "view.json").read_text())
    if not open3d_offscreen_available():
        assert info["backend"] == "matplotlib"
    for name in ("frame_000.png", "frame_005.png", "strip.png"):
        assert (out / name).stat().st_size > 2000
    video = out / "particles.mp4"
    assert video.is_file() or (out / "particles.gif").is_file()
    import imageio.v3 as iio

    img = iio.imread(out / "frame_005.png")
    assert img.shape[:2] == (160, 320) and img.std() > 5
    assert "rendered with" in capsys.readouterr().out


def test_export_bundles_the_results(bench, tmp_path):
    assert main(["benchmark", "--out", str(bench["out"]), "--tables-only", "--no-figures", "--export", str(tmp_path / "x")]) == 0
    names = sorted(p.name for p in (tmp_path / "x").iterdir())
    assert names == ["progress.jsonl", "results.tar.gz", "tables.json", "tables.md"]
    with tarfile.open(tmp_path / "x" / "results.tar.gz") as tar:
        members = tar.getnames()
    assert "runs/neo_hookean/000/cams3/progressive/summary.json" in members
    assert "runs/neo_hookean/000/cams3/progressive/physics/history.json" in members
    searches = sorted(str(p.relative_to(bench["out"])) for p in bench["out"].glob("runs/**/material_search.json"))
    assert searches and set(searches) <= set(members)  # the coarse search's record comes back with the fit
    assert all(os.path.getsize(tmp_path / "x" / n) < 16 * 2**20 for n in names)


def test_tables_are_exported_before_the_figures_are_drawn(bench, tmp_path, capsys):
    """A lent machine whose time runs out while the figures are drawn still has the tables out."""
    capsys.readouterr()
    assert main(bench["args"] + ["--export", str(tmp_path / "x")]) == 0
    kinds = [e["event"] for e in _events(capsys.readouterr().out)]
    first = kinds.index("exported")
    assert kinds.index("tables") < first < kinds.index("figures") < kinds.index("figures_done")
    assert kinds.count("exported") == 2 and kinds.index("figures_done") < len(kinds) - 1 - kinds[::-1].index("exported")
    assert (tmp_path / "x" / "tables.md").is_file()


def test_ray_executor_runs_jobs_and_stops_them_at_the_time_limit(tmp_path):
    pytest.importorskip("ray")  # optional extra: projo4d[ray]
    from toolkit.benchmark.runner import RayExecutor, run_jobs

    events = []
    jobs = [{"id": f"j{i}", "kind": "fit", "folder": str(tmp_path / f"j{i}"), "fingerprint": "x", "seconds": s, "depends": []}
            for i, s in enumerate([0.2, 0.3, 60.0])]
    ex = RayExecutor(None, gpus_per_job=0.0, cpus_per_job=1.0, fn="tests.bench_helpers:sleepy_job")
    try:
        # Ray starts its worker processes with the first tasks; on a loaded 2-core machine that took
        # longer than the deadline below, so they are started before the clock runs
        warm = [{"id": f"w{i}", "kind": "fit", "folder": str(tmp_path / f"w{i}"), "fingerprint": "x", "seconds": 0.0,
                 "depends": []} for i in range(2)]
        assert run_jobs(warm, ex, lambda e, **f: None, heartbeat=100)["done"] == 2
        counts = run_jobs(jobs, ex, lambda e, **f: events.append({"event": e, **f}), deadline=time.time() + 30.0, grace=3.0,
                          heartbeat=100, min_start_s=0)
    finally:
        ex.shutdown()
    assert counts["done"] == 2 and counts["remaining"] == 1
    assert [e["job"] for e in events if e["event"] == "interrupted"] == ["j2"]


def test_divergence_guard_restores_the_last_valid_parameters():
    import torch

    from materials import get_material
    from toolkit.benchmark.callbacks import DivergenceGuard

    class Fake(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.material = get_material("sand")
            self.raw = torch.nn.Parameter(self.material.to_raw({"friction_angle": 30.0}))
            self.v0 = torch.nn.Parameter(torch.zeros(3))
            self.curriculum_step = 0
            self.history = []

        def material_params(self):
            return self.material.to_physical(self.raw)

    trainer = type("Trainer", (), {"should_stop": False})()
    m, guard = Fake(), DivergenceGuard()
    for step, angle in enumerate([25.0, 12.0, -3.0]):  # the third step pushes the angle out of its range
        guard.on_train_batch_start(trainer, m, None, step)
        with torch.no_grad():
            m.raw.copy_(m.material.to_raw({"friction_angle": 30.0}))
            m.raw[m.material.param_names.index("friction_angle")] = angle
        m.curriculum_step += 1
        m.history.append({"step": m.curriculum_step})
        guard.on_train_batch_end(trainer, m, torch.tensor(0.0), None, step)
        if trainer.should_stop:
            break
    assert trainer.should_stop and guard.diverged["step"] == 3 and "friction_angle" in guard.diverged["reason"]
    assert m.material_params()[m.material.param_names.index("friction_angle")].item() == pytest.approx(12.0)
    assert "diverged" in m.history[-1]
    with torch.no_grad():
        m.v0[0] = float("nan")
    assert "v0" in DivergenceGuard.check(m)


def test_scheduler_takes_the_kth_scene_of_every_family_before_the_next(tmp_path):
    """A chunk that ends early must leave every family with as many finished scenes: with one job
    at a time, fits start scene 0 of each material, then scene 1 of each, in planning order within."""
    from toolkit.benchmark.executors import InlineExecutor
    from toolkit.benchmark.scheduler import run_jobs

    jobs = [{"id": f"fit:{m}/{k}:{s}", "kind": "fit", "material": m, "scene": f"{m}/{k}", "folder": str(tmp_path / m / str(k) / s),
             "fingerprint": "x", "depends": []}
            for m in ("elastic", "sand") for k in range(2) for s in ("joint", "progressive")]
    starts: list[str] = []
    run_jobs(jobs, InlineExecutor(fn="tests.bench_helpers:sleepy_job"),
             lambda e, **f: starts.append(f["job"]) if e == "start" else None, heartbeat=100, min_start_s=0)
    assert starts == ["fit:elastic/0:joint", "fit:elastic/0:progressive", "fit:sand/0:joint", "fit:sand/0:progressive",
                      "fit:elastic/1:joint", "fit:elastic/1:progressive", "fit:sand/1:joint", "fit:sand/1:progressive"]


def test_scheduler_does_not_rebuild_what_only_finished_jobs_need(tmp_path):
    """A scene whose fits are all done (their results restored from another machine) is neither
    generated nor prepared again; a scene with one fit left still is."""
    from toolkit.benchmark.executors import InlineExecutor
    from toolkit.benchmark.scheduler import run_jobs

    jobs = []
    for k in range(2):
        jobs += [{"id": f"generate:{k}", "kind": "generate", "scene": str(k), "material": "m", "folder": str(tmp_path / f"g{k}"),
                  "fingerprint": "x", "depends": []},
                 {"id": f"prepare:{k}", "kind": "prepare", "scene": str(k), "material": "m", "folder": str(tmp_path / f"p{k}"),
                  "fingerprint": "x", "depends": [f"generate:{k}"]}]
        jobs += [{"id": f"fit:{k}:{s}", "kind": "fit", "scene": str(k), "material": "m", "folder": str(tmp_path / f"f{k}{s}"),
                  "fingerprint": "x", "depends": [f"prepare:{k}"]} for s in ("a", "b")]
    done = {"fit:0:a", "fit:0:b", "fit:1:a"}
    import toolkit.benchmark.jobs as jobs_module

    real = jobs_module.job_is_done
    jobs_module.job_is_done = lambda j: j["id"] in done
    try:
        starts: list[str] = []
        run_jobs(jobs, InlineExecutor(fn="tests.bench_helpers:sleepy_job"),
                 lambda e, **f: starts.append(f["job"]) if e == "start" else None, heartbeat=100, min_start_s=0)
    finally:
        jobs_module.job_is_done = real
    assert starts == ["generate:1", "prepare:1", "fit:1:b"]

"""The benchmark's time estimates (toolkit.benchmark.estimate): what a fit's grid refinement adds.

On CUDA a fit whose grid check fails is fitted again at half the grid spacing (``refine_grid``
``auto``), which costs 1.4-3.4x its physics stage on a GPU (8x on a CPU, where ``auto`` does not refine).
A plan that leaves that out told a user 435 s for five full-size elastic fits on one H100 that
were still refining after 1600 s, so the plan also gives the wall time if every fit refines.
"""

from __future__ import annotations

import json

import pytest

from toolkit.benchmark.estimate import PROFILES, estimate_job, fit_may_refine, refinement_estimate, scene_info
from toolkit.cli import main

FULL = {"n_frames": 20, "n_cameras": 11, "width": 400, "height": 400, "n_train_frames": 14}


def _fit(**settings) -> dict:
    return {"kind": "fit", "strategy": "progressive", "material": "neo_hookean", "scene": "neo_hookean/000",
            "settings": {"curriculum": "progressive", "sim": {"substeps": 100}, **settings}, "extra": {}}


@pytest.mark.parametrize("refine, profile, expected", [
    (None, "cuda", True),     # the default, auto: refines on CUDA
    (None, "cpu", False),     # ... but only says so on a CPU
    ("auto", "cpu", False),
    (True, "cpu", True),
    (False, "cuda", False),
])
def test_which_fits_may_refine(refine, profile, expected):
    job = _fit() if refine is None else _fit(refine_grid=refine)
    assert fit_may_refine(job, PROFILES[profile]) is expected
    assert not fit_may_refine({**job, "kind": "prepare"}, PROFILES[profile])


def test_a_refinement_costs_the_fit_again_times_the_measured_factor():
    info = scene_info("", FULL)
    job = _fit()
    cuda, cpu = PROFILES["cuda"], PROFILES["cpu"]
    fit_s = estimate_job(job, info, cuda, 2000)
    assert refinement_estimate(job, info, cuda, 2000) == pytest.approx((fit_s - cuda.startup) * 4.0)
    assert refinement_estimate(job, info, cpu, 2000) == 0.0  # auto on a CPU: no refit
    forced = _fit(refine_grid=True)
    assert refinement_estimate(forced, info, cpu, 2000) == pytest.approx(
        (estimate_job(forced, info, cpu, 2000) - cpu.startup) * 8.0)
    half = _fit(refine_grid=True, refine_iterations=0.5)  # a refit of half the curriculum: half the work
    assert refinement_estimate(half, info, cpu, 2000) == pytest.approx(refinement_estimate(forced, info, cpu, 2000) / 2)


def test_the_plan_gives_the_wall_time_if_every_fit_refines(tmp_path, capsys):
    args = ["benchmark", "--suite", str(tmp_path / "suite"), "--generate", "--families", "neo_hookean",
            "--per-family", "2", "--size", "full", "--strategies", "progressive", "--out", str(tmp_path / "bench"),
            "--dry-run", "--estimate-for", "cuda", "--workers", "2"]
    assert main(args) == 0
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    plan = next(e for e in events if e.get("event") == "plan")
    fits = [e["est_s"] for e in events if e.get("event") == "estimate" and e["job"].startswith("fit:")]
    assert plan["refinable_fits"] == 2 and len(fits) == 2
    # the two fits run side by side after generation and stage 0: refining both adds one refinement
    added = plan["estimated_wall_s_if_all_refined"] - plan["estimated_wall_s"]
    factor = PROFILES["cuda"].refine_factor
    assert factor == pytest.approx(4.0)  # a full-size fit alone on an H200: refit physics / first physics 4.1x
    assert added == pytest.approx((fits[0] - PROFILES["cuda"].startup) * factor, abs=1.0)
    assert "refine_grid" in plan["note"] and f"{factor:g}x" in plan["note"]
    assert not (tmp_path / "bench").exists() and not (tmp_path / "suite").exists()  # a dry run writes nothing

    capsys.readouterr()
    assert main(args + ["--no-refine-grid"]) == 0
    plan = next(json.loads(line) for line in capsys.readouterr().out.splitlines() if '"event": "plan"' in line)
    assert "estimated_wall_s_if_all_refined" not in plan and "refine_grid" not in plan["note"]


def test_fits_sharing_a_gpu_are_priced_as_measured_and_other_jobs_as_before():
    """k fits on one GPU time-slice it: 5 a GPU measured a 3.8x median slowdown over the committed
    rounds (the old guess, 1.47x, made every plan 2.4x optimistic); generation and stage 0 keep theirs."""
    from toolkit.benchmark.estimate import sharing_slowdown

    assert sharing_slowdown(1, "fit") == 1.0 and sharing_slowdown(1) == 1.0
    assert sharing_slowdown(5, "fit") == pytest.approx(5 / 1.28)
    assert 3.0 < sharing_slowdown(5, "fit") < 4.5
    assert sharing_slowdown(5, "prepare") == sharing_slowdown(5, "generate") == pytest.approx(5 / 3.4)
    slow = [sharing_slowdown(k, "fit") for k in range(1, 9)]
    assert all(b > a for a, b in zip(slow, slow[1:])) and all(s <= k for k, s in enumerate(slow, 1))


@pytest.mark.parametrize("value", ["0", "1.5", "-0.5"])
def test_a_refit_fraction_outside_0_1_is_refused_before_planning(tmp_path, capsys, value):
    args = ["benchmark", "--suite", str(tmp_path / "suite"), "--generate", "--families", "sand", "--per-family", "1",
            "--size", "small", "--strategies", "progressive", "--refine-iterations", value, "--out", str(tmp_path / "b"),
            "--dry-run"]
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code not in (0, None)
    err = str(stop.value.code) + capsys.readouterr().err
    assert "--refine-iterations" in err and "(0, 1]" in err and '"event": "plan"' not in err
    assert not (tmp_path / "b").exists() and not (tmp_path / "suite").exists()


def _log_line(**e) -> str:
    return json.dumps(e) + "\n"


def test_estimate_check_recovers_the_sharing_from_an_event_log(tmp_path, capsys):
    """A log where two fits share GPU 0 for all their run and a third is alone on GPU 1: the check
    counts k = 2 and 1, takes a refit's seconds out, and inverts k / (1 + overlap (k - 1))."""
    from tests.bench_helpers import load_benchmark_script
    from toolkit.benchmark.estimate import sharing_slowdown

    mod = load_benchmark_script("estimate_check")
    assumed = sharing_slowdown(2, "other")  # what an old plan's note named
    alone = 100.0
    slow_true = sharing_slowdown(2, "fit")  # the truth of this made-up machine: overlap 0.07
    log = tmp_path / "benchmark_log.jsonl"
    with log.open("w") as f:
        f.write(_log_line(event="plan", note=f"...; 2 jobs sharing a GPU are assumed {assumed:.2f}x slower each"))
        for j in ("fit:a/000:cams3:progressive", "fit:a/001:cams3:progressive"):
            f.write(_log_line(event="estimate", job=j, est_s=alone * assumed, basis="model"))
            f.write(_log_line(event="start", t=10.0, job=j))
        f.write(_log_line(event="estimate", job="fit:a/002:cams3:progressive", est_s=alone * assumed, basis="model"))
        f.write(_log_line(event="start", t=10.0, job="fit:a/002:cams3:progressive"))
        for j in ("fit:a/000:cams3:progressive", "fit:a/001:cams3:progressive"):
            f.write(_log_line(event="done", t=10.0 + alone * slow_true, job=j, wall_s=alone * slow_true, gpu="0",
                              result={"timings_s": {"refine_s": 0.0}}))
        f.write(_log_line(event="done", t=10.0 + alone + 50.0, job="fit:a/002:cams3:progressive", wall_s=alone + 50.0,
                          gpu="1", result={"timings_s": {"refine_s": 50.0}}))
    assert mod.main([str(log)]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    fits = {r["job"].split(":")[1]: r for r in lines if "job" in r}
    assert fits["a/000"]["k"] == pytest.approx(2.0) and fits["a/002"]["k"] == pytest.approx(1.0)
    assert fits["a/000"]["alone_model_s"] == pytest.approx(alone, rel=1e-2)
    assert fits["a/000"]["overlap"] == pytest.approx(0.07, abs=0.01)
    assert fits["a/002"]["measured_s"] == pytest.approx(alone) and "overlap" not in fits["a/002"]  # the refit left out
    summary = lines[-1]["summary"]
    assert summary["fits_with_sharing"] == 2 and summary["median_overlap"] == pytest.approx(0.07, abs=0.01)
    with pytest.raises(SystemExit):
        mod.main([str(tmp_path / "missing.jsonl")])


def test_the_plan_prices_fits_at_the_sharing_they_will_have(tmp_path, capsys):
    """Two fits planned on one GPU with 5 slots share it two ways, not five: the plan's fit estimate is
    the alone estimate times sharing_slowdown(2, "fit"), and its note names both numbers, which
    benchmarks/estimate_check.py reads back."""
    from toolkit.benchmark.estimate import sharing_slowdown

    args = ["benchmark", "--suite", str(tmp_path / "suite"), "--generate", "--families", "neo_hookean",
            "--per-family", "2", "--size", "full", "--strategies", "progressive", "--out", str(tmp_path / "bench"),
            "--dry-run", "--estimate-for", "cuda", "--gpus", "1", "--jobs-per-gpu", "5", "--no-refine-grid"]
    assert main(args) == 0
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    plan = next(e for e in events if e.get("event") == "plan")
    fit = next(e["est_s"] for e in events if e.get("event") == "estimate" and e["job"].startswith("fit:"))
    assert "(2 fits) a fit is assumed" in plan["note"]
    assert main(args[:-2] + ["1", "--no-refine-grid"]) == 0  # one job a GPU: the fit alone
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    alone = next(e["est_s"] for e in events if e.get("event") == "estimate" and e["job"].startswith("fit:"))
    assert fit == pytest.approx(alone * sharing_slowdown(2, "fit"), rel=0.01)
    from tests.bench_helpers import load_benchmark_script

    mod = load_benchmark_script("estimate_check")
    assert mod.assumed_slowdown(plan) == pytest.approx(sharing_slowdown(2, "fit"), abs=0.01)

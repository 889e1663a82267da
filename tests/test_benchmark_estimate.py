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
    assert refinement_estimate(job, info, cuda, 2000) == pytest.approx((fit_s - cuda.startup) * 2.7)
    assert refinement_estimate(job, info, cpu, 2000) == 0.0  # auto on a CPU: no refit
    forced = _fit(refine_grid=True)
    assert refinement_estimate(forced, info, cpu, 2000) == pytest.approx(
        (estimate_job(forced, info, cpu, 2000) - cpu.startup) * 8.0)


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
    assert added == pytest.approx((fits[0] - PROFILES["cuda"].startup) * 2.7, abs=1.0)
    assert "refine_grid" in plan["note"] and "2.7x" in plan["note"]
    assert not (tmp_path / "bench").exists() and not (tmp_path / "suite").exists()  # a dry run writes nothing

    capsys.readouterr()
    assert main(args + ["--no-refine-grid"]) == 0
    plan = next(json.loads(line) for line in capsys.readouterr().out.splitlines() if '"event": "plan"' in line)
    assert "estimated_wall_s_if_all_refined" not in plan and "refine_grid" not in plan["note"]

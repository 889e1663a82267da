"""Benchmarks of strategies over suites of scenes: plan, run in parallel (resumable), tabulate.

>>> from toolkit.benchmark import BenchmarkSpec, scenes_from_suite, run_benchmark   # doctest: +SKIP
>>> spec = BenchmarkSpec(scenes_from_suite("suites/s0"), ["sequential", "joint", "progressive"])  # doctest: +SKIP
>>> run_benchmark(spec, "bench/s0", time_limit=540)                                    # doctest: +SKIP

* :mod:`toolkit.benchmark.plan`: scenes x camera counts x strategies as jobs; stage 0 runs once
  per scene and camera set and every strategy fits from the same ``physics_input.pt``;
* :mod:`toolkit.benchmark.runner`: :func:`run_benchmark`, the whole command (estimates, run,
  tables, export);
* :mod:`toolkit.benchmark.scheduler`: dependencies, priorities, time limits, resume;
* :mod:`toolkit.benchmark.executors`: the executor interface; local worker processes (one per
  GPU) and inline; :mod:`toolkit.benchmark.ray_executor` (Ray) and
  :mod:`toolkit.benchmark.slurm` (SLURM through submitit);
* :mod:`toolkit.benchmark.jobs`: what a worker does with one job;
* :mod:`toolkit.benchmark.tables`: per-material mean ± std tables (Markdown and JSON);
* :mod:`toolkit.benchmark.plots`: trajectories, per-frame errors and image strips per strategy;
* :mod:`toolkit.benchmark.estimate`: wall-time estimates per job;
* :mod:`toolkit.benchmark.commands`: ``projo4d benchmark``.

Importing this package is light (no torch, Warp or Lightning until a function needs them).
"""

from toolkit.benchmark.plan import (
    BENCH_SIZES,
    BenchmarkError,
    BenchmarkSpec,
    Job,
    SceneEntry,
    StrategyEntry,
    camera_subset,
    parse_strategy,
    plan_benchmark,
)
from toolkit.benchmark.runner import run_benchmark
from toolkit.benchmark.scenes import scenes_from_dirs, scenes_from_suite, scenes_to_generate

__all__ = [
    "BENCH_SIZES",
    "BenchmarkError",
    "BenchmarkSpec",
    "Job",
    "SceneEntry",
    "StrategyEntry",
    "camera_subset",
    "parse_strategy",
    "plan_benchmark",
    "run_benchmark",
    "scenes_from_dirs",
    "scenes_from_suite",
    "scenes_to_generate",
]

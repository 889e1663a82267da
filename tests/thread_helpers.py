"""Job function for the thread tests (importable by spawned worker processes and Ray tasks)."""

from __future__ import annotations

import os
from types import SimpleNamespace


def report_threads_job(job: dict) -> dict:
    """Size the thread pools as a benchmark job does (:func:`toolkit.benchmark.jobs._set_threads`,
    with the job's optional ``threads`` setting), then report what this process got."""
    import numpy  # noqa: F401 - its OpenBLAS is loaded, so the BLAS count is checked too
    import torch

    from toolkit.benchmark.jobs import _set_threads
    from toolkit.threads import blas_threads

    choice = _set_threads(SimpleNamespace(threads=job.get("threads"), out=job["folder"], device=job.get("device", "cuda")))
    blas = blas_threads()
    return {"id": job["id"], "status": "done", "pid": os.getpid(), "wall_s": 0.0,
            "result": {"torch": torch.get_num_threads(), "interop": torch.get_num_interop_threads(),
                       "omp_env": os.environ.get("OMP_NUM_THREADS"), "openblas_env": os.environ.get("OPENBLAS_NUM_THREADS"),
                       "threads_env": os.environ.get("PROJO4D_THREADS"),
                       "concurrent_env": os.environ.get("PROJO4D_CONCURRENT_RUNS"), "choice": choice,
                       "blas": sorted(set(blas.values()))}}

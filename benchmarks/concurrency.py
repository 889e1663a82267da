"""Several ``projo4d run`` processes on one machine: wall time per run against one run alone (issue #25).

For each N in ``--n`` it starts N ``projo4d run`` processes at the same moment, each on the same
tiny generated scene (read-only) with its own run folder, and waits for all of them. One JSON
line per N::

    {"benchmark": "concurrency", "n": 2, "mode": "told", "device": "cpu", "cores": 2,
     "threads": [1, 1], "wall_s": [...], "mean_s": ..., "max_s": ..., "ratio_to_n1": ...,
     "bound": 1.2 * n / capacity, "within_bound": true, "physics_s": [...], "evaluation_s": [...],
     "gpu_util_mean": ..., "gpu_util_zero_fraction": ..., "load_mean": ...}

``ratio_to_n1`` is the slowest run's wall time divided by the N=1 wall time of the same call
(``--n`` must start with 1 for it). Issue #25's goal: ``ratio_to_n1 <= 1.2 * N / capacity``,
with ``capacity`` (``--capacity``) the number of runs the machine holds at full speed (default 1:
a run alone may use the whole machine). GPU utilization (``nvidia-smi``, once a second, while
any run is alive) shows whether runs sit idle at 0 %.

Modes (``--mode``):

* ``told`` (default): each run gets ``PROJO4D_CONCURRENT_RUNS=N`` (what the benchmark's executors
  and a well-behaved launcher do), so it takes ``cores // N`` threads;
* ``untold``: nothing is set: each run sizes its pools for the whole machine (at most 8 threads),
  which is what a plain shell loop does;
* ``threads=K``: every run gets ``--threads K``.

Before the measurements one untimed run fills Warp's kernel cache (``--no-warmup`` skips it).

Usage::

    python benchmarks/concurrency.py --device cpu --n 1 2                      # 2-core CPU, ~2 min
    python benchmarks/concurrency.py --device cuda --preset gpu --n 1 2 4 8    # one GPU machine
    python benchmarks/concurrency.py --device cuda --preset gpu --n 8 --mode untold --timeout 600

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import threading
import time
from typing import Optional

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: scene and run settings per preset: ``cpu`` is the test suite's tiny scene (32 px, ~1.5k
#: particles); ``gpu`` is issue #25's case (128 px, oracle geometry, 250 iterations)
PRESETS = {
    "cpu": {"scene": dict(width=32, height=32, n_frames=6, n_train_frames=5, dx=0.04, particle_spacing=0.01, substeps=80,
                          supersample=1, ground_plane=False),
            "sim": {"dx": 0.04, "substeps": 30}, "curriculum": "XAS:6@3,XASM:6"},
    "gpu": {"scene": dict(width=128, height=128, n_frames=10, n_train_frames=7, dx=0.02, substeps=200, ground_plane=False),
            "sim": {"dx": 0.02, "substeps": 100}, "curriculum": "XAS:100@3,XASM:150"},
}


def make_scene(root: pathlib.Path, preset: str) -> pathlib.Path:
    """The preset's falling elastic box (generated once, reused)."""
    from toolkit.synthetic import SceneSpec, generate_scene

    if (root / "ground_truth.json").is_file():
        return root
    spec = SceneSpec.preset("small", shape="box", shape_size={"size_x": 0.12, "size_y": 0.08, "size_z": 0.1},
                            material="neo_hookean", params={"E": 3e4, "nu": 0.3}, v0=(0.4, 0.0, 0.0), position=(0.0, 0.16, 0.0),
                            **PRESETS[preset]["scene"])
    generate_scene(spec, root, progress=False)
    return root


class Sampler:
    """Samples GPU utilization (nvidia-smi, when present) and the 1-minute load average."""

    def __init__(self, period: float = 1.0):
        self.period = period
        self.gpu: list[float] = []
        self.load: list[float] = []
        self._stop = threading.Event()
        self.has_smi = shutil.which("nvidia-smi") is not None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.has_smi:
                try:
                    out = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"],
                                         capture_output=True, text=True, timeout=5).stdout
                    vals = [float(v) for v in out.split() if v.strip()]
                    if vals:
                        self.gpu.append(sum(vals) / len(vals))
                except (subprocess.SubprocessError, ValueError, OSError):
                    pass
            self.load.append(os.getloadavg()[0])
            self._stop.wait(self.period)

    def __enter__(self) -> "Sampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def run_batch(n: int, scene: pathlib.Path, out: pathlib.Path, args, tag: str) -> dict:
    """Start ``n`` runs at once; wait (up to ``args.timeout``); collect wall times and summaries."""
    preset = PRESETS[args.preset]
    env = {k: v for k, v in os.environ.items() if k not in ("PROJO4D_THREADS", "PROJO4D_CONCURRENT_RUNS", "OMP_NUM_THREADS",
                                                              "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    extra: list[str] = []
    if args.mode == "told":
        env["PROJO4D_CONCURRENT_RUNS"] = str(n)
    elif args.mode.startswith("threads="):
        extra = ["--threads", args.mode.split("=", 1)[1]]
    procs, starts, folders = [], [], []
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        folder = out / f"{tag}_n{n}_{i}"
        shutil.rmtree(folder, ignore_errors=True)
        folders.append(folder)
        cmd = [sys.executable, "-m", "toolkit.cli", "run", str(scene), "--out", str(folder), "--geometry", "oracle",
               "--stage0", "tiny", "--sim", json.dumps(preset["sim"]), "--curriculum", preset["curriculum"],
               "--material", "neo_hookean", "--device", args.device, *extra]
        log = open(logs / f"{tag}_n{n}_{i}.log", "w")
        starts.append(time.perf_counter())
        procs.append((subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT), log))
    walls: list[Optional[float]] = [None] * n
    deadline = time.perf_counter() + args.timeout
    with Sampler() as sampler:
        while any(w is None for w in walls) and time.perf_counter() < deadline:
            for i, (p, _) in enumerate(procs):
                if walls[i] is None and p.poll() is not None:
                    walls[i] = time.perf_counter() - starts[i]
            time.sleep(0.2)
    codes = []
    for p, log in procs:
        if p.poll() is None:
            p.kill()
            p.wait()
        codes.append(p.returncode)
        log.close()
    summaries = []
    for f in folders:
        path = f / "summary.json"
        summaries.append(json.loads(path.read_text()) if path.is_file() else {})
    done = [w for w in walls if w is not None]
    rec = {"benchmark": "concurrency", "n": n, "mode": args.mode, "device": args.device, "preset": args.preset,
           "cores": len(os.sched_getaffinity(0)), "finished": len(done), "exit_codes": codes,
           "threads": [(s.get("threads") or {}).get("threads") for s in summaries],
           "wall_s": [None if w is None else round(w, 2) for w in walls],
           "mean_s": round(sum(done) / len(done), 2) if done else None, "max_s": round(max(done), 2) if len(done) == n else None,
           "physics_s": [(s.get("timings_s") or {}).get("physics_s") for s in summaries],
           "evaluation_s": [(s.get("timings_s") or {}).get("evaluation_s") for s in summaries],
           "load_mean": round(sum(sampler.load) / len(sampler.load), 2) if sampler.load else None}
    if sampler.gpu:
        rec["gpu_util_mean"] = round(sum(sampler.gpu) / len(sampler.gpu), 1)
        rec["gpu_util_zero_fraction"] = round(sum(1 for g in sampler.gpu if g == 0) / len(sampler.gpu), 3)
    return rec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, nargs="+", default=[1, 2], help="numbers of concurrent runs (start with 1)")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--preset", choices=sorted(PRESETS), default=None, help="scene size (default: the device's)")
    p.add_argument("--mode", default="told", help="told, untold or threads=K (see the module docstring)")
    p.add_argument("--capacity", type=float, default=1.0, help="runs the machine holds at full speed (for 'bound')")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds before unfinished runs are killed")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("/tmp/projo4d_concurrency"))
    p.add_argument("--no-warmup", action="store_true", help="skip the untimed run that fills Warp's kernel cache")
    args = p.parse_args(argv)
    if args.mode not in ("told", "untold") and not args.mode.startswith("threads="):
        p.error(f"--mode must be told, untold or threads=K, got {args.mode!r}")
    args.preset = args.preset or ("cpu" if args.device == "cpu" else "gpu")
    args.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(args.out / f"scene_{args.preset}", args.preset)
    if not args.no_warmup:
        warm = run_batch(1, scene, args.out, args, "warmup")
        print(json.dumps({**warm, "benchmark": "concurrency_warmup"}), flush=True)
    t1 = None
    for n in args.n:
        rec = run_batch(n, scene, args.out, args, "run")
        if n == 1 and rec["max_s"] is not None:
            t1 = rec["max_s"]
        if t1 and rec["max_s"] is not None:
            rec["ratio_to_n1"] = round(rec["max_s"] / t1, 3)
            rec["bound"] = round(1.2 * n / args.capacity, 3)
            rec["within_bound"] = rec["ratio_to_n1"] <= rec["bound"]
        print(json.dumps(rec), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

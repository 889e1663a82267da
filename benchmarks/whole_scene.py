"""Whole scene, stage by stage: wall time of each stage and the accuracy it reaches (issue #16).

Generates one full-size scene of the synthetic suite (``sample_scene_spec(family, index, seed,
"full")``: 400x400 px, 11 cameras, 20 frames; truth simulated at dx 0.01 with 200 substeps and
drawn by the generator's mesh renderer), then runs the whole pipeline on it, ``projo4d run
--config configs/synthetic_<family>.yaml`` (3 fitted cameras, ProJo4D, the config's simulation
settings), once per stage-0 budget. A budget of N iterations is GIC's 40k schedule with every
iteration count scaled by N / 40k (:meth:`toolkit.scene.stage0_schedule.Stage0Schedule.compressed`), so
the trade between stage-0 time and accuracy is visible (``projo4d run --stage0-iterations N``). Each run is a fresh process: its time
includes imports and Warp's kernel compile (from the cache when it is warm; ``cold_cache`` says
whether the cache was emptied first).

One JSON line per budget::

    {"benchmark": "whole_scene", "device_name": ..., "family": "neo_hookean", "stage0_iterations": 10000,
     "wall_s": ..., "stage0_s": ..., "continuum_s": ..., "physics_s": ..., "evaluation_s": ...,
     "init_cd": ..., "cd": ..., "emd": ..., "errors": {"log10_E": ..., "nu": ..., "v0": ...}, ...}

``init_cd`` is the Chamfer distance between the fitted and true particles at frame 0 (stage 0's
geometry); ``cd``/``emd`` are over the future frames (DESIGN §7); ``errors`` as in the strategy
comparison (absolute errors; log10 for log parameters, the v0 vector's norm in m/s);
``grid_check`` the run's grid check (``toolkit.physics.grid_check``: how far a grid of half the
spacing moves the fit, against the fit's residual).

Usage::

    python benchmarks/whole_scene.py --out /tmp/whole --budgets 2500 5000 10000 40000
    python benchmarks/whole_scene.py --out /tmp/whole --budgets 10000 --family plasticine
    python benchmarks/whole_scene.py --out /tmp/whole --generate-only     # write the scene, no fit
    python benchmarks/whole_scene.py --out /tmp/w --size small --device cpu --budgets 400 -- \
        --curriculum-options '{"stage1_iterations": 4, "stage2_iterations": 4}'   # a quick CPU check

Several budgets run one after another; to time them side by side, give each process its own GPU
(``CUDA_VISIBLE_DEVICES=k python benchmarks/whole_scene.py --budgets N``): the scene folder is
shared and generated once (the generator skips a complete scene). Benchmarks are never part of
the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from toolkit.atomic import write_text  # noqa: E402

FAMILY_CONFIGS = {"neo_hookean": "elastic", "newtonian": "newtonian", "non_newtonian": "non_newtonian",
                  "plasticine": "plasticine", "sand": "sand"}


def generate(out: pathlib.Path, family: str, index: int, seed: int, device: str, size: str = "full") -> pathlib.Path:
    """Write (or find complete) the benchmark's scene under ``out/scene``; returns its folder."""
    from toolkit.synthetic.scene import generate_scene, scene_is_complete
    from toolkit.synthetic.suite import sample_scene_spec

    spec = sample_scene_spec(family, index, seed, size, "cuda:0" if device.startswith("cuda") else device)
    folder = out / "scene"
    if not scene_is_complete(folder, spec):
        t = time.perf_counter()
        generate_scene(spec, folder, progress=False)
        print(json.dumps({"benchmark": "whole_scene", "event": "generated", "scene": str(folder), "shape": spec.shape,
                          "params": spec.params, "v0": list(spec.v0), "seconds": round(time.perf_counter() - t, 1)}), flush=True)
    return folder


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        import torch

        return torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cuda (unavailable)"
    import platform

    return f"cpu ({os.cpu_count()} cores, {platform.processor() or platform.machine()})"


def run_budget(scene: pathlib.Path, out: pathlib.Path, family: str, budget: int, device: str, cold_cache: bool,
               extra: list[str]) -> dict:
    """One whole ``projo4d run`` with stage 0 compressed to ``budget`` iterations; its record."""
    from toolkit.benchmark.tables import record_from_run

    run = out / f"stage0_{budget}"
    if run.exists():
        shutil.rmtree(run)
    if cold_cache:
        import warp as wp

        shutil.rmtree(wp.config.kernel_cache_dir or pathlib.Path.home() / ".cache" / "warp", ignore_errors=True)
    cmd = [sys.executable, "-m", "toolkit.cli", "run", str(scene), "--config", str(ROOT / "configs" / f"synthetic_{FAMILY_CONFIGS[family]}.yaml"),
           "--out", str(run), "--stage0-iterations", str(budget), "--device", device, *extra]
    t = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, check=False)
    wall = time.perf_counter() - t
    write_text(out / f"stage0_{budget}.log", proc.stdout)
    rec = record_from_run(run, {"scene": "whole_scene", "strategy": "progressive", "cameras": 3}) if proc.returncode == 0 else None
    line = {"benchmark": "whole_scene", "device_name": device_name(device), "family": family, "stage0_iterations": budget,
            "returncode": proc.returncode, "wall_s": round(wall, 1), "cold_cache": cold_cache}
    if rec is None:
        line["error"] = proc.stdout[-2000:]
        return line
    line.update({k: round(float(v), 2) for k, v in rec["timings_s"].items() if isinstance(v, (int, float))})
    line.update({k: rec["metrics"][k] for k in ("init_cd", "cd", "emd", "psnr")})
    line["errors"] = rec["errors"]
    summary = json.loads((run / "summary.json").read_text())
    line["estimates"] = {r["parameter"]: {k: r.get(k) for k in ("estimate", "truth", "label", "low", "high", "grid_value")}
                         for r in summary.get("parameters", []) if isinstance(r, dict)}
    grid = summary.get("grid_check") or {}
    line["grid_check"] = {k: grid.get(k) for k in ("dx", "fine_dx", "shift_m", "residual_m", "converged", "skipped") if k in grid}
    settings = run / "settings.json"
    line["sim"] = json.loads(settings.read_text()).get("sim") if settings.is_file() else None  # the fit's grid
    return line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="folder for the scene and the runs")
    parser.add_argument("--family", default="neo_hookean", choices=sorted(FAMILY_CONFIGS))
    parser.add_argument("--index", type=int, default=0, help="scene index in the suite (default 0)")
    parser.add_argument("--seed", type=int, default=0, help="suite seed (default 0)")
    parser.add_argument("--budgets", type=int, nargs="+", default=[2500, 5000, 10000, 40000],
                        help="stage-0 iterations, one whole run each (default 2500 5000 10000 40000)")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--size", default="full", choices=["full", "small"],
                        help="scene size preset (small: 64 px, for a quick CPU check of the script)")
    parser.add_argument("--cold-cache", action="store_true", help="empty Warp's kernel cache before each run")
    parser.add_argument("--generate-only", action="store_true")
    parser.add_argument("run_args", nargs="*", help="after --: more `projo4d run` arguments")
    args = parser.parse_args()
    bad = [b for b in args.budgets if b < 100]
    if bad:
        parser.error(f"--budgets must be >= 100 iterations, got {bad}")
    out = pathlib.Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if args.generate_only:
        generate(out, args.family, args.index, args.seed, args.device, args.size)
        return
    # generate in a child process: Warp's memory pool keeps what the truth simulation took until the
    # process ends, and the fit needs the card (46 GB for sand/002 before deterministic rollouts
    # stopped capturing graphs; see toolkit.mpm.config.captures_graphs)
    gen = [sys.executable, str(pathlib.Path(__file__).resolve()), "--out", str(out), "--family", args.family,
           "--index", str(args.index), "--seed", str(args.seed), "--device", args.device, "--size", args.size,
           "--generate-only"]
    if subprocess.run(gen, cwd=ROOT, check=False).returncode != 0:
        sys.exit("whole_scene: generating the scene failed (its output is above)")
    scene = out / "scene"
    for budget in args.budgets:
        line = run_budget(scene, out, args.family, budget, args.device, args.cold_cache, args.run_args)
        print(json.dumps(line), flush=True)
        # one budget per GPU means several processes add to this file: each adds one line in one
        # O_APPEND write (whole lines, none lost), which a read-and-replace could not promise
        with open(out / "whole_scene.jsonl", "a") as f:
            f.write(json.dumps(line) + "\n")


if __name__ == "__main__":
    main()

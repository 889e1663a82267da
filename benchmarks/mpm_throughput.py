"""Throughput of the Warp MPM: forward and forward+backward, per material and particle count.

Prints one JSON line per measurement. Examples::

    python benchmarks/mpm_throughput.py                      # cuda, N in 1e4, 3.2e4, 1e5, 3e5
    python benchmarks/mpm_throughput.py --device cpu --small  # a quick CPU run
    python benchmarks/mpm_throughput.py --memory              # 1e5 particles x 2600 substeps with gradients
    python benchmarks/mpm_throughput.py --cold-compile        # compile time of the differentiable step

Particles fill a cube on a lattice of dx/2 (the default particle spacing), dropped onto the ground.
Fields: material, device, n, substeps, fwd_us_per_substep, fwd_particle_substeps_per_s,
fwd_bwd_us_per_substep, iteration_over_forward (one gradient step / forward rollout), keep_tapes
(the setting, ``--keep-tapes``) and tapes_kept (whether the forward's tapes were kept, so the
backward pass skipped the recompute: ``toolkit.mpm.tapes``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np


def _block(n_target: int, spacing: float):
    import torch

    side = max(2, round(n_target ** (1 / 3)))
    idx = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = (idx + 0.5) * spacing + np.array([0.0, 0.3, 0.0])
    return torch.tensor(pts, dtype=torch.float32)


PARAMS = {
    "neo_hookean": {"E": 1e5, "nu": 0.3},
    "neo_hookean_simplicits": {"E": 1e5, "nu": 0.3},
    "newtonian": {"mu": 1.0, "kappa": 1e4},
    "non_newtonian": {"mu": 100.0, "kappa": 1e5, "yield_stress": 10.0, "plastic_viscosity": 1.0},
    "plasticine": {"E": 1e5, "nu": 0.3, "yield_stress": 1e3},
    "sand": {"friction_angle": 30.0, "E": 1e5},
}


def _sync(device: str) -> None:
    import torch
    import warp as wp

    wp.synchronize_device(device)
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _time(fn, device: str, repeats: int) -> float:
    fn()  # warm-up: compile, graph capture, allocation
    _sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def measure(material: str, n: int, device: str, frames: int, substeps: int, repeats: int, backward: bool,
            keep_tapes: bool | str = "auto") -> dict:
    import torch

    from toolkit.mpm import MPMSimulator, SimConfig

    cfg = SimConfig(substeps=substeps, checkpoint_every=25, margin=0.1, keep_tapes=keep_tapes)
    sim = MPMSimulator(material, cfg, device=device)
    x0 = _block(n, cfg.dx / 2).to(sim._torch_device)
    v0 = torch.tensor([0.2, -0.5, 0.1], device=sim._torch_device)
    params = sim.material.pack(PARAMS[material], device=sim._torch_device)
    steps = frames * substeps
    fwd = _time(lambda: sim.rollout(x0, v0, params, n_frames=frames), device, repeats)
    rec = {
        "material": material,
        "device": device,
        "n": int(x0.shape[0]),
        "substeps": steps,
        "grid_nodes": sim.grid.n_nodes,
        "fwd_us_per_substep": round(fwd / steps * 1e6, 3),
        "fwd_particle_substeps_per_s": round(x0.shape[0] * steps / fwd, 1),
    }
    if backward:
        raw = sim.material.to_raw(PARAMS[material]).to(sim._torch_device).requires_grad_()
        v = v0.clone().requires_grad_()
        w = torch.randn(frames + 1, x0.shape[0], 3, device=sim._torch_device)

        def step():
            out = sim.simulate(x0, v, sim.material.to_physical(raw), n_frames=frames)
            (out.positions * w).sum().backward()

        both = _time(step, device, repeats)
        rec["fwd_bwd_us_per_substep"] = round(both / steps * 1e6, 3)
        rec["iteration_over_forward"] = round(both / fwd, 3)
        rec["keep_tapes"] = keep_tapes
        rec["tapes_kept"] = any(k[0] == "tapes" for k in sim._buffers)
    return rec


def memory_probe(device: str, n: int = 100_000, frames: int = 26, substeps: int = 100) -> dict:
    """Peak device memory of one gradient step over frames x substeps (DESIGN target: < 4 GB)."""
    import torch
    import warp as wp

    from toolkit.mpm import MPMSimulator, SimConfig

    cfg = SimConfig(substeps=substeps, checkpoint_every=25, margin=0.1, ground_height=None, gravity=(0, 0, 0))
    sim = MPMSimulator("neo_hookean", cfg, device=device)
    x0 = _block(n, cfg.dx / 2).to(sim._torch_device)
    raw = sim.material.to_raw(PARAMS["neo_hookean"]).to(sim._torch_device).requires_grad_()
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    out = sim.simulate(x0, torch.tensor([0.1, 0.0, 0.0], device=sim._torch_device), sim.material.to_physical(raw), n_frames=frames)
    out.positions[-1].sum().backward()
    _sync(device)
    rec = {"probe": "memory", "device": device, "n": int(x0.shape[0]), "substeps": frames * substeps,
           "seconds": round(time.perf_counter() - t0, 2), "grid_nodes": sim.grid.n_nodes}
    if device.startswith("cuda"):
        rec["torch_peak_gb"] = round(torch.cuda.max_memory_allocated() / 1e9, 3)
        high = getattr(wp, "get_mempool_used_mem_high", None)
        if high is not None:
            rec["warp_peak_gb"] = round(high(device) / 1e9, 3)
    return rec


def cold_compile(device: str) -> dict:
    """Compile time of the differentiable step from an empty kernel cache (fresh process)."""
    code = (
        "import time, torch; t=time.perf_counter();"
        "import warp as wp; wp.config.quiet=True; wp.init();"
        "from toolkit.mpm import MPMSimulator, SimConfig;"
        f"sim=MPMSimulator('plasticine', SimConfig(substeps=4), device='{device}');"
        "x=torch.rand(64,3)*0.05+0.3; x.requires_grad_(True);"
        "o=sim.simulate(x, None, None, n_frames=1); o.positions.sum().backward();"
        "wp.synchronize(); print(time.perf_counter()-t)"
    )
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, WARP_CACHE_PATH=cache)
        t = float(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()[-1])
    return {"probe": "cold_compile", "device": device, "material": "plasticine", "seconds": round(t, 2)}


def main() -> None:
    import torch
    import warp as wp

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--materials", nargs="*", default=list(PARAMS))
    parser.add_argument("--sizes", nargs="*", type=float, default=None)
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--substeps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--small", action="store_true", help="CPU-sized run: N = 1e3, 4e3")
    parser.add_argument("--no-backward", action="store_true")
    parser.add_argument("--keep-tapes", nargs="+", default=["auto"], choices=["auto", "true", "false"],
                        help="SimConfig.keep_tapes values to time side by side (default auto)")
    parser.add_argument("--memory", action="store_true", help="run the 1e5 x 2600-substep memory probe")
    parser.add_argument("--cold-compile", action="store_true", help="time compiling from an empty cache")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    if args.cold_compile:
        print(json.dumps(cold_compile(args.device)), flush=True)
    if args.memory:
        print(json.dumps(memory_probe(args.device)), flush=True)
        return
    sizes = args.sizes or ([1e3, 4e3] if args.small else [1e4, 32768, 1e5, 3e5])
    for material in args.materials:
        for n in sizes:
            for keep in args.keep_tapes:
                rec = measure(material, int(n), args.device, args.frames, args.substeps, args.repeats, not args.no_backward,
                              {"auto": "auto", "true": True, "false": False}[keep])
                print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()

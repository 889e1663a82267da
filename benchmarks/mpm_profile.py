"""Where the simulator's time goes: per-kernel GPU time of a forward substep and of one gradient
step, and the host's share of a rollout.

Prints JSON lines. Example (on the GPU machine)::

    python benchmarks/mpm_profile.py --sizes 32768 1e5 --frames 2 --substeps 100

Fields of a ``"probe": "kernels"`` line: ``pass`` (forward or gradient), ``us_per_substep`` per
kernel or memset name (GPU time from Warp's activity timing, launched without graphs), and
``launches_per_substep``. A ``"probe": "rollout"`` line splits a graph-captured rollout into
``prepare_us`` (input checks, grid sizing, per call) and ``rollout_us_per_substep`` (whole call).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict



def _scene(n: int, device: str, substeps: int, graphs, variant: str = "lattice"):
    """``variant``: the particles' order, ``lattice`` (the benchmark's: z fastest) or ``shuffled``
    (random; a P2G scatter's speed depends on how often a warp's lanes add into the same nodes)."""
    import torch

    from mpm_throughput import PARAMS, _block
    from toolkit.mpm import MPMSimulator, SimConfig

    cfg = SimConfig(substeps=substeps, checkpoint_every=25, margin=0.1, graphs=graphs)
    sim = MPMSimulator("neo_hookean", cfg, device=device)
    x0 = _block(n, cfg.dx / 2).to(sim._torch_device)
    if variant == "shuffled":
        x0 = x0[torch.randperm(x0.shape[0], generator=torch.Generator().manual_seed(0)).to(x0.device)].contiguous()
    v0 = torch.tensor([0.2, -0.5, 0.1], device=sim._torch_device)
    params = sim.material.pack(PARAMS["neo_hookean"], device=sim._torch_device)
    return sim, x0, v0, params


def kernel_times(n: int, device: str, frames: int, substeps: int, variant: str = "lattice") -> list[dict]:
    """GPU time per kernel and memset, forward and forward+backward, launched one by one."""
    import torch
    import warp as wp

    from mpm_throughput import PARAMS, _sync

    sim, x0, v0, params = _scene(n, device, substeps, graphs=False, variant=variant)
    steps = frames * substeps
    raw = sim.material.to_raw(PARAMS["neo_hookean"]).to(sim._torch_device).requires_grad_()
    w = torch.randn(frames + 1, x0.shape[0], 3, device=sim._torch_device)

    def gradient_step():
        out = sim.simulate(x0, v0, sim.material.to_physical(raw), n_frames=frames)
        (out.positions * w).sum().backward()

    out = []
    for name, fn in (("forward", lambda: sim.rollout(x0, v0, params, n_frames=frames)), ("gradient", gradient_step)):
        fn()
        _sync(device)
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        fn()
        _sync(device)
        results = wp.timing_end()
        per = defaultdict(float)
        count = 0
        for r in results:
            per[r.name] += r.elapsed
            count += 1
        rec = {"probe": "kernels", "variant": variant, "pass": name, "device": device, "n": int(x0.shape[0]), "grid_nodes": sim.grid.n_nodes,
               "substeps": steps, "launches_per_substep": round(count / steps, 2),
               "total_us_per_substep": round(sum(per.values()) * 1e3 / steps, 2),
               "us_per_substep": {k: round(v * 1e3 / steps, 2) for k, v in sorted(per.items(), key=lambda kv: -kv[1])}}
        out.append(rec)
    return out


def rollout_split(n: int, device: str, frames: int, substeps: int, repeats: int, variant: str = "lattice") -> dict:
    """Host share of a graph-captured rollout."""
    from mpm_throughput import _time

    sim, x0, v0, params = _scene(n, device, substeps, graphs="auto", variant=variant)
    steps = frames * substeps
    total = _time(lambda: sim.rollout(x0, v0, params, n_frames=frames), device, repeats)
    prep = _time(lambda: sim._prepare(x0, v0, params, None, None, frames), device, repeats)
    rec = {"probe": "rollout", "variant": variant, "device": device, "n": int(x0.shape[0]), "substeps": steps,
           "rollout_us_per_substep": round(total / steps * 1e6, 2), "prepare_us": round(prep * 1e6, 1)}
    return rec


def main() -> None:
    import torch
    import warp as wp

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--sizes", nargs="*", type=float, default=[32768])
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--substeps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--variants", nargs="*", default=["lattice"], choices=["lattice", "shuffled"])
    parser.add_argument("--no-kernels", action="store_true", help="only the rollout timing")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    for n in args.sizes:
        for variant in args.variants:
            if args.device.startswith("cuda") and not args.no_kernels:
                for rec in kernel_times(int(n), args.device, args.frames, args.substeps, variant):
                    print(json.dumps(rec), flush=True)
            print(json.dumps(rollout_split(int(n), args.device, args.frames, args.substeps, args.repeats, variant)), flush=True)


if __name__ == "__main__":
    main()

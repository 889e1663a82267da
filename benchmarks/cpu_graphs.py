"""Captured Warp graphs against launch by launch on the CPU: when replaying pays (issue #16).

A block of particles falls onto a sticky ground for 6 frames of 40 substeps; each timed pass is
the rollout plus its gradient (``loss.backward()``), on one CPU thread, best of ``--reps - 2``
after two warm-up passes (a CPU chain is launched one by one on its first use and captured on its
second, :class:`toolkit.mpm.graph_cache.GraphCache`). The grid is auto-sized around the block and its
fall, so a finer ``dx`` gives a larger grid around the same body. ``SimConfig.graphs="auto"``
captures on the CPU up to :data:`toolkit.mpm.config.CPU_GRAPH_MAX_NODES` grid nodes.

One JSON line per case::

    {"benchmark": "cpu_graphs", "particles": 216, "dx": 0.04, "grid": [15, 14, 15], "nodes": 3150,
     "launched_s": ..., "captured_s": ..., "speedup": ..., "auto_captures": true, "same_result": true}

Usage::

    python benchmarks/cpu_graphs.py                      # the default cases
    python benchmarks/cpu_graphs.py --cases 216:0.04 4096:0.01
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from toolkit.mpm import MPMSimulator, SimConfig
from toolkit.mpm.config import captures_graphs


def _block(side: int) -> torch.Tensor:
    """``side**3`` particles filling a 10 cm cube whose bottom is 15 cm above the ground."""
    h = 0.1 / side
    axis = (np.arange(side) + 0.5) * h - 0.05
    x = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + np.array([0.5, 0.2, 0.5])
    return torch.tensor(x, dtype=torch.float32)


def _passes(graphs: bool, side: int, dx: float, reps: int) -> tuple[float, list, float, np.ndarray]:
    sim = MPMSimulator("neo_hookean", SimConfig(dx=dx, substeps=40, boundary="sticky", graphs=graphs), device="cpu")
    x0 = _block(side)
    raw0 = sim.material.to_raw({"E": 2e4, "nu": 0.3})
    times = []
    for _ in range(reps):
        raw = raw0.clone().requires_grad_()
        v0 = torch.tensor([0.3, -0.5, 0.1], requires_grad=True)
        t = time.perf_counter()
        out = sim.simulate(x0, v0, sim.material.to_physical(raw), gravity=torch.tensor([0.0, -9.8, 0.0]), n_frames=6)
        loss = out.positions[1:].sum()
        loss.backward()
        times.append(time.perf_counter() - t)
    return min(times[2:]), list(sim.grid.dims), loss.item(), raw.grad.numpy().copy()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["216:0.04", "1000:0.04", "4096:0.02", "216:0.03", "216:0.025",
                                                      "4096:0.025", "216:0.01", "4096:0.01"],
                    help="PARTICLES:DX, PARTICLES a cube (216, 1000, 4096, ...)")
    ap.add_argument("--reps", type=int, default=4)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    for case in args.cases:
        n, dx = case.split(":")
        side = round(int(n) ** (1 / 3))
        launched, dims, loss_l, grad_l = _passes(False, side, float(dx), args.reps)
        captured, _, loss_c, grad_c = _passes(True, side, float(dx), args.reps)
        nodes = int(np.prod(dims))
        print(json.dumps({"benchmark": "cpu_graphs", "particles": side ** 3, "dx": float(dx), "grid": dims, "nodes": nodes,
                          "launched_s": round(launched, 4), "captured_s": round(captured, 4),
                          "speedup": round(launched / captured, 3), "auto_captures": captures_graphs("auto", "cpu", False, nodes),
                          "same_result": bool(loss_l == loss_c and np.array_equal(grad_l, grad_c))}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

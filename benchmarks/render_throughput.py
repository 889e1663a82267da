"""Renderer throughput: forward and forward+backward time per batched call of 3 cameras.

For every available renderer backend (default: all registered except the dense ``"torch"``
reference, which is far too slow at these sizes; add it with ``--backends``), every N and every
square resolution, it renders random Gaussians (means in a 1 m cube in front of the cameras,
standard deviations 1-3 cm, random rotations, opacities and colours) into 3 cameras in one call,
warms up, then reports the median over timed repeats, synchronizing the device (torch and Warp)
around every timed region. One JSON line per (backend, N, resolution):

    {"backend": "warp", "device": "cuda", "device_name": ..., "n": 100000, "width": 800,
     "height": 800, "cams": 3, "fwd_ms": ..., "fwd_bwd_ms": ..., "fwd_bwd_ms_per_view": ...,
     "fwd_ratio_to_gsplat": ..., "fwd_bwd_ratio_to_gsplat": ...}

The ratios (time / gsplat time, lower is better) appear when gsplat ran in the same process for
the same configuration (it runs first). ``fwd_bwd`` times one forward plus one backward with fixed
random cotangents for rgb, alpha and depth, gradients w.r.t. every Gaussian attribute.

Usage::

    python benchmarks/render_throughput.py                        # CUDA when present
    python benchmarks/render_throughput.py --device cpu --small   # quick CPU run
    python benchmarks/render_throughput.py --device cpu --small --cpu-tile-edges 16 4   # CPU tile edges

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import statistics
import sys
import time
from typing import Callable

import torch

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from renderers import RENDERERS, get_renderer  # noqa: E402
from renderers.base import Gaussians  # noqa: E402
from toolkit.cameras import Cameras  # noqa: E402

FULL_NS = (10_000, 100_000, 500_000)
FULL_RES = (400, 800)
SMALL_NS = (1_000, 10_000)
SMALL_RES = (64, 128)
CAMS = 3


def random_scene(n: int, res: int, device: str, seed: int = 0) -> tuple[Gaussians, Cameras]:
    """N random Gaussians in a 1 m cube at the origin and 3 cameras 2.5 m away looking at it.

    The 40 degree field of view makes the cube fill most of each image.
    """
    g = torch.Generator().manual_seed(seed)
    gs = Gaussians(
        means=torch.rand(n, 3, generator=g) - 0.5,
        log_scales=torch.log(0.01 + 0.02 * torch.rand(n, 3, generator=g)),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
    ).to(device)
    eyes = []
    for k in range(CAMS):
        a = 2.0 * math.pi * k / CAMS + 0.2
        eyes.append([2.5 * math.sin(a), 0.5, 2.5 * math.cos(a)])
    cams = Cameras.look_at(torch.tensor(eyes), (0.0, 0.0, 0.0), fov_y_deg=40.0, width=res, height=res)
    return gs, cams.to(device)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        import warp as wp

        torch.cuda.synchronize(device)
        wp.synchronize_device(device)


def _median_ms(fn: Callable[[], None], device: str, warmup: int, repeats: int) -> float:
    for _ in range(warmup):
        fn()
    _sync(device)
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def bench_one(name: str, n: int, res: int, device: str, warmup: int, repeats: int, validate: bool) -> dict:
    """Median forward and forward+backward milliseconds of backend ``name`` for one configuration."""
    renderer = get_renderer(name)
    if not validate:
        try:
            renderer = get_renderer(name, validate=False)
        except TypeError:  # this backend always validates
            pass
    gs, cams = random_scene(n, res, device)
    attrs = ("means", "log_scales", "quats", "opacity_logits", "colors")
    leaves = {k: getattr(gs, k).detach().clone().requires_grad_(True) for k in attrs}
    g = Gaussians(**leaves)
    gen = torch.Generator().manual_seed(1)
    cot = [
        torch.randn(CAMS, res, res, 3, generator=gen).to(device),
        torch.randn(CAMS, res, res, generator=gen).to(device),
        torch.randn(CAMS, res, res, generator=gen).to(device),
    ]

    def forward() -> None:
        with torch.no_grad():
            renderer(g, cams)

    def forward_backward() -> None:
        out = renderer(g, cams)
        torch.autograd.backward([out.rgb, out.alpha, out.depth], cot)
        for t in leaves.values():
            t.grad = None

    fwd = _median_ms(forward, device, warmup, repeats)
    fwd_bwd = _median_ms(forward_backward, device, warmup, repeats)
    return {"fwd_ms": round(fwd, 4), "fwd_bwd_ms": round(fwd_bwd, 4), "fwd_bwd_ms_per_view": round(fwd_bwd / CAMS, 4)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cuda, cuda:1 or cpu")
    parser.add_argument("--small", action="store_true", help=f"N in {SMALL_NS} at {SMALL_RES} px (quick CPU run)")
    parser.add_argument("--backends", default=None, help="comma-separated backends (default: all registered but 'torch')")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats (default 20 on CUDA, 5 on CPU)")
    parser.add_argument("--no-validate", action="store_true", help="skip per-call input checks where a backend allows it")
    parser.add_argument("--cpu-tile-edges", type=int, nargs="+", default=None, metavar="PX",
                        help="on the CPU, also time the warp backend with these tile edges (default: its own, "
                             "renderers.warp_tiles.CPU_TILE_SIZE); e.g. 16 4 compares the old and new edge")
    args = parser.parse_args(argv)
    if args.cpu_tile_edges and args.device.startswith("cuda"):
        parser.error(f"--cpu-tile-edges applies to --device cpu, not {args.device!r} (CUDA tiles are 16 px)")
    if args.cpu_tile_edges and min(args.cpu_tile_edges) < 1:
        parser.error(f"--cpu-tile-edges must be >= 1 px, got {args.cpu_tile_edges}")

    device = args.device
    if device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("CUDA is not available; use --device cpu --small")
    repeats = args.repeats or (20 if device.startswith("cuda") else 5)
    names = args.backends.split(",") if args.backends else [b for b in RENDERERS.names() if b != "torch"]
    names = sorted(names, key=lambda b: b != "gsplat")  # gsplat first: the others report ratios to it
    ns, resolutions = (SMALL_NS, SMALL_RES) if args.small else (FULL_NS, FULL_RES)
    device_name = torch.cuda.get_device_name(device) if device.startswith("cuda") else "cpu"

    for n in ns:
        for res in resolutions:
            baseline = None
            for name, edge in [(b, e) for b in names for e in (args.cpu_tile_edges if b == "warp" and args.cpu_tile_edges else [None])]:
                line = {"backend": name, "device": device, "device_name": device_name}
                line.update(n=n, width=res, height=res, cams=CAMS)
                if edge is not None:
                    import renderers.warp_tiles as warp_tiles

                    warp_tiles.CPU_TILE_SIZE = edge
                    line["cpu_tile_edge"] = edge
                try:
                    line.update(bench_one(name, n, res, device, args.warmup, repeats, not args.no_validate))
                except Exception as exc:  # report and go on with the other backends
                    line["error"] = f"{type(exc).__name__}: {exc}"
                    print(json.dumps(line), flush=True)
                    continue
                if name == "gsplat":
                    baseline = line
                elif baseline is not None:
                    line["fwd_ratio_to_gsplat"] = round(line["fwd_ms"] / baseline["fwd_ms"], 3)
                    line["fwd_bwd_ratio_to_gsplat"] = round(line["fwd_bwd_ms"] / baseline["fwd_bwd_ms"], 3)
                print(json.dumps(line), flush=True)
                if device.startswith("cuda"):
                    torch.cuda.empty_cache()


if __name__ == "__main__":
    main()

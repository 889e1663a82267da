"""Stage 0 training speed: iterations per second of :class:`Gaussians4DModule`.

For every renderer backend (default: every registered one except the dense ``"torch"`` reference
on images larger than 128 px), image size, Gaussian count and phase, it builds an in-memory scene
(3 cameras on a ring at PAC-NeRF-like spacing looking at a textured ellipsoid of Gaussians that
falls and slides over the frames; ground truth rendered once with the same backend, masks from its
alpha), initializes the model in the visual hull with exactly N Gaussians, disables densification
(N stays fixed), and runs the real Lightning training loop. After ``--warmup-iters`` untimed
iterations it times ``--iters`` iterations, synchronizing the device at both ends. One JSON line
per configuration::

    {"benchmark": "stage0_speed", "device": "cuda", "device_name": ..., "renderer": "warp",
     "phase": "dynamic", "n_gaussians": 100000, "width": 800, "height": 800, "cams": 3,
     "network": "gic", "sh_degree": 3, "iters": 200, "it_per_s": ..., "ms_per_it": ...,
     "views_per_s": ..., "peak_mem_mb": ..., "it_per_s_ratio_to_gsplat": ...}

``phase`` is ``dynamic`` (after the warm-up: deformation network + renderer, the 37k of GIC's 40k
iterations) or ``static`` (warm-up: renderer only). The ratio to gsplat (higher is better for the
other backend) appears when the gsplat backend ran the same configuration in the same process.

Usage::

    python benchmarks/stage0_speed.py                      # CUDA when present, PAC-NeRF-like sizes
    python benchmarks/stage0_speed.py --device cpu --small --threads 1   # quick CPU run

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

import torch

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import pytorch_lightning as pl  # noqa: E402

from renderers import RENDERERS, get_renderer  # noqa: E402
from renderers.base import Gaussians  # noqa: E402
from toolkit.cameras import Cameras  # noqa: E402
from toolkit.scene.deformation import DeformationConfig  # noqa: E402
from toolkit.scene.gaussian_model import DensificationConfig  # noqa: E402
from toolkit.scene.stage0 import (  # noqa: E402
    Gaussians4DModule,
    Stage0DataModule,
    Stage0Schedule,
    TrainingViews,
    default_renderer_name,
)

FULL_NS = (30_000, 100_000, 300_000)
FULL_RES = (400, 800)
SMALL_NS = (1_000,)
SMALL_RES = (64,)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def make_views(res: int, n_frames: int, device: str, cams: int = 3, seed: int = 0) -> TrainingViews:
    """Ground truth of a textured ellipsoid (about 0.3 m wide) falling and sliding, seen by
    ``cams`` cameras 2 m away (fov 40 degrees), rendered with the default backend."""
    g = torch.Generator().manual_seed(seed)
    n_gt = 20_000
    u = torch.randn(n_gt, 3, generator=g)
    u = u / u.norm(dim=-1, keepdim=True) * torch.rand(n_gt, 1, generator=g) ** (1 / 3)
    base = u * torch.tensor([0.16, 0.08, 0.12]) + torch.tensor([0.0, 0.4, 0.0])
    colors = 0.5 + 0.4 * torch.sin(12.0 * base + torch.tensor([0.0, 2.0, 4.0]))
    eyes = []
    for k in range(cams):
        a = 2 * math.pi * k / cams
        eyes.append([2.0 * math.sin(a), 0.9, 2.0 * math.cos(a)])
    cameras = Cameras.look_at(torch.tensor(eyes), target=(0.0, 0.3, 0.0), width=res, height=res, fov_y_deg=40.0)
    fps = 24.0
    times = torch.arange(n_frames, dtype=torch.float32) / fps
    r = get_renderer(default_renderer_name())  # the ground truth is not timed: use the fast backend
    images, masks = [], []
    with torch.no_grad():
        for t in times.tolist():
            offset = torch.tensor([0.4 * t, -4.9 * t * t, 0.0])
            gs = Gaussians(
                means=(base + offset).to(device),
                log_scales=torch.full((n_gt, 3), math.log(0.006), device=device),
                quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device).expand(n_gt, 4).contiguous(),
                opacity_logits=torch.full((n_gt,), 4.0, device=device),
                colors=colors.to(device),
            )
            out = r(gs, cameras.to(device))
            images.append(out.rgb)
            masks.append((out.alpha > 0.5).float())
    return TrainingViews(
        cameras=cameras,
        images=torch.stack(images).cpu(),
        masks=torch.stack(masks).cpu(),
        times=times,
        frames=list(range(n_frames)),
        camera_indices=list(range(cams)),
    )


class _Timer(pl.Callback):
    def __init__(self, start_step: int, device: str):
        self.start_step, self.device = start_step, device
        self.t0 = self.t1 = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if pl_module.step == self.start_step:
            _sync(self.device)
            self.t0 = time.perf_counter()

    def on_train_end(self, trainer, pl_module):
        _sync(self.device)
        self.t1 = time.perf_counter()


def run_one(views: TrainingViews, renderer: str, n: int, phase: str, network: str, sh_degree: int,
            iters: int, warmup_iters: int, device: str) -> dict:
    total = warmup_iters + iters
    schedule = Stage0Schedule(
        iterations=total,
        warmup=0 if phase == "dynamic" else total + 1,
        densify_from=total + 1,
        densify_until=0,
        sh_increase_interval=1,
        densification=DensificationConfig(),
        log_every=0,
    )
    deformation = DeformationConfig() if network == "gic" else DeformationConfig.tiny()
    module = Gaussians4DModule(schedule, deformation, sh_degree=sh_degree, renderer=renderer, init="hull", init_points=n)
    timer = _Timer(warmup_iters, device)
    trainer = pl.Trainer(
        accelerator="gpu" if device.startswith("cuda") else "cpu",
        devices=1,
        max_epochs=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        callbacks=[timer],
    )
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    trainer.fit(module, datamodule=Stage0DataModule(views=views))
    seconds = timer.t1 - timer.t0
    rec = {
        "benchmark": "stage0_speed",
        "device": "cuda" if device.startswith("cuda") else "cpu",
        "device_name": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu",
        "renderer": renderer,
        "phase": phase,
        "n_gaussians": module.gaussians.n,
        "width": views.cameras.width,
        "height": views.cameras.height,
        "cams": views.n_cameras,
        "network": network,
        "sh_degree": sh_degree,
        "iters": iters,
        "torch_threads": torch.get_num_threads(),
        "it_per_s": iters / seconds,
        "ms_per_it": 1e3 * seconds / iters,
        "views_per_s": iters * views.n_cameras / seconds,
    }
    if device.startswith("cuda"):
        rec["peak_mem_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return rec


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--renderers", default=None, help="comma-separated backend names (default: all but 'torch' above 128 px)")
    p.add_argument("--sizes", default=None, help="comma-separated square image sizes, px")
    p.add_argument("--gaussians", default=None, help="comma-separated Gaussian counts")
    p.add_argument("--phases", default="dynamic,static")
    p.add_argument("--network", choices=("gic", "tiny"), default=None, help="deformation network (default gic; tiny with --small)")
    p.add_argument("--sh-degree", type=int, default=None, help="SH degree (default 3; 0 with --small)")
    p.add_argument("--frames", type=int, default=14)
    p.add_argument("--iters", type=int, default=None)
    p.add_argument("--warmup-iters", type=int, default=None)
    p.add_argument("--small", action="store_true", help="CPU-sized run: 64 px, 1000 Gaussians, tiny network")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (use 1 on a shared machine: oversubscribed threads were 25x slower)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    sizes = [int(s) for s in args.sizes.split(",")] if args.sizes else list(SMALL_RES if args.small else FULL_RES)
    ns = [int(s) for s in args.gaussians.split(",")] if args.gaussians else list(SMALL_NS if args.small else FULL_NS)
    network = args.network or ("tiny" if args.small else "gic")
    sh_degree = args.sh_degree if args.sh_degree is not None else (0 if args.small else 3)
    iters = args.iters or (20 if args.small else 200)
    warmup_iters = args.warmup_iters if args.warmup_iters is not None else (5 if args.small else 20)
    names = args.renderers.split(",") if args.renderers else RENDERERS.names()
    # gsplat first, so the other backends can report their ratio to it
    names = sorted(names, key=lambda n: (n != "gsplat", n))

    for res in sizes:
        views = make_views(res, args.frames, args.device)
        for name in names:
            if name == "torch" and res > 128 and not args.renderers:
                continue
            for n in ns:
                for phase in args.phases.split(","):
                    rec = run_one(views, name, n, phase, network, sh_degree, iters, warmup_iters, args.device)
                    key = (res, n, phase)
                    if name == "gsplat":
                        main.gsplat[key] = rec["it_per_s"]  # type: ignore[attr-defined]
                    elif key in main.gsplat:  # type: ignore[attr-defined]
                        rec["it_per_s_ratio_to_gsplat"] = rec["it_per_s"] / main.gsplat[key]  # type: ignore[attr-defined]
                    print(json.dumps(rec), flush=True)
    return 0


main.gsplat = {}  # type: ignore[attr-defined]

if __name__ == "__main__":
    raise SystemExit(main())

"""``projo4d demo``: the embedded default job, runnable with no download on a 2-core CPU.

It simulates an elastic torus dropped on the ground with the differentiable Warp MPM, renders
the particles as Gaussians with a registered renderer from three cameras, recovers Young's
modulus and the initial velocity from the simulated positions by gradient descent through the
simulator, and writes an image strip, a video and a JSON summary to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

__all__ = ["configure", "run", "run_demo"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"), help="output folder (default: %(default)s)")
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default: %(default)s)")
    parser.add_argument("--frames", type=int, default=12, help="frames to simulate at 24 fps (default: %(default)s)")
    parser.add_argument("--iterations", type=int, default=30, help="gradient steps of the parameter fit (default: %(default)s)")
    parser.add_argument("--renderer", default="warp", help="registered renderer name (default: %(default)s)")
    parser.add_argument("--size", type=int, default=96, help="image size in pixels (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    summary = run_demo(args.out, device=args.device, frames=args.frames, iterations=args.iterations,
                       renderer=args.renderer, size=args.size)
    print(json.dumps(summary, indent=2))
    return 0


def _device(name: str) -> str:
    import torch

    if name == "auto":
        return "cuda:0" if torch.cuda.is_available() else "cpu"
    return name


def run_demo(out: Path, device: str = "auto", frames: int = 12, iterations: int = 30, renderer: str = "warp",
             size: int = 96) -> dict:
    """Run the demo; returns the summary written to ``out/summary.json``."""
    import imageio.v3 as iio
    import numpy as np
    import torch
    import trimesh
    from rich.progress import Progress

    from renderers import Gaussians, get_renderer
    from toolkit.cameras import Cameras
    from toolkit.mpm import MPMSimulator, SimConfig

    device = _device(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    cfg = SimConfig(dx=0.02, substeps=60, boundary="sticky")
    torus = trimesh.creation.torus(major_radius=0.07, minor_radius=0.03, major_sections=48, minor_sections=24)
    torus.apply_transform(trimesh.transformations.rotation_matrix(math.radians(60), [1, 0, 0]))
    pts = torus.voxelized(cfg.dx / 2).fill().points
    pts = pts - pts.mean(0) + np.array([0.0, 0.18, 0.0])
    x0 = torch.tensor(pts, dtype=torch.float32)
    truth = {"E": 4e4, "nu": 0.3}
    v0_true = torch.tensor([0.6, -0.4, 0.2])
    sim = MPMSimulator("neo_hookean", cfg, device=device)
    with torch.no_grad():
        target = sim.simulate(x0, v0_true, sim.material.pack(truth), n_frames=frames).positions

    # fit log10 E (0.8 decades off at the start) and v0 (zero at the start) to the simulated
    # positions, progressively as ProJo4D does: v0 alone on the first frames (before contact, where
    # E does not matter), then E and v0 together on all frames
    nu = torch.tensor(truth["nu"], device=target.device)
    log_e = torch.tensor(math.log10(truth["E"]) - 0.8, device=target.device, requires_grad=True)
    v0 = torch.zeros(3, device=target.device, requires_grad=True)
    opt_v = torch.optim.Adam([v0], lr=0.1)
    opt_e = torch.optim.Adam([log_e], lr=0.1)
    early = min(3, frames)
    stage1 = iterations // 3
    history = []
    with Progress() as progress:
        task = progress.add_task("fitting v0 (first frames), then E and v0 (all frames)", total=iterations)
        for it in range(iterations):
            joint = it >= stage1
            n = frames if joint else early
            opt_v.zero_grad()
            opt_e.zero_grad()
            pred = sim.simulate(x0, v0, torch.stack([10.0**log_e, nu]), n_frames=n).positions
            loss = ((pred - target[: n + 1]) ** 2).sum(-1).mean()
            loss.backward()
            opt_v.step()
            if joint:
                opt_e.step()
            history.append({"iteration": it, "stage": 2 if joint else 1, "frames": n, "loss": loss.item(),
                            "E": float(10.0 ** log_e.detach()), "v0": v0.detach().cpu().tolist()})
            progress.advance(task)

    # render the truth from three cameras as small Gaussians coloured by height
    cams = Cameras.cat([
        Cameras.look_at(eye=(0.6 * math.cos(a), 0.35, 0.6 * math.sin(a)), target=(0.05, 0.08, 0.0), fov_y_deg=40,
                        width=size, height=size)
        for a in np.radians([0, 120, 240])
    ]).to(target.device)
    rend = get_renderer(renderer)
    n = x0.shape[0]
    height = (x0[:, 1] - x0[:, 1].min()) / (x0[:, 1].max() - x0[:, 1].min() + 1e-9)
    colors = torch.stack([0.9 - 0.6 * height, 0.3 + 0.5 * height, 0.2 + 0.7 * height], -1).to(target.device)
    frames_rgb = []
    for f in range(frames + 1):
        g = Gaussians(means=target[f], log_scales=torch.full((n, 3), math.log(cfg.dx * 0.35), device=target.device),
                      quats=torch.tensor([[1.0, 0, 0, 0]], device=target.device).expand(n, 4).contiguous(),
                      opacity_logits=torch.full((n,), 2.0, device=target.device), colors=colors)
        with torch.no_grad():
            img = rend(g, cams).rgb.clamp(0, 1)
        frames_rgb.append((torch.cat(list(img), dim=1).cpu().numpy() * 255).astype(np.uint8))
    strip = np.concatenate(frames_rgb[:: max(1, frames // 4)], axis=0)
    iio.imwrite(out / "strip.png", strip)
    try:
        iio.imwrite(out / "simulation.mp4", np.stack(frames_rgb), fps=8, codec="libx264", macro_block_size=1)
    except Exception:  # no ffmpeg: the strip and GIF still show it
        iio.imwrite(out / "simulation.gif", np.stack(frames_rgb), duration=125, loop=0)
    summary = {
        "device": device,
        "particles": n,
        "frames": frames,
        "true": {"E": truth["E"], "v0": v0_true.tolist()},
        "recovered": {"E": history[-1]["E"], "v0": history[-1]["v0"]},
        "log10_E_error": abs(math.log10(history[-1]["E"]) - math.log10(truth["E"])),
        "v0_mae": float((torch.tensor(history[-1]["v0"]) - v0_true).abs().mean()),
        "final_loss": history[-1]["loss"],
        "seconds": round(time.perf_counter() - t_start, 1),
    }
    (out / "history.json").write_text(json.dumps(history, indent=1))
    summary["outputs"] = sorted(p.name for p in out.iterdir()) + ["summary.json"]
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary

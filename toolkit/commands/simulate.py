"""``projo4d simulate TWIN``: re-simulate a digital twin under new conditions and render a video.

``TWIN`` is a ``twin.npz`` from ``projo4d export`` (or the folder holding it). Change the initial
velocity (``--v0``, m/s, canonical world: y up), material parameters (``--params '{"E": 2e5}'``,
physical units), effect parameters (``--effects '{"air_drag": {"k": 0.5}}'``), gravity or the
number of frames; render from the dataset's cameras (``--cameras 0,3``) or an orbit
(``--orbit 8``). Writes ``OUT/particles.npz`` (positions (T, N, 3), means (T, G, 3), times) and
``OUT/video.mp4`` (cameras side by side, at the render resolution, captions below the picture).

Examples::

    projo4d simulate runs/torus/export/twin.npz --v0 -0.5,0,1.2 --frames 40
    projo4d simulate runs/torus/export --params '{"E": 3e5}' --orbit 4 --device cuda
"""

from __future__ import annotations

import argparse
from pathlib import Path

from toolkit.commands.arguments import json_arg

__all__ = ["configure", "run"]


def _vec3(text: str) -> list[float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three numbers like 1.0,0,-0.5, got {text!r}") from None
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers like 1.0,0,-0.5, got {text!r}")
    return v


def _indices(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 0-based camera indices like 0,3, got {text!r}") from None


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("twin", metavar="TWIN", type=Path, help="twin.npz (projo4d export) or its folder")
    parser.add_argument("--out", type=Path, help="output folder (default: TWIN's folder/simulate)")
    parser.add_argument("--v0", type=_vec3, help="initial velocity vx,vy,vz in m/s (default: the fitted one)")
    parser.add_argument("--params", type=json_arg, help='material parameters to change, JSON, e.g. \'{"E": 2e5}\'')
    parser.add_argument("--effects", type=json_arg, help="effect parameters to change, JSON {effect: {param: value}}")
    parser.add_argument("--gravity", type=_vec3, help="gravity gx,gy,gz in m/s^2 (default: the twin's)")
    parser.add_argument("--frames", type=int, help="frames after the initial one (default: the fitted video's)")
    views = parser.add_mutually_exclusive_group()
    views.add_argument("--cameras", type=_indices, help="render these dataset cameras (0-based; default: the fitted ones)")
    views.add_argument("--orbit", type=int, metavar="N", help="render N cameras on an orbit around the object")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="orbit image size in px (default: the dataset's)")
    parser.add_argument("--no-video", action="store_true", help="only simulate (write particles.npz)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from toolkit.atomic import write_with
    from toolkit.twin import DigitalTwin, dataset_cameras, orbit_cameras, render_trajectory, simulate_twin, write_video

    twin = DigitalTwin.load(args.twin)
    if args.frames is not None and args.frames < 0:
        raise SystemExit(f"projo4d simulate: --frames must be >= 0, got {args.frames}")
    out = args.out or (args.twin if args.twin.is_dir() else args.twin.parent) / "simulate"
    traj = simulate_twin(twin, v0=args.v0, params=args.params, effects=args.effects, gravity=args.gravity,
                         n_frames=args.frames, device=args.device)
    out.mkdir(parents=True, exist_ok=True)
    write_with(out / "particles.npz", lambda p: np.savez_compressed(
        p, positions=traj.positions.numpy(), means=traj.means.numpy(), times=traj.times))
    c = traj.conditions
    print(f"simulated {c['n_frames']} frames ({traj.substeps} substeps each): v0 {np.round(c['v0'], 4).tolist()} m/s, "
          + ", ".join(f"{k} = {v:.4g}" for k, v in c["params"].items()))
    print(f"particles: {out / 'particles.npz'}")
    if args.no_video:
        return 0
    if args.orbit:
        w, h = args.size or (None, None)
        cams = orbit_cameras(twin, n=args.orbit, width=w, height=h)
    else:
        cams = dataset_cameras(twin, args.cameras if args.cameras is not None else twin.meta["cameras"]["train"])
    frames = render_trajectory(twin, traj, cams, device=args.device)  # (T, C, H, W, 3)
    tiled = np.concatenate(list(frames.transpose(1, 0, 2, 3, 4)), axis=2)  # cameras side by side
    caps = [f"t = {t:.3f} s  frame {i}/{len(traj.times) - 1}" for i, t in enumerate(traj.times)]
    video = write_video(out / "video.mp4", tiled, fps=1.0 / twin.frame_dt, captions=caps)
    print(f"video:     {video}  ({tiled.shape[2]}x{tiled.shape[1]} px, {len(cams)} camera(s))")
    return 0

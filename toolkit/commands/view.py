"""``projo4d view RUN_DIR``: predicted and ground-truth particles over time.

With a display, an open3d window plays the sequence (space: pause/play, N/P: step, G: toggle
the ground truth). Without one (or with ``--offscreen``), every frame is rendered to
``RUN_DIR/view/`` (or ``--out``): ``frame_XXX.png`` for a few frames, ``strip.png`` and
``particles.mp4``, with open3d's offscreen renderer where it works and a matplotlib scatter
render otherwise (``--backend`` picks one).

Examples::

    projo4d view runs/torus
    projo4d view runs/torus --offscreen --frames 0 7 9 --backend matplotlib
    projo4d view bench/s0/runs/sand/000/cams3/progressive --offscreen --export-ply
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["configure", "run"]


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 960x480, got {text!r}") from None
    if w < 32 or h < 32:
        raise argparse.ArgumentTypeError(f"image size must be at least 32x32, got {text!r}")
    return w, h


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="a run folder (projo4d run / benchmark)")
    parser.add_argument("--offscreen", action="store_true", help="write PNG/MP4 files even where a display exists")
    parser.add_argument("--out", type=Path, help="folder of the files (default RUN_DIR/view)")
    parser.add_argument("--frames", nargs="+", type=int, help="frames saved as PNG (default: first, last fitted, last)")
    parser.add_argument("--format", nargs="+", choices=["png", "mp4"], default=["png", "mp4"], dest="formats")
    parser.add_argument("--backend", choices=["auto", "open3d", "matplotlib"], default="auto",
                        help="offscreen renderer (auto: open3d where it works, else matplotlib)")
    parser.add_argument("--size", type=_size, default=(960, 480), help="image size WIDTHxHEIGHT (default 960x480)")
    parser.add_argument("--fps", type=float, default=6.0)
    parser.add_argument("--max-points", type=int, default=20000, help="points drawn per cloud (default 20000)")
    parser.add_argument("--elev", type=float, default=20.0, help="view elevation, degrees")
    parser.add_argument("--azim", type=float, default=-60.0, help="view azimuth, degrees")
    parser.add_argument("--export-ply", action="store_true", help="also write predicted_XXX.ply (coloured by error)")
    parser.add_argument("--device", default="cpu", help="device of the simulation when no prediction is stored")


def run(args: argparse.Namespace) -> int:
    from toolkit.viewer import display_available, show, write_views

    if not args.run_dir.is_dir():
        raise SystemExit(f"projo4d view: {args.run_dir} is not a folder")
    if not args.offscreen and display_available():
        try:
            show(args.run_dir, fps=args.fps, max_points=args.max_points, device=args.device)
            return 0
        except Exception as err:  # noqa: BLE001 - no usable window: write files instead
            print(f"projo4d view: no interactive window ({err}); writing files instead")
    files = write_views(args.run_dir, args.out, frames=args.frames, formats=args.formats, backend=args.backend,
                        size=args.size, fps=args.fps, max_points=args.max_points, export_ply=args.export_ply,
                        elev=args.elev, azim=args.azim, device=args.device)
    import json

    backend = json.loads(((args.out or args.run_dir / "view") / "view.json").read_text())["backend"]
    print(f"rendered with {backend}:")
    for f in files:
        print(f"  {f}")
    return 0

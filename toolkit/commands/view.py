"""``projo4d view RUN_DIR``: predicted and ground-truth particles over time.

By default every frame is rendered to ``RUN_DIR/view/`` (or ``--out``): ``frame_XXX.png`` for a
few frames, ``strip.png`` and ``particles.mp4`` (matplotlib: truth blue, prediction coloured by its
distance to the truth with a colour bar in cm, axes in metres, y up, captions above the plots).
``--browser`` serves the interactive viewer instead (viser; the ``viewer`` extra): open the printed
address for a time slider, prediction against truth, the cameras and a re-simulation playground.

Examples::

    projo4d view runs/torus --browser            # then open http://127.0.0.1:8080
    projo4d view runs/torus --browser --host 0.0.0.0 --port 8899
    projo4d view runs/torus --frames 0 7 9
    projo4d view bench/s0/runs/sand/000/cams3/progressive --export-ply
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
    parser.add_argument("--browser", action="store_true", help="serve the interactive browser viewer (until Ctrl-C)")
    parser.add_argument("--host", default="127.0.0.1", help="--browser: address to listen on (0.0.0.0: every interface)")
    parser.add_argument("--port", type=int, default=8080, help="--browser: port (default 8080)")
    parser.add_argument("--offscreen", action="store_true", help="write PNG/MP4 files (the default; kept for old scripts)")
    parser.add_argument("--out", type=Path, help="folder of the files (default RUN_DIR/view)")
    parser.add_argument("--frames", nargs="+", type=int, help="frames saved as PNG (default: first, last fitted, last)")
    parser.add_argument("--format", nargs="+", choices=["png", "mp4"], default=["png", "mp4"], dest="formats")
    parser.add_argument("--backend", choices=["auto", "open3d", "matplotlib"], default="auto",
                        help="file renderer (auto = matplotlib; open3d needs the optional open3d extra and EGL)")
    parser.add_argument("--size", type=_size, default=(960, 480), help="image size WIDTHxHEIGHT (default 960x480)")
    parser.add_argument("--fps", type=float, default=6.0)
    parser.add_argument("--max-points", type=int, default=20000, help="points drawn per cloud (default 20000)")
    parser.add_argument("--elev", type=float, default=20.0, help="view elevation, degrees")
    parser.add_argument("--azim", type=float, default=-60.0, help="view azimuth, degrees")
    parser.add_argument("--export-ply", action="store_true", help="also write predicted_XXX.ply (coloured by error)")
    parser.add_argument("--device", default="cpu", help="device of the simulation when no prediction is stored")


def run(args: argparse.Namespace) -> int:
    from toolkit.viewer import show, write_views

    if not args.run_dir.is_dir():
        raise SystemExit(f"projo4d view: {args.run_dir} is not a folder")
    if args.browser:
        show(args.run_dir, host=args.host, port=args.port, max_points=args.max_points, device=args.device)
        return 0
    files = write_views(args.run_dir, args.out, frames=args.frames, formats=args.formats, backend=args.backend,
                        size=args.size, fps=args.fps, max_points=args.max_points, export_ply=args.export_ply,
                        elev=args.elev, azim=args.azim, device=args.device)
    import json

    backend = json.loads(((args.out or args.run_dir / "view") / "view.json").read_text())["backend"]
    print(f"rendered with {backend}:")
    for f in files:
        print(f"  {f}")
    return 0

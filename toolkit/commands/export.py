"""``projo4d export RUN_DIR``: the fitted run as a digital twin and as files other tools read.

Writes to ``RUN_DIR/export/`` (or ``--out``): ``gaussians.ply`` (the physics-refined Gaussians, 3DGS
PLY in the INRIA layout), ``sequence/particles_XXX.ply`` and ``sequence/gaussians_XXX.ply`` per frame,
``twin.npz`` (the twin: material, parameters, effects, particles, Gaussian embedding, simulator
settings, world frame, units; see :mod:`toolkit.twin.format`), ``twin.json`` and ``twin.schema.json``.

Examples::

    projo4d export runs/torus
    projo4d export runs/torus --out twins/torus --no-sequence
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="a fitted run folder (projo4d run / benchmark)")
    parser.add_argument("--out", type=Path, help="output folder (default RUN_DIR/export)")
    parser.add_argument("--no-sequence", action="store_true", help="skip the per-frame PLY sequence")
    parser.add_argument("--device", default="cpu", help="device used when the run has no stored prediction")


def run(args: argparse.Namespace) -> int:
    from toolkit.twin.export import export_run
    from toolkit.twin.format import DigitalTwin

    if not args.run_dir.is_dir():
        raise SystemExit(f"projo4d export: {args.run_dir} is not a folder")
    if not (args.run_dir / "physics" / "checkpoints" / "last.ckpt").is_file():
        raise SystemExit(f"projo4d export: {args.run_dir} holds no fitted model (physics/checkpoints/last.ckpt); "
                         "run `projo4d run` first")
    files = export_run(args.run_dir, args.out, sequence=not args.no_sequence, device=args.device)
    print(DigitalTwin.load(files["twin"]).summary())
    print(f"twin:      {files['twin']}")
    print(f"gaussians: {files['gaussians']}  (3DGS PLY)")
    if "sequence" in files:
        print(f"sequence:  {files['sequence']}/  ({files['sequence_files']} PLY files)")
    return 0

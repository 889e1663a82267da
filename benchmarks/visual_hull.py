"""How much of a body's shape the cameras' silhouettes determine: the exact visual hull of a scene's masks.

A voxel (edge ``--voxel``, metres) is inside the hull when its centre projects inside the mask
(``> 0.5``) of every camera given. No stage-0 model and no threshold of the continuum is involved,
so the hull is the largest body the silhouettes alone allow: what stage 0 cannot carve from masks,
whatever it is trained with. One JSON line: the hull of the fitting cameras (``--cameras``, default
the scene's sparse views from its ground truth), the hull of all the scene's cameras, the true
body's extent (its ``gt_points`` cloud, when the scene has one) and, with ``--continuum``, a
continuum's (``particles.ply``, e.g. a run's ``continuum/particles.ply``, and its volume from the
``stats.json`` beside it)::

    python benchmarks/visual_hull.py SCENE --continuum RUN/continuum/particles.ply
    python benchmarks/visual_hull.py SCENE --frame 5 --cameras 0 3 6
    python benchmarks/visual_hull.py SCENE --cameras 1 5 9 --rank-cameras 0 6   # which camera to add

Volumes in litres, extents in metres (x, y, z of the scene's frame). Benchmarks are never part of
the test suite.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def hull_of(scene, cameras, frame: int, lo, hi, voxel: float) -> dict:
    """Volume (L), extent and height range of the voxels inside every camera's mask at ``frame``."""
    import numpy as np
    import torch

    from toolkit.scene.silhouette_agreement import inside_masks

    axes = [np.arange(lo[i], hi[i], voxel) for i in range(3)]
    centres = torch.tensor(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3), dtype=torch.float32)
    masks = {cam: torch.as_tensor(scene.load_mask(cam, frame) > 0.5) for cam in cameras}
    inside, _ = inside_masks(scene.cameras, list(cameras), masks, centres)
    if not bool(inside.any()):
        return {"volume_L": 0.0}
    pts = centres[inside].numpy()
    touches = bool((pts.min(0) <= lo + voxel).any() or (pts.max(0) >= hi - voxel).any())
    return {"volume_L": round(float(inside.sum()) * voxel ** 3 * 1e3, 4), "extent_m": np.ptp(pts, 0).round(3).tolist(),
            "y_range_m": [round(float(pts[:, 1].min()), 3), round(float(pts[:, 1].max()), 3)],
            **({"reaches_box_edge": True} if touches else {})}


def rank_cameras(scene, cameras, frames, box, voxel: float) -> list[dict]:
    """The scene's other cameras ranked by how much each, added to ``cameras``, carves the hull:
    ``[{"camera", "volume_L" (mean over ``frames``), "per_frame_L"}]``, smallest hull first, with
    ``"without": True`` on an entry for ``cameras`` alone (the reference). ``box(frame)`` gives the
    search box ``(lo, hi)`` of a frame (the body moves). Which camera to add to a fit is a question
    the masks answer without any model."""
    import numpy as np

    def volumes(cams):
        return [hull_of(scene, cams, f, *box(f), voxel)["volume_L"] for f in frames]

    base = volumes(cameras)
    out = [{"camera": None, "without": True, "volume_L": round(float(np.mean(base)), 4), "per_frame_L": base}]
    for cam in range(scene.n_cameras):
        if cam in cameras:
            continue
        v = volumes(list(cameras) + [cam])
        out.append({"camera": cam, "volume_L": round(float(np.mean(v)), 4), "per_frame_L": v})
    return sorted(out, key=lambda r: r["volume_L"])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=pathlib.Path, help="a scene folder (images, masks, cameras)")
    p.add_argument("--frame", type=int, default=0)
    p.add_argument("--cameras", type=int, nargs="*", default=None,
                   help="the fitting cameras (default: the ground truth's sparse_view_indices)")
    p.add_argument("--voxel", type=float, default=0.0025, help="voxel edge (m; default 0.0025)")
    p.add_argument("--margin", type=float, default=0.1, help="search box around the true body or continuum (m)")
    p.add_argument("--continuum", type=pathlib.Path, default=None, help="a continuum's particles.ply to compare")
    p.add_argument("--rank-cameras", type=int, nargs="+", default=None, metavar="FRAME",
                   help="also rank the other cameras by how much each, added to --cameras, carves the hull at these "
                        "frames (mean volume; e.g. 0 6: before and during a slide)")
    args = p.parse_args()

    import numpy as np

    from toolkit.data import load_scene
    from toolkit.verbosity import configure_output

    configure_output(False)  # stdout holds only the JSON lines (no Warp banner or module-load lines)
    from toolkit.data.ply import read_ply_points

    if not args.scene.is_dir():
        p.error(f"{args.scene}: no such scene folder")
    if args.continuum is not None and not args.continuum.is_file():
        p.error(f"--continuum {args.continuum}: no such file (a run's continuum/particles.ply)")
    if args.voxel <= 0:
        p.error(f"--voxel must be positive, got {args.voxel}")
    scene = load_scene(args.scene)
    for f in [args.frame] + list(args.rank_cameras or []):
        scene.check_frame(f)
    gt_file = args.scene / "ground_truth.json"
    gt = json.loads(gt_file.read_text()) if gt_file.is_file() else {}
    cameras = args.cameras if args.cameras is not None else (gt.get("cameras") or {}).get("sparse_view_indices")
    if not cameras:
        p.error("give --cameras: the scene's ground_truth.json names no sparse_view_indices")
    for cam in cameras:
        scene.check_camera(cam)
    truth_file = args.scene / "gt_points" / f"frame_{args.frame:03d}.ply"
    truth = read_ply_points(truth_file) if truth_file.is_file() else None
    body = read_ply_points(args.continuum) if args.continuum is not None else None
    ref = truth if truth is not None else body
    if ref is None:
        p.error("no true body (gt_points) in the scene: give --continuum to place the search box")
    lo, hi = ref.min(0) - args.margin, ref.max(0) + args.margin
    out = {"benchmark": "visual_hull", "scene": str(args.scene), "frame": args.frame, "voxel_m": args.voxel,
           "fitting_cameras": list(cameras), f"hull_of_{len(cameras)}_fitting_cameras": hull_of(scene, cameras, args.frame, lo, hi, args.voxel),
           f"hull_of_all_{scene.n_cameras}_cameras": hull_of(scene, range(scene.n_cameras), args.frame, lo, hi, args.voxel)}
    if truth is not None:
        out["truth_particles"] = {"n": len(truth), "extent_m": np.ptp(truth, 0).round(3).tolist(),
                                  "y_range_m": [round(float(truth[:, 1].min()), 3), round(float(truth[:, 1].max()), 3)]}
        spacing = ((gt.get("simulation") or {}).get("particle_volume"))
        if spacing:
            out["truth_particles"]["volume_L"] = round(len(truth) * float(spacing) * 1e3, 4)
    if args.rank_cameras:
        def box(f):
            pts = args.scene / "gt_points" / f"frame_{f:03d}.ply"
            ref_f = read_ply_points(pts) if pts.is_file() else ref  # without the truth: the body of --frame
            return ref_f.min(0) - args.margin, ref_f.max(0) + args.margin

        out["camera_ranking"] = {"frames": list(args.rank_cameras),
                                 "ranking": rank_cameras(scene, list(cameras), args.rank_cameras, box, args.voxel)}
    if body is not None:
        stats_file = args.continuum.parent / "stats.json"
        vol = json.loads(stats_file.read_text()).get("volume") if stats_file.is_file() else None
        out["continuum"] = {"n": len(body), "extent_m": np.ptp(body, 0).round(3).tolist(),
                            "y_range_m": [round(float(body[:, 1].min()), 3), round(float(body[:, 1].max()), 3)],
                            **({"volume_L": round(float(vol) * 1e3, 4)} if vol else {})}
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()

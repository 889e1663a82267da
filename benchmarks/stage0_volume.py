"""How much volume stage 0's continuum gives a body, against the true body (issue #20).

The continuum (``toolkit.scene.continuum``) fills the stage-0 model with simulation particles,
one per interior voxel of its final lattice. The suite's true body, filled by the generator's
``fill_mesh`` at the same spacing, gives the count it should have. Their ratio is the volume (and
mass, at the config's density) the fit works with, relative to the truth's.

Inputs are stage-0 records as the benchmark write-ups keep them (``FAMILY_INDEX.json`` with
``continuum.frames[0].particles`` and ``spacing``), ``--count FAMILY/INDEX=N`` for a run whose
record was not kept (spacing ``--spacing``), or ``--runs``: run folders of generated suite scenes
with a finished stage 0 (``projo4d stage0 SUITE/FAMILY/INDEX --out RUN``), whose continuum is built
again under each ``--variant`` (``KEY=VALUE`` settings of
:class:`~toolkit.scene.continuum.ContinuumConfig` joined by ``+``, on the pipeline's lattice), or
``--bodies FAMILY/INDEX=PLY``: continua already built (a benchmark scene's
``continuum/particles.ply``). One JSON line per scene (and variant); with ``--runs`` and
``--bodies`` also the body's centroid offset from the true body's and that of its lowest point
(y up, metres)::

    python benchmarks/stage0_volume.py docs/results/paper_size/round8/stage0/*.json
    python benchmarks/stage0_volume.py --shape-set spring_gaus --count neo_hookean/006=4188
    python benchmarks/stage0_volume.py --shape-set spring_gaus --bodies neo_hookean/006=BENCH/scenes/neo_hookean/006/cams3/continuum/particles.ply
    python benchmarks/stage0_volume.py --size small --runs runs/nh000 runs/sand000 \
        --variant centre_stamp=voxel+carve_depth=expected centre_stamp=ellipsoid+carve_depth=opaque

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("records", nargs="*", type=pathlib.Path, help="stage-0 records FAMILY_INDEX.json")
    parser.add_argument("--count", nargs="*", default=[], metavar="FAMILY/INDEX=N",
                        help="a scene's continuum particle count, for scenes without a record")
    parser.add_argument("--spacing", type=float, default=0.01, help="the continuum's spacing for --count (m; default 0.01)")
    parser.add_argument("--shape-set", default="pac_nerf", help="the suite's shape set of every scene given (one set per call)")
    parser.add_argument("--size", default="full", choices=["full", "small"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default=None, help="where --runs rebuild the continua (default: the stage-0 model's)")
    parser.add_argument("--runs", nargs="*", default=[], type=pathlib.Path, help="run folders with a finished stage 0")
    parser.add_argument("--bodies", nargs="*", default=[], metavar="FAMILY/INDEX=PLY",
                        help="continua already built (a run's or a benchmark scene's continuum/particles.ply, lattice "
                             "pitch --spacing): volume and placement against the true body")
    parser.add_argument("--variant", nargs="*", default=["centre_stamp=voxel+carve_depth=expected"],
                        help="continuum settings for --runs, KEY=VALUE joined by +")
    parser.add_argument("--surfaces", action="store_true",
                        help="with --runs: build every training frame and report, per frame, the share of surface points "
                             "below the ground, the lowest point against the truth's and the mean distance (mm) from a "
                             "surface point to the nearest true particle (the geometric loss's targets)")
    args = parser.parse_args()
    if args.bodies:
        for item in args.bodies:
            name, sep, ply = item.partition("=")
            family, _, index = name.partition("/")
            if not (sep and index.isdigit() and pathlib.Path(ply).is_file()):
                parser.error(f"--bodies expects FAMILY/INDEX=PLY with an existing PLY file, got {item!r}")
            with contextlib.redirect_stdout(sys.stderr):  # Warp's messages: stdout keeps the JSON lines
                row = placement(family, int(index), pathlib.Path(ply), args)
            print(json.dumps(row), flush=True)
        return
    if args.runs:
        out = sys.stdout
        with contextlib.redirect_stdout(sys.stderr):  # Warp's and Lightning's messages: stdout keeps the JSON lines
            rebuild(args, out)
        return

    from toolkit.synthetic.filling import fill_mesh
    from toolkit.synthetic.suite import sample_scene_spec
    from toolkit.synthetic.truth import build_object

    scenes: list[tuple[str, int, int, float, str]] = []
    for path in args.records:
        family, index = path.stem.rsplit("_", 1)
        first = json.loads(path.read_text())["continuum"]["frames"][0]
        scenes.append((family, int(index), int(first["particles"]), float(first["spacing"]), str(path)))
    for item in args.count:
        try:
            name, n = item.split("=")
            family, index = name.split("/")
            scenes.append((family, int(index), int(n), args.spacing, "--count"))
        except ValueError:
            parser.error(f"--count expects FAMILY/INDEX=N (e.g. neo_hookean/006=4188), got {item!r}")
    if not scenes:
        parser.error("give stage-0 records, --count, --runs or --bodies")
    for family, index, n_stage0, spacing, source in scenes:
        spec = sample_scene_spec(family, index, args.seed, args.size, "cpu", shape_set=args.shape_set)
        particles, _ = fill_mesh(build_object(spec), spacing, device="cpu")
        print(json.dumps({"benchmark": "stage0_volume", "scene": f"{family}/{index:03d}", "shape": spec.shape,
                          "spacing_m": spacing, "true_particles": len(particles), "stage0_particles": n_stage0,
                          "volume_ratio": round(n_stage0 / len(particles), 3), "source": source}), flush=True)


def offsets(body, true_pts) -> dict:
    """Where a body (N, 3) sits against the true body's particles (M, 3), metres, y up."""
    return {"centroid_offset_m": [round(float(x), 4) for x in body.mean(0) - true_pts.mean(0)],
            "lowest_point_offset_m": round(float(body[:, 1].min() - true_pts[:, 1].min()), 4)}


def placement(family: str, index: int, ply: pathlib.Path, args: argparse.Namespace) -> dict:
    """Volume ratio, centroid and lowest-point offsets (m, y up) of a continuum PLY against the
    true body of the suite scene ``family/index`` filled at ``args.spacing``."""
    import numpy as np

    from toolkit.data.ply import read_ply_points
    from toolkit.synthetic.filling import fill_mesh
    from toolkit.synthetic.suite import sample_scene_spec
    from toolkit.synthetic.truth import build_object

    spec = sample_scene_spec(family, index, args.seed, args.size, "cpu", shape_set=args.shape_set)
    true_pts = np.asarray(fill_mesh(build_object(spec), args.spacing, device="cpu")[0])
    body = np.asarray(read_ply_points(ply))
    return {"benchmark": "stage0_volume", "scene": f"{family}/{index:03d}", "shape": spec.shape, "spacing_m": args.spacing,
            "true_particles": len(true_pts), "stage0_particles": len(body), "volume_ratio": round(len(body) / len(true_pts), 3),
            **offsets(body, true_pts), "source": str(ply)}


def rebuild(args: argparse.Namespace, out) -> None:
    """The continuum of each run's stage-0 model, built again under each variant."""
    import numpy as np
    import torch

    from toolkit.data import load_scene
    from toolkit.pipeline import RunSettings, fit_stage0_step
    from toolkit.scene.continuum import ContinuumConfig, build_continuum
    from toolkit.synthetic.filling import fill_mesh
    from toolkit.synthetic.suite import sample_scene_spec
    from toolkit.synthetic.truth import build_object

    fields = ContinuumConfig().to_dict()
    for run in args.runs:
        settings = RunSettings(**json.loads((run / "settings.json").read_text()))
        scene_dir = pathlib.Path(settings.scene)
        family, index = scene_dir.parent.name, int(scene_dir.name)
        scene = load_scene(scene_dir)
        module, views = fit_stage0_step(settings, scene, run, {})  # a finished stage 0 is loaded
        coverage_file = run / "stage0" / "coverage.json"
        lost = json.loads(coverage_file.read_text()).get("lost_frames", []) if coverage_file.is_file() else []
        spec = sample_scene_spec(family, index, args.seed, args.size, "cpu", shape_set=args.shape_set)
        dx = float(settings.sim.get("dx", 0.02))
        true_counts: dict = {}
        for variant in args.variant:
            cfg = {"grid_size": 8 * dx / 2, "candidate_level": 3, "final_level": 3}
            for part in variant.split("+"):
                key, _, value = part.partition("=")
                if key not in fields:
                    raise SystemExit(f"--variant: {key!r} is not a continuum setting ({', '.join(fields)})")
                if isinstance(fields[key], bool):
                    if value not in ("true", "false"):
                        raise SystemExit(f"--variant: {key} takes true or false, got {value!r}")
                    cfg[key] = value == "true"
                else:
                    cfg[key] = type(fields[key])(value)
            with torch.no_grad():
                cont = build_continuum(module, views, config=ContinuumConfig.from_dict(cfg), device=args.device,
                                       frames=None if args.surfaces else [0],
                                       ground=(scene.world.ground_point, scene.world.ground_normal), lost_frames=lost)
            if cont.spacing not in true_counts:
                true_counts[cont.spacing] = fill_mesh(build_object(spec), cont.spacing, device="cpu")[0]
            true_pts = true_counts[cont.spacing]
            n_true = len(true_pts)
            body = cont.particles.numpy()
            carve = cont.stats["frames"][0].get("ground_carve")
            print(json.dumps({"benchmark": "stage0_volume", "scene": f"{family}/{index:03d}", "shape": spec.shape,
                              "variant": variant, "spacing_m": cont.spacing, "true_particles": n_true,
                              "stage0_particles": int(cont.particles.shape[0]),
                              "volume_ratio": round(cont.particles.shape[0] / n_true, 3),
                              "carve_ratio": round(cont.stats["frames"][0]["carved"] / n_true, 3),
                              "ground_carved": carve.get("removed") if isinstance(carve, dict) else carve,
                              **offsets(body, np.asarray(true_pts)),
                              **(surface_quality(cont, scene_dir, scene.world) if args.surfaces else {}),
                              "source": str(run)}),
                  file=out, flush=True)


def surface_quality(cont, scene_dir: pathlib.Path, world) -> dict:
    """Per frame: share of surface points more than half a voxel below the ground, lowest surface
    point minus the true cloud's lowest (m, along the ground normal), and the mean distance (mm)
    from a surface point to the nearest point of the frame's ground-truth cloud."""
    import numpy as np
    from scipy.spatial import cKDTree

    from toolkit.data.ply import read_ply_points

    below, lowest, dist = [], [], []
    for i, surf in enumerate(cont.surfaces):
        truth = np.asarray(read_ply_points(scene_dir / "gt_points" / f"frame_{i:03d}.ply"))
        pts = surf.numpy()
        if len(pts) == 0:
            below.append(None), lowest.append(None), dist.append(None)
            continue
        h, h_true = world.height(pts), world.height(truth)
        below.append(round(float(np.mean(h < -cont.spacing / 2)), 3))
        lowest.append(round(float(h.min() - h_true.min()), 4))
        dist.append(round(float(cKDTree(truth).query(pts, k=1)[0].mean()) * 1e3, 2))
    return {"surface_below_ground": below, "surface_lowest_offset_m": lowest, "surface_to_truth_mm": dist}


if __name__ == "__main__":
    main()

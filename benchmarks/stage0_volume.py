"""How much volume stage 0's continuum gives a body, against the true body (issue #20).

The continuum (``toolkit.scene.continuum``) fills the stage-0 model with simulation particles,
one per interior voxel of its final lattice. The suite's true body, filled by the generator's
``fill_mesh`` at the same spacing, gives the count it should have. Their ratio is the volume (and
mass, at the config's density) the fit works with, relative to the truth's.

Inputs are stage-0 records as the benchmark write-ups keep them (``FAMILY_INDEX.json`` with
``continuum.frames[0].particles`` and ``spacing``), or ``--count FAMILY/INDEX=N`` for a run whose
record was not kept (spacing ``--spacing``). One JSON line per scene::

    python benchmarks/stage0_volume.py docs/results/paper_size/round8/stage0/*.json
    python benchmarks/stage0_volume.py --shape-set spring_gaus --count neo_hookean/006=4188

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
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
    args = parser.parse_args()

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
        parser.error("give stage-0 records or --count")
    for family, index, n_stage0, spacing, source in scenes:
        spec = sample_scene_spec(family, index, args.seed, args.size, "cpu", shape_set=args.shape_set)
        particles, _ = fill_mesh(build_object(spec), spacing, device="cpu")
        print(json.dumps({"benchmark": "stage0_volume", "scene": f"{family}/{index:03d}", "shape": spec.shape,
                          "spacing_m": spacing, "true_particles": len(particles), "stage0_particles": n_stage0,
                          "volume_ratio": round(n_stage0 / len(particles), 3), "source": source}), flush=True)


if __name__ == "__main__":
    main()

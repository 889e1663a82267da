"""How much the fitting grid alone biases a material parameter (issue #20).

The synthetic suite simulates its truth at a finer grid than the fit uses (full size: dx 0.008 m,
particles at 0.004 m, at least 200 substeps, since 2026-11-26; 0.01 m before; the configs fit at
dx 0.02 m). This script takes one suite
scene's body and throw, simulates the truth exactly as the generator does, then simulates the
same body at the fitting resolution (the mesh filled at ``fit_dx / 2``, the config's substep
planning) for a sweep of one parameter around its true value, and scores each rollout against the
truth's particles: the per-frame symmetric Chamfer distance (mean nearest-neighbour distance both
ways, metres), averaged over the frames. No images, no stage 0, no optimizer: if the lowest
score sits away from the truth, the fitting grid alone moves the estimate there. Each row also
gives the body's rebound (the highest centroid after its first low point, metres) and its
horizontal travel, the two things a ground contact changes most: with the ``sticky`` ground both
depend on the grid (``--boundary`` sets the ground of truth and rollouts alike).

One JSON line per swept value, then a summary line with the best value and its offset from the
truth (decades for log parameters)::

    python benchmarks/grid_bias.py --family neo_hookean --index 0 --size full --fit-dx 0.02
    python benchmarks/grid_bias.py --family neo_hookean --index 0 --size full --fit-dx 0.01   # a finer fitting grid
    python benchmarks/grid_bias.py --family neo_hookean --index 0 --truth-dx 0.02 --fit-dx 0.02  # control: the truth's grid
    python benchmarks/grid_bias.py --family neo_hookean --index 0 --boundary separate          # another ground
    python benchmarks/grid_bias.py --family neo_hookean --index 1 --shape-set spring_gaus      # the banana stand-in
    python benchmarks/grid_bias.py --family neo_hookean --index 0 --dilate 0.01                # a body 1 cm too thick
    python benchmarks/grid_bias.py --family neo_hookean --index 0 --body RUN/continuum/particles.ply  # stage 0's body
    python benchmarks/grid_bias.py --family plasticine --index 4 --param nu --base E=3.12e5  # along nu at a fit's E

``--base NAME=VALUE`` holds the other material parameters at those values (a fit's, say) instead
of the truth's in every rollout; the swept parameter's offsets stay relative to its true value,
so two sweeps, with and without ``--base``, say whether a fit's pair of values scores as well
as the truth on the fitting grid (a ridge between the parameters).

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def contact_summary(positions: np.ndarray) -> dict:
    """The body's rebound and travel from particle positions (F, N, 3), y up, metres: the frame of
    the centroid's first low point (the last frame when it has not bounced yet), its highest point
    after that (``rebound_m``), and the horizontal distance the centroid travelled from frame 0 to
    the last frame (``travel_m``)."""
    c = positions.mean(1)
    y = c[:, 1]
    low = next((f for f in range(1, len(y) - 1) if y[f] <= y[f - 1] and y[f] < y[f + 1]), len(y) - 1)
    return {"contact_frame": int(low), "rebound_m": round(float(y[low:].max()), 4),
            "travel_m": round(float(np.hypot(c[-1, 0] - c[0, 0], c[-1, 2] - c[0, 2])), 4)}


def dilated(particles: np.ndarray, body: np.ndarray, spacing: float, distance: float) -> np.ndarray:
    """The body grown by a shell: ``particles`` (the body filled on a lattice of pitch
    ``spacing``) plus the points of that lattice within ``distance`` (m) of ``body`` (the same body
    filled much finer), as stage 0's continuum sets lattice points outside the surface."""
    from scipy.spatial import cKDTree

    k = int(np.ceil(distance / spacing)) + 1
    r = np.arange(-k, k + 1)
    offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    keys = np.round((particles - particles[0]) / spacing).astype(np.int64)
    keys = np.unique((keys[:, None, :] + offs[None]).reshape(-1, 3), axis=0)
    grown = particles[0] + keys * spacing
    near = cKDTree(body).query(grown, distance_upper_bound=distance + 1e-9)[0] <= distance + 1e-9
    old = {tuple(x) for x in np.round((particles - particles[0]) / spacing).astype(np.int64).tolist()}
    new = np.array([g for g, key, n in zip(grown, keys.tolist(), near) if n and tuple(key) not in old]).reshape(-1, 3)
    return np.concatenate([particles, new.astype(particles.dtype)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default="neo_hookean")
    parser.add_argument("--index", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", default="full", choices=["full", "small"])
    parser.add_argument("--shape-set", default="pac_nerf", help="the suite's shape set (pac_nerf, spring_gaus)")
    parser.add_argument("--frames", type=int, default=14, help="frames simulated (default 14, the training frames)")
    parser.add_argument("--fit-dx", type=float, default=0.02, help="the fitting grid spacing, metres (default 0.02)")
    parser.add_argument("--param", default="E", help="the swept parameter (default E)")
    parser.add_argument("--decades", type=float, nargs="+", default=[-1.5, -1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5],
                        help="offsets from the truth: decades for log parameters, multiples of --linear-step for others")
    parser.add_argument("--linear-step", type=float, default=0.1,
                        help="unit of an offset for a parameter that is not log-scaled (e.g. 5 for a friction angle in degrees)")
    parser.add_argument("--truth-dx", type=float, default=None, help="the truth's grid spacing, metres (default: the size preset's)")
    parser.add_argument("--boundary", default=None, choices=["sticky", "slip", "separate"],
                        help="the ground of the truth and of every rollout (default: the scene's)")
    parser.add_argument("--body", type=pathlib.Path, default=None,
                        help="simulate this body instead of the true one: a PLY of particles on a lattice of pitch "
                             "fit_dx / 2 in the scene's frame, e.g. a run's continuum/particles.ply")
    parser.add_argument("--dilate", type=float, default=0.0,
                        help="grow the fitting body by this distance, metres (the lattice points within it of the "
                             "filled body join it, each of the same volume): a stage-0 body that is too large")
    parser.add_argument("--base", nargs="+", default=[], metavar="NAME=VALUE",
                        help="hold these material parameters at these values in every rollout instead of the truth's")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    base: dict[str, float] = {}
    for item in args.base:
        name, sep, value = item.partition("=")
        try:
            base[name] = float(value)
        except ValueError:
            sep = ""
        if not sep or name == args.param:
            parser.error(f"--base: expected NAME=VALUE with NAME a material parameter other than --param "
                         f"({args.param}) and VALUE a number, got {item!r}")
    if args.truth_dx is not None and not args.truth_dx > 0:
        parser.error(f"--truth-dx must be a positive grid spacing in metres, got {args.truth_dx}")
    if not args.fit_dx > 0:
        parser.error(f"--fit-dx must be a positive grid spacing in metres, got {args.fit_dx}")
    if args.frames < 2:
        parser.error(f"--frames must be >= 2 (the first frame is the start), got {args.frames}")
    if args.body is not None and not args.body.is_file():
        parser.error(f"--body: {args.body} is not a file (expected a PLY of particles, e.g. RUN/continuum/particles.ply)")
    if not args.dilate >= 0:
        parser.error(f"--dilate must be a distance >= 0 in metres, got {args.dilate}")
    if not args.linear_step > 0:
        parser.error(f"--linear-step must be > 0, got {args.linear_step}")

    import torch

    from materials import MaterialError, get_material
    from toolkit.metrics import mean_nearest_distance
    from toolkit.mpm import MPMSimulator, SimConfig
    from toolkit.synthetic.filling import fill_mesh
    from toolkit.synthetic.suite import sample_scene_spec
    from toolkit.synthetic.truth import GROUND_HEIGHT, build_object, simulate_truth

    overrides = {"n_frames": args.frames, **({"dx": args.truth_dx} if args.truth_dx else {}),
                 **({"boundary": args.boundary} if args.boundary else {})}
    spec = sample_scene_spec(args.family, args.index, args.seed, args.size, args.device,
                             shape_set=args.shape_set, **overrides)
    material = get_material(spec.material, **spec.material_options)
    try:
        p = material.param(args.param)
        for name in base:
            material.param(name)
    except MaterialError as err:
        parser.error(f"--param/--base: {err}")
    mesh = build_object(spec)
    t = time.perf_counter()
    truth = simulate_truth(spec, mesh)
    print(json.dumps({"benchmark": "grid_bias", "event": "truth", "shape": spec.shape, "params": spec.params, "v0": list(spec.v0),
                      "dx": spec.dx, "boundary": spec.boundary, "particles": int(truth.particles.shape[1]),
                      "substeps": truth.substeps, **contact_summary(truth.particles), "seconds": round(time.perf_counter() - t, 1)}),
          flush=True)
    particles, volume = fill_mesh(mesh, args.fit_dx / 2, device=args.device)
    n_true = len(particles)
    if args.body is not None:
        from toolkit.data.ply import read_ply_points

        true_centroid = np.asarray(particles).mean(0)
        particles = np.asarray(read_ply_points(args.body), dtype=np.float32)
        print(json.dumps({"benchmark": "grid_bias", "event": "body", "path": str(args.body),
                          "volume_ratio": round(len(particles) / n_true, 3),
                          "centroid_offset_m": [round(float(x), 4) for x in particles.mean(0) - true_centroid]}), flush=True)
    if args.dilate > 0:
        body = np.asarray(fill_mesh(mesh, args.fit_dx / 8, device=args.device)[0])
        particles = dilated(np.asarray(particles), body, args.fit_dx / 2, args.dilate)
        print(json.dumps({"benchmark": "grid_bias", "event": "dilated", "dilate_m": args.dilate,
                          "volume_ratio": round(len(particles) / n_true, 3)}), flush=True)
    config = SimConfig(dx=args.fit_dx, frame_dt=1.0 / spec.fps, density=spec.density, particle_volume=volume,
                       gravity=tuple(spec.gravity), ground_height=GROUND_HEIGHT, boundary=spec.boundary,
                       auto_dt_halving=True)
    log_axis = p.transform == "log10"
    true_value = float(spec.params[args.param])
    rows = []
    for k in args.decades:
        value = true_value * 10.0**k if log_axis else true_value + args.linear_step * k
        params = material.complete({**spec.params, **base, args.param: value})
        sim = MPMSimulator(material, dataclasses.replace(config), device=args.device)
        t = time.perf_counter()
        out = sim.rollout(torch.as_tensor(particles, dtype=torch.float32), v0=np.asarray(spec.v0, np.float32),
                          params=material.pack(params), n_frames=args.frames - 1)
        pos = out.positions.cpu().numpy()
        per_frame = [mean_nearest_distance(pos[f], truth.particles[f]) for f in range(args.frames)]
        row = {"benchmark": "grid_bias", "param": args.param, "offset": k, "value": value, "base": base, "fit_dx": args.fit_dx,
               "particles": len(particles), "substeps": int(out.substeps), "cd_mean_m": float(np.mean(per_frame)),
               "cd_per_frame_mm": [round(1e3 * c, 3) for c in per_frame], **contact_summary(pos),
               "seconds": round(time.perf_counter() - t, 1)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    best = min(rows, key=lambda r: r["cd_mean_m"])
    print(json.dumps({"benchmark": "grid_bias", "event": "summary", "param": args.param, "truth": true_value, "fit_dx": args.fit_dx,
                      "truth_dx": spec.dx, "boundary": spec.boundary, "best_value": best["value"], "best_offset": best["offset"],
                      "offset_unit": "decades" if log_axis else f"x{args.linear_step:g}", "cd_at_truth_m": next(
                          (r["cd_mean_m"] for r in rows if r["offset"] == 0.0), math.nan), "cd_best_m": best["cd_mean_m"]}),
          flush=True)


if __name__ == "__main__":
    main()

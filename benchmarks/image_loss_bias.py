"""Where the fit's image loss puts a material parameter, against where the particles put it (issue #20).

Takes one scene of the synthetic suite (generated into ``--suite`` unless it is there already),
builds the physics input from the true body (``oracle_input``, its Gaussians at
``--gaussian-scale`` times the particle spacing) or loads a run folder's stage-0 input
(``--input RUN/physics_input.pt``), puts v0 and every material parameter at the truth, then sweeps
one parameter and scores each rollout over the training frames 1..n_train-1 and the fitting
cameras by:

* ``image`` and ``geometry``: the fit's own loss terms (its image term, ``(1 - ssim_weight) L1 +
  ssim_weight (1 - SSIM)``, and its geometric term against the input's surfaces), as the coarse
  search scores a candidate;
* ``l1`` and ``dssim``: the image term with its SSIM weight at 0 and at 1;
* ``chamfer_mm``: the particles' mean nearest-neighbour distance to the truth's clouds, both ways.

No optimizer and no coarse search: if the image terms' minimum sits away from the truth while the
particles' does not, the images pull a fit there. The simulation uses ``--fit-dx`` (default: the
truth's own grid, so the grid adds no bias of its own).

One JSON line per value, then a summary line with each score's best offset::

    python benchmarks/image_loss_bias.py --family neo_hookean --index 1                      # the small banana
    python benchmarks/image_loss_bias.py --family neo_hookean --index 1 --gaussian-scale 0.15
    python benchmarks/image_loss_bias.py --family neo_hookean --index 1 --input RUN/physics_input.pt  # stage 0's body

Runs on the CPU (a few seconds a value at the small size). Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

DEFAULT_OFFSETS = [-1.0, -0.75, -0.5, -0.25, -0.125, 0.0, 0.125, 0.25, 0.5]


def scores(module, positions, cams: list[int], frames: list[int], clouds: list[np.ndarray]) -> dict:
    """The scores of one rollout ``positions`` (T+1, N, 3): the fit's own loss terms
    (:meth:`~toolkit.physics.InversePhysicsModule.probe_losses` of its material stage: ``image``,
    ``geometry``), the image term again with its SSIM weight at 0 (``l1``) and 1 (``dssim``), and
    the particles' Chamfer distance to the truth's clouds (``chamfer_mm``)."""
    from toolkit.metrics import mean_nearest_distance

    stage = next(s for s in module.stages if "M" in s.groups)
    out = module.probe_losses(positions, stage, cams, frames)
    weight = module.ssim_weight
    try:
        for key, w in (("l1", 0.0), ("dssim", 1.0)):
            module.ssim_weight = w
            out[key] = module.probe_losses(positions, stage, cams, frames)["image"]
    finally:
        module.ssim_weight = weight
    pos = positions.cpu().numpy()
    chamfer = float(np.mean([mean_nearest_distance(pos[f], clouds[f]) for f in frames]))
    return {"l1": out["l1"], "dssim": out["dssim"], "image": out["image"], "geometry": out.get("geometry", 0.0),
            "chamfer_mm": 1e3 * chamfer}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default="neo_hookean")
    parser.add_argument("--index", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", default="small", choices=["small", "full"])
    parser.add_argument("--suite", type=pathlib.Path, default=pathlib.Path("runs/image_loss_bias_suite"),
                        help="where the scene is generated (reused when there)")
    parser.add_argument("--param", default="E")
    parser.add_argument("--offsets", type=float, nargs="+", default=None,
                        help="decades for log10 parameters, physical steps for the others (default: -1 .. +0.5 decades, "
                             "or -0.2 .. +0.1)")
    parser.add_argument("--fit-dx", type=float, default=None, help="grid spacing of the rollouts, m (default: the truth's)")
    parser.add_argument("--gaussian-scale", type=float, default=0.6,
                        help="the true body's Gaussians' standard deviation over the particle spacing (default 0.6, oracle_input's)")
    parser.add_argument("--input", type=pathlib.Path, default=None, help="a run's physics_input.pt (stage 0's body) instead of the true body")
    args = parser.parse_args()
    if args.input is not None and not args.input.is_file():
        parser.error(f"--input: {args.input} is not a file (expected RUN/physics_input.pt)")
    if args.index < 0:
        parser.error(f"--index must be >= 0 (the scene's index in its family), got {args.index}")
    if not args.gaussian_scale > 0:
        parser.error(f"--gaussian-scale must be > 0, got {args.gaussian_scale}")
    if args.fit_dx is not None and not args.fit_dx > 0:
        parser.error(f"--fit-dx must be a positive grid spacing in metres, got {args.fit_dx}")

    import torch

    from materials import MaterialError, get_material
    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.inputs import PhysicsInput
    from toolkit.physics.oracle import oracle_input
    from toolkit.synthetic.errors import SpecError
    from toolkit.synthetic.suite import generate_suite, sample_scene_spec

    name = f"{args.family}/{args.index:03d}"
    try:
        spec = sample_scene_spec(args.family, args.index, args.seed, args.size, "cpu")
    except SpecError as err:
        parser.error(f"--family: {err}")
    try:  # before any generation or simulation
        p = get_material(spec.material, **spec.material_options).param(args.param)
    except MaterialError as err:
        parser.error(f"--param: {err}")
    fit_dx = args.fit_dx or spec.dx
    scene = args.suite / name
    if not (scene / "ground_truth.json").is_file():
        generate_suite(args.suite, families=[args.family], scenes_per_family=args.index + 1, seed=args.seed, size=args.size,
                       device="cpu", only=[name], progress=False)
    truth_input = oracle_input(scene, particle_spacing=fit_dx / 2, dx=fit_dx, gaussian_scale=args.gaussian_scale)
    clouds = [np.asarray(c) for c in truth_input.surfaces]
    inp = truth_input
    if args.input is not None:
        inp = PhysicsInput.load(args.input)
        inp.ground_truth = truth_input.ground_truth
    gt = truth_input.ground_truth
    module = InversePhysicsModule(inp, material=gt["material"], initial_params=dict(gt["params"]), v0_init=list(gt["v0"]),
                                  sim=SimConfig(dx=fit_dx, boundary=spec.boundary, auto_dt_halving=True))
    log_axis = p.transform == "log10"
    offsets = args.offsets or (DEFAULT_OFFSETS if log_axis else [-0.2, -0.1, -0.05, 0.0, 0.05, 0.1])
    index = module.material.param_names.index(args.param)
    base = module.material_params().detach().clone()
    cams, frames = list(inp.train_cameras), list(range(1, inp.n_train))
    x0 = (module.particles0 + module.particle_offset).detach()
    print(json.dumps({"benchmark": "image_loss_bias", "event": "settings", "scene": name, "size": args.size,
                      "body": str(args.input) if args.input else "truth", "gaussian_scale": None if args.input else args.gaussian_scale,
                      "fit_dx": fit_dx, "truth_dx": spec.dx, "param": args.param, "truth": float(base[index]),
                      "particles": int(x0.shape[0]), "gaussians": int(module.gaussian_means0.shape[0]),
                      "frames": frames, "cameras": cams}), flush=True)
    rows = []
    for k in offsets:
        params = base.clone()
        params[index] = base[index] * 10.0 ** k if log_axis else base[index] + k
        t = time.perf_counter()
        with torch.no_grad():
            out = module.simulator.rollout(x0, module.v0.detach(), params, gravity=module.gravity.detach(),
                                           effect_params=module.effect_params.detach(), n_frames=max(frames))
        row = {"benchmark": "image_loss_bias", "offset": k, "value": float(params[index]),
               **{key: round(v, 6) for key, v in scores(module, out.positions, cams, frames, clouds).items()},
               "seconds": round(time.perf_counter() - t, 1)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    keys = ("l1", "dssim", "image", "geometry", "chamfer_mm")
    best = {key: min(rows, key=lambda r: r[key])["offset"] for key in keys}
    spread = {key: round(max(r[key] for r in rows) / max(min(r[key] for r in rows), 1e-12) - 1, 4) for key in keys}
    print(json.dumps({"benchmark": "image_loss_bias", "event": "summary", "scene": name, "param": args.param,
                      "body": "stage0" if args.input else "truth", "gaussian_scale": None if args.input else args.gaussian_scale,
                      "best_offset": best, "relative_spread": spread,
                      "offset_unit": "decades" if log_axis else "physical"}), flush=True)


if __name__ == "__main__":
    main()

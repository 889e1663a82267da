"""The fit's own loss along one material parameter, for a finished run, at the true state.

Loads a run folder's fitted module (its appearance, positions and embedding as fitted), puts the
initial velocity and every material parameter at the scene's ground truth, then varies one
parameter and prints the image and geometric terms over the training frames (every training
camera), total and per frame. Shows which frames and which term pull an estimate away from the
truth (docs/results/five_families_small.md, "every family is fitted too soft").

``--gaussian-shape rigid|deformed`` sweeps with the Gaussians' shapes kept or deformed with the
material (``A Sigma A^T``, :meth:`toolkit.physics.InversePhysicsModule.set_gaussian_shape`)
instead of as the run was fitted; ``--deform-covariances`` is ``--gaussian-shape deformed``.

Each value's row also gives ``chamfer_mm_per_frame``: the symmetric mean nearest-neighbour
distance (mm, :func:`toolkit.metrics.geometry.mean_nearest_distance`) of the simulated particles to
the run's geometric targets of that frame. With ``--geometry oracle`` those targets are the truth's
particles, so the row puts the image loss and the particles' distance to the truth side by side on
the same rollout (where the two prefer different values, the images pull the estimate somewhere the
motion does not).

Output: one JSON line of settings; two reference lines, ``{"point": "fit" | "truth", "params",
"v0", ...scores}``: every parameter and v0 as fitted, then all at the truth (so a sweep says
whether the fit's own loss ranks the fit's point below the truth's: a biased loss, or above it:
the optimizer stopped short); then one line per value: ``{param: value, "geometry", "image",
"image_per_frame", "chamfer_mm", "chamfer_mm_per_frame"}`` (frames 1 .. n_train-1).

Usage::

    projo4d run SCENE --geometry oracle --out RUN ...                      # a fitted run of a generated scene
    python benchmarks/fitted_landscape.py RUN mu 0.01 0.05 0.3 1 3.5 10
    python benchmarks/fitted_landscape.py RUN mu 0.05 0.5 3.5 10 --gaussian-shape rigid
    python benchmarks/fitted_landscape.py RUN E 3e3 1e4 3e4 1e5 3e5 --device cuda
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a finished run folder (physics/checkpoints/last.ckpt) of a scene with ground truth")
    ap.add_argument("param", help="material parameter to vary (the others stay at the truth)")
    ap.add_argument("values", type=float, nargs="+", help="physical values of the parameter")
    ap.add_argument("--gaussian-shape", choices=["rigid", "deformed"],
                    help="Gaussians' shapes during the sweep (default: as the run was fitted)")
    ap.add_argument("--deform-covariances", action="store_const", const="deformed", dest="gaussian_shape",
                    help="the same as --gaussian-shape deformed")
    ap.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N (default cpu)")
    args = ap.parse_args(argv)
    from toolkit.run_validation import parse_device_option

    args.device = parse_device_option(ap, args.device)

    import torch

    from toolkit.verbosity import configure_output

    configure_output(False)  # stdout holds only the JSON lines (no Warp banner or module-load lines)

    from toolkit.metrics.geometry import mean_nearest_distance
    from toolkit.pipeline import load_fitted_module

    module = load_fitted_module(args.run, device=args.device)
    gt = module.input.ground_truth
    if not gt or not gt.get("params"):
        raise SystemExit(f"{args.run}: the scene has no ground truth to sweep around")
    names = list(module.material.param_names)
    if args.param not in names:
        raise SystemExit(f"{args.param!r} is not a parameter of {module.material.registry_name}: {', '.join(names)}")
    fitted_v0 = module.v0.detach().clone()
    fitted = module.material_params().detach().clone()
    with torch.no_grad():
        module.v0.copy_(torch.tensor(gt["v0"], dtype=module.v0.dtype))
    base = fitted.clone()
    for j, name in enumerate(names):
        if name in gt["params"]:
            base[j] = gt["params"][name]
    cams = list(module.input.train_cameras)
    frames = list(range(1, module.input.n_train))
    x0 = (module.particles0 + module.particle_offset).detach()
    if args.gaussian_shape:
        module.set_gaussian_shape(args.gaussian_shape)
    print(json.dumps({"run": str(args.run), "truth": gt["params"], "param": args.param, "frames": frames,
                      "gaussian_shape": module.gaussian_shape}), flush=True)

    def score(params, v0) -> dict:
        out = module.simulator.rollout(x0, v0, params, gravity=module.gravity.detach(),
                                       effect_params=module.effect_params.detach(), n_frames=max(frames))
        whole = module.probe_losses(out.positions, module.stages[-1], cams, frames)
        per = [module.probe_losses(out.positions, module.stages[-1], cams, [f])["image"] for f in frames]
        chamfer = [1e3 * mean_nearest_distance(out.positions[f].detach().cpu().numpy(),
                                               module.input.surfaces[f].cpu().numpy()) for f in frames]
        return {"geometry": whole["geometry"], "image": whole["image"], "image_per_frame": [round(x, 6) for x in per],
                "chamfer_mm": round(sum(chamfer) / len(chamfer), 4), "chamfer_mm_per_frame": [round(x, 3) for x in chamfer]}

    with torch.no_grad():
        for point, params, v0 in (("fit", fitted, fitted_v0), ("truth", base, module.v0.detach())):
            print(json.dumps({"point": point, "params": dict(zip(names, params.tolist())), "v0": v0.tolist(),
                              **score(params, v0)}), flush=True)
        for value in args.values:
            params = base.clone()
            params[names.index(args.param)] = value
            print(json.dumps({args.param: value, **score(params, module.v0.detach())}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The fit's own loss along one material parameter, for a finished run, at the true state.

Loads a run folder's fitted module (its appearance, positions and embedding as fitted), puts the
initial velocity and every material parameter at the scene's ground truth, then varies one
parameter and prints the image and geometric terms over the training frames (every training
camera), total and per frame. Shows which frames and which term pull an estimate away from the
truth (docs/results/five_families_small.md, "every family is fitted too soft").

With ``--deform-covariances`` every Gaussian's covariance is also deformed by the affine motion of
its 24 nearest particles, ``A Sigma A^T`` (:func:`toolkit.physics.embedding.local_deformation`),
which the fit itself does not do yet: it shows where the image term's minimum would be if it did.

Output: one JSON line of settings, then one per value: ``{param: value, "geometry", "image",
"image_per_frame"}`` (frames 1 .. n_train-1).

Usage::

    projo4d run SCENE --geometry oracle --out RUN ...                      # a fitted run of a generated scene
    python benchmarks/fitted_landscape.py RUN mu 0.01 0.05 0.3 1 3.5 10
    python benchmarks/fitted_landscape.py RUN mu 0.05 0.5 3.5 10 --deform-covariances
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
    ap.add_argument("--deform-covariances", action="store_true",
                    help="deform each Gaussian's covariance with its neighbourhood's affine motion (not what the fit does)")
    args = ap.parse_args(argv)

    import torch

    from toolkit.pipeline import load_fitted_module

    module = load_fitted_module(args.run, device="cpu")
    gt = module.input.ground_truth
    if not gt or not gt.get("params"):
        raise SystemExit(f"{args.run}: the scene has no ground truth to sweep around")
    names = list(module.material.param_names)
    if args.param not in names:
        raise SystemExit(f"{args.param!r} is not a parameter of {module.material.registry_name}: {', '.join(names)}")
    with torch.no_grad():
        module.v0.copy_(torch.tensor(gt["v0"], dtype=module.v0.dtype))
    base = module.material_params().detach().clone()
    for j, name in enumerate(names):
        if name in gt["params"]:
            base[j] = gt["params"][name]
    cams = list(module.input.train_cameras)
    frames = list(range(1, module.input.n_train))
    x0 = (module.particles0 + module.particle_offset).detach()
    if args.deform_covariances:
        _deform_covariances(module, x0)
    print(json.dumps({"run": str(args.run), "truth": gt["params"], "param": args.param, "frames": frames,
                      "deform_covariances": args.deform_covariances}), flush=True)
    for value in args.values:
        params = base.clone()
        params[names.index(args.param)] = value
        out = module.simulator.rollout(x0, module.v0.detach(), params, gravity=module.gravity.detach(),
                                       effect_params=module.effect_params.detach(), n_frames=max(frames))
        whole = module.probe_losses(out.positions, module.stages[-1], cams, frames)
        per = [module.probe_losses(out.positions, module.stages[-1], cams, [f])["image"] for f in frames]
        print(json.dumps({args.param: value, "geometry": whole["geometry"], "image": whole["image"],
                          "image_per_frame": [round(x, 6) for x in per]}), flush=True)
    return 0


def _deform_covariances(module, x0) -> None:
    """Wrap ``module.gaussians_at`` so every Gaussian carries its neighbourhood's deformation
    gradient since frame 0 (``Gaussians.deformation``: covariance ``A R S S^T R^T A^T``)."""
    import torch

    from toolkit.physics.embedding import local_deformation

    idx, grad = local_deformation((module.gaussian_means0 + module.gaussian_offset).detach(), x0)
    original = module.gaussians_at

    def gaussians_at(positions, x0_, appearance_grad=True):
        return [g.replace(deformation=torch.einsum("gki,gkj->gij", p.detach()[idx], grad))
                for p, g in zip(positions, original(positions, x0_, appearance_grad))]

    module.gaussians_at = gaussians_at


if __name__ == "__main__":
    sys.exit(main())

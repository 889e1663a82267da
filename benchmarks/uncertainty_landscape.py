"""The fit's own loss along one material parameter for one scene of the uncertainty benchmark, at the true v0.

Shows where the loss terms have their minimum, apart from any optimizer or start: the image term
(the truth is rendered by the generator's mesh renderer, the fit by Gaussians) and the geometric
term (simulated surface vs the oracle geometry's surfaces), on the benchmark's fitting grid or on
another. Used to find why stiff tosses end soft (docs/tutorials/uncertainty.md).

Output: one JSON line per E with the loss terms over frames 1..n_train-1 and over the coarse
search's 3 scoring frames (2, 4, 6), every training camera.

Usage::

    python benchmarks/uncertainty_landscape.py 33                  # scene 33 on the benchmark's grid (dx 0.04 m)
    python benchmarks/uncertainty_landscape.py 33 --dx 0.02 --spacing 0.01 --substeps 80   # on the truth's grid
    python benchmarks/uncertainty_landscape.py 1 --material sand --param friction_angle --values 15 20 25 30 35 40

The other parameters stay at the truth; ``--param`` values are physical (log10 for ``E``'s
default list only).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=int, help="scene index of benchmarks/uncertainty.py's plan (24-47: the held-out set)")
    ap.add_argument("--out", default="outputs/uncertainty_landscape", help="where the scene is generated")
    ap.add_argument("--dx", type=float, help="fitting grid spacing, m (default: the benchmark's)")
    ap.add_argument("--spacing", type=float, help="fitting particle spacing, m (default: the benchmark's)")
    ap.add_argument("--substeps", type=int, help="substeps per frame (default: the benchmark's)")
    ap.add_argument("--log-e", type=float, nargs="+", default=[4.0, 4.5, 5.0, 5.25, 5.5, 5.75, 6.0, 6.5])
    ap.add_argument("--material", default="neo_hookean", help="material family of the scene plan (neo_hookean, plasticine, newtonian, sand)")
    ap.add_argument("--param", default="E", help="material parameter to vary (default E)")
    ap.add_argument("--values", type=float, nargs="+", help="physical values of --param (default: 10**--log-e for E)")
    args = ap.parse_args(argv)

    import torch

    import uncertainty as bench
    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.oracle import oracle_input

    fit = dict(bench.FIT)
    fit.update({k: v for k, v in (("dx", args.dx), ("particle_spacing", args.spacing), ("substeps", args.substeps)) if v})
    plan = bench.scene_plan(1, args.scene, args.material)[0]
    truth = dict(plan.get("params") or {"E": plan["E"], "nu": plan["nu"]})
    values = args.values or [10.0 ** v for v in args.log_e]
    root = bench.generate(plan, Path(args.out) / "scenes" / plan["name"])
    inp = oracle_input(root, particle_spacing=fit["particle_spacing"], dx=fit["dx"])
    boundary = "slip" if plan["throw"] == "slide" else "sticky"
    module = InversePhysicsModule(inp, curriculum=fit["curriculum"], sim=SimConfig(dx=fit["dx"], substeps=fit["substeps"],
                                  auto_dt_halving=True, boundary=boundary), renderer="warp",
                                  material=args.material, initial_params=truth, optimize_params=[args.param])
    with torch.no_grad():
        module.v0.copy_(torch.tensor(plan["v0"], dtype=module.v0.dtype))
    cams = list(module.input.train_cameras)
    every = list(range(1, module.input.n_train))
    scored = [f for f in (2, 4, 6) if f < module.input.n_train]
    base = module.material_params().detach().clone()
    if args.param not in module.material.param_names:
        raise SystemExit(f"--param {args.param!r} is not a parameter of {args.material}: {', '.join(module.material.param_names)}")
    i_e = module.material.param_names.index(args.param)
    x0 = (module.particles0 + module.particle_offset).detach()
    print(json.dumps({"scene": plan["name"], "truth": truth, "throw": plan["throw"],
                      "fit": {k: fit[k] for k in ("dx", "particle_spacing", "substeps")}}), flush=True)
    for value in values:
        params = base.clone()
        params[i_e] = value
        out = module.simulator.rollout(x0, module.v0.detach(), params, gravity=module.gravity.detach(),
                                       effect_params=module.effect_params.detach(), n_frames=max(every))
        whole = module.probe_losses(out.positions, module.stages[-1], cams, every)
        search = module.probe_losses(out.positions, module.stages[-1], cams, scored)
        print(json.dumps({args.param: value, "clip": whole, "search_frames": search}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Discovery's confirmation objective along one candidate's strength, the base refitted at each value.

For a fitted run folder (a discovery benchmark's ``runs/<scene>`` or any ``projo4d run`` folder),
builds the discovery library (:class:`toolkit.discovery.library.LibraryModel`) on the same fit
frames as :func:`toolkit.discovery.workflow.discover`
(:func:`~toolkit.discovery.workflow.refit_frames`), refits the base parameters once, then for each
value of one strength (``PARAM``, e.g.
``ground_friction.mu``) holds it there and refits the base parameters (v0, the material, the body's
shift) with the confirmation's Levenberg-Marquardt. The lowest objective over the values is where
the data put that strength once everything else may follow it; a profile that falls toward the
truth while the confirmation's refit stays at zero says the refit's start, one that rises says the
objective itself.

``--surfaces-from RUN2`` uses another run's geometric targets (an oracle run's of the same
scene, or the reverse), which splits what the body does from what the targets do.

``--start observed-slide`` also refits each value from v0's horizontal components at the observed
slide's velocity where it starts (the base fit may have slowed the throw to imitate friction);
each line then has both starts. The phase the workflow would find (``leading_phase`` on the base
fit) and the minimum height of the base prediction above the ground per frame (grid cells) are in
the first line: discovery only gives ground friction a refit of its own on a slide.

Output: one JSON line of settings, then one per value: ``{PARAM: value, START: {"objective",
"v0"}}``. Usage::

    python benchmarks/strength_profile.py RUN ground_friction.mu 0 0.1 0.2 0.3 0.4 --start observed-slide

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a fitted run folder (physics_input.pt + physics/checkpoints/last.ckpt)")
    ap.add_argument("param", help="a candidate strength of the discovery library, e.g. ground_friction.mu")
    ap.add_argument("values", type=float, nargs="+", help="values of the strength (the library's units)")
    ap.add_argument("--start", choices=["base", "observed-slide"], default="base",
                    help="observed-slide: also refit from v0 at the observed slide's velocity")
    ap.add_argument("--surfaces-from", metavar="RUN2",
                    help="use another run's geometric targets (its physics_input.pt's surfaces, the same scene "
                         "and frames), e.g. an oracle run's, to split the body from the targets")
    ap.add_argument("--iterations", type=int, default=8, help="Levenberg-Marquardt iterations per refit (default 8)")
    ap.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N (default cpu)")
    args = ap.parse_args(argv)
    from toolkit.run_validation import parse_device_option

    args.device = parse_device_option(ap, args.device)
    if args.surfaces_from and not (Path(args.surfaces_from) / "physics_input.pt").is_file():
        ap.error(f"--surfaces-from {args.surfaces_from}: no physics_input.pt there (expected a run folder of the same scene)")

    import numpy as np

    from toolkit.verbosity import configure_output

    configure_output(False)  # stdout holds only the JSON lines (no Warp banner or module-load lines)

    from toolkit.discovery.confirm import lm_refit
    from toolkit.discovery.kinematics import leading_phase, observed_motion
    from toolkit.discovery.library import LibraryModel
    from toolkit.discovery.loading import load_fitted_module
    from toolkit.discovery.workflow import refit_frames

    module = load_fitted_module(args.run, device=args.device)
    if args.surfaces_from:
        from toolkit.physics.inputs import PhysicsInput

        other = PhysicsInput.load(Path(args.surfaces_from) / "physics_input.pt")
        if len(other.surfaces) != len(module.input.surfaces):
            raise SystemExit(f"--surfaces-from {args.surfaces_from}: {len(other.surfaces)} frames of surfaces, "
                             f"{args.run} has {len(module.input.surfaces)}; expected a run of the same scene")
        module.input.surfaces = [t.to(module.input.surfaces[0].device) for t in other.surfaces]
    lib = LibraryModel(module, None)
    if args.param not in lib.index_of:
        raise SystemExit(f"{args.param!r} is not a strength of this run's library: "
                         f"{', '.join(n for n in lib.index_of if '.' in n and not n.startswith(('v0.', 'mat.', 'shift.')))}")
    lib.calibrate_geometry_weight(lib.q0)
    lib.fit_frames, _ = refit_frames(module.input.n_train)
    frames, phase = leading_phase(lib, lib.q0, lib.fit_frames)
    _, pos = lib.trajectory(lib.q0, lib.fit_frames)
    ground, dx = lib.sim.config.ground_height, float(lib.sim.config.dx)
    heights = None if ground is None else [round(float((p[..., 1].min() - ground) / dx), 3) for p in pos]
    motion = observed_motion(lib, lib.q0)
    if args.start == "observed-slide" and (motion is None or motion.phase != "slide"):
        found = f"a {phase} over frames {frames}" if frames else "no run of 5 frames on or off the ground"
        raise SystemExit(f"{args.run}: no observed slide (the base prediction has {found}); "
                         f"--start observed-slide needs one")
    base = lm_refit(lib, lib.q0, lib.base_names, "base", iterations=args.iterations)
    print(json.dumps({"run": str(args.run), "surfaces_from": args.surfaces_from, "param": args.param,
                      "base_names": lib.base_names,
                      "base_objective": base.objective, "fit_frames": lib.fit_frames,
                      "leading_phase": {"frames": frames, "phase": phase}, "min_height_cells": heights,
                      "motion": motion.to_dict() if motion else None}), flush=True)
    starts = {"base": base.q}
    if args.start == "observed-slide":
        q = base.q.copy()
        t1 = float(module.input.times[motion.frames[0]]) - float(module.input.times[0])
        v1 = np.asarray(motion.v0) + np.asarray(motion.acceleration) * t1
        q[lib.index_of["v0.x"]], q[lib.index_of["v0.z"]] = v1[0], v1[2]
        starts["observed_slide"] = q
    i = lib.index_of[args.param]
    for value in args.values:
        row: dict = {args.param: value}
        for label, q0 in starts.items():
            q = q0.copy()
            q[i] = value
            t = time.time()
            rf = lm_refit(lib, q, lib.base_names, f"{args.param}={value}", iterations=args.iterations)
            row[label] = {"objective": rf.objective, "v0": [round(float(rf.q[lib.index_of[f"v0.{a}"]]), 4) for a in "xyz"],
                          "seconds": round(time.time() - t, 1)}
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

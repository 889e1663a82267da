"""Calibration benchmark of the uncertainty (issue #24): do the 90 % intervals contain the truth?

Generates scenes of three throws (``toss``: thrown down onto the ground, impact in the fitted
frames; ``slide``: set down on a frictionless (slip) ground and pushed sideways, no impact; ``lob``:
thrown up, landing near the end of the clip), several stiffnesses E (1e4 to 3e5 Pa), two shapes
(box, sphere) and camera rings turned by different azimuths. Each scene is simulated and rendered by
the synthetic generator at a finer resolution than the fit (truth dx 0.02 m with 0.01 m particles;
fit dx 0.04 m with 0.02 m particles), fitted with oracle geometry from the material's default
initial guess (log10 E = 5.5; nu fixed at the truth), and the fit's
:func:`toolkit.physics.uncertainty.estimate_uncertainty` (run by the fit's estimate writer) is
compared with the truth.

Output: one JSON line per scene and, at the end, one JSON line per (parameter, label) with the
number of estimates and the fraction whose interval contains the truth, one per label over all
parameters, and one with the cost of the uncertainty relative to the fit; ``OUT/results.jsonl``
(resumable: finished scenes are skipped) and ``OUT/coverage.md`` (the table for the docs).

Usage::

    python benchmarks/uncertainty.py --out outputs/uncertainty            # 24 tiny CPU scenes
    python benchmarks/uncertainty.py --out outputs/uncertainty --scenes 6 # a quick look
    python benchmarks/uncertainty.py --out outputs/uncertainty_heldout --first 24   # 24 other scenes
    python benchmarks/uncertainty.py --out outputs/unc_plasticine --material plasticine --scenes 12
    python benchmarks/uncertainty.py --out outputs/uncertainty --jobs 8   # 8 scenes at a time, one core each

Other materials (``--material plasticine|newtonian|sand``): the same throws, shapes and cameras
with the truths of :data:`OTHER_TRUTHS`, every optimizable parameter fitted from the material's
default guess (after the coarse search), default learning rates.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from toolkit.atomic import write_text  # noqa: E402

THROWS = ("toss", "slide", "lob")
STIFFNESS = (1e4, 3e4, 1e5, 3e5)
SHAPES = {"box": {"size_x": 0.12, "size_y": 0.08, "size_z": 0.1}, "sphere": {"radius": 0.05}}
TRUTH_DX = 0.02
FIT = dict(dx=0.04, substeps=30, particle_spacing=0.02, curriculum="XAS:20@3,XASM:50")


#: truths of the other material families (``--material``), cycled like STIFFNESS; every optimizable
#: parameter of the material is fitted from the material's default guess (coarse search first)
OTHER_TRUTHS: dict[str, tuple[dict[str, float], ...]] = {
    "plasticine": ({"E": 2e5, "nu": 0.3, "yield_stress": 3e3}, {"E": 5e5, "nu": 0.25, "yield_stress": 1e4},
                   {"E": 1e5, "nu": 0.35, "yield_stress": 1e3}, {"E": 1e6, "nu": 0.3, "yield_stress": 2e4}),
    "newtonian": ({"mu": 1.0, "kappa": 3e4}, {"mu": 10.0, "kappa": 1e5}, {"mu": 0.3, "kappa": 1e4}, {"mu": 3.0, "kappa": 5e4}),
    "sand": ({"friction_angle": 25.0}, {"friction_angle": 35.0}, {"friction_angle": 40.0}, {"friction_angle": 30.0}),
}


def scene_plan(n: int, first: int = 0, material: str = "neo_hookean") -> list[dict]:
    """``n`` scenes from index ``first``, cycling through throws, stiffnesses (or, for another
    ``material``, the truths of :data:`OTHER_TRUTHS`), shapes, speeds and camera azimuths
    (deterministic; ``first = 24`` gives 24 scenes unlike the first 24)."""
    if material != "neo_hookean":
        plans = scene_plan(n, first)
        truths = OTHER_TRUTHS[material]
        for k, plan in enumerate(plans):
            i = first + k
            plan.update(material=material, params=dict(truths[(i // 3) % len(truths)]),
                        name=f"{i:02d}_{material}_{plan['throw']}_{plan['shape']}")
            plan.pop("E"), plan.pop("nu")
        return plans
    plans = []
    for i in range(first, first + n):
        throw = THROWS[i % 3]
        E = STIFFNESS[(i // 3) % len(STIFFNESS)]
        shape = ("box", "sphere")[(i // 12) % 2]
        sign = 1 if i % 2 == 0 else -1
        speed = 0.5 + 0.1 * (i % 5)
        if throw == "toss":
            v0 = (sign * speed, -0.8, 0.2 * sign)
        elif throw == "slide":
            v0 = (speed, 0.0, -0.2 * sign)
        else:
            v0 = (0.3 * sign, 1.1 + 0.05 * (i % 3), speed * 0.4)
        plans.append({"name": f"{i:02d}_{throw}_{shape}_E{E:.0e}", "throw": throw, "E": E, "nu": 0.3, "shape": shape,
                      "v0": v0, "azimuth": 17.0 * i, "material": "neo_hookean", "params": {"E": E, "nu": 0.3}})
    return plans


def _height(shape: str) -> float:
    size = SHAPES[shape]
    return size.get("size_y", 2 * size.get("radius", 0.0))


def generate(plan: dict, root: Path) -> Path:
    from toolkit.synthetic import SceneSpec, generate_scene

    if (root / "ground_truth.json").exists():
        return root
    h = _height(plan["shape"])
    y = {"toss": 0.22, "slide": h / 2 + TRUTH_DX + 1e-4, "lob": h / 2 + 0.05}[plan["throw"]]
    spec = SceneSpec.preset(
        "small", shape=plan["shape"], shape_size=dict(SHAPES[plan["shape"]]), material=plan.get("material", "neo_hookean"),
        params=dict(plan.get("params") or {"E": plan["E"], "nu": plan["nu"]}), v0=tuple(plan["v0"]), position=(0.0, y, 0.0), n_frames=8, n_train_frames=7,
        width=32, height=32, dx=TRUTH_DX, particle_spacing=0.01, substeps=80, supersample=1, ground_plane=False,
        boundary="slip" if plan["throw"] == "slide" else "sticky", azimuth_offset_deg=plan["azimuth"],
    )
    generate_scene(spec, root)
    return root


def run_scene(plan: dict, out: Path) -> dict:
    import torch

    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.fit import fit_physics
    from toolkit.physics.oracle import oracle_input

    root = generate(plan, out / "scenes" / plan["name"])
    inp = oracle_input(root, particle_spacing=FIT["particle_spacing"], dx=FIT["dx"])
    sim = SimConfig(dx=FIT["dx"], substeps=FIT["substeps"], auto_dt_halving=True,
                    boundary="slip" if plan["throw"] == "slide" else "sticky")
    material = plan.get("material", "neo_hookean")
    if material == "neo_hookean":  # E alone, nu fixed at the truth (the calibration set of issue #24)
        options = dict(initial_params={"nu": plan["nu"]}, optimize_params=["E"], learning_rates={"velocity": 0.1, "E": 0.1})
    else:  # every optimizable parameter from the material's default guess, default learning rates
        options = dict(material=material)
    module = InversePhysicsModule(inp, curriculum=FIT["curriculum"], sim=sim, renderer="warp", **options)
    t = time.perf_counter()
    torch.manual_seed(0)
    fit_physics(module, out / "fits" / plan["name"], checkpoint_every=0, accelerator="cpu", progress=False)
    total = time.perf_counter() - t
    unc = module.uncertainty_result
    truth = {**plan["params"], "v0_x": plan["v0"][0], "v0_y": plan["v0"][1], "v0_z": plan["v0"][2]}
    params = {}
    for name, p in unc["parameters"].items():
        tr = truth.get(name)
        params[name] = {k: p.get(k) for k in ("value", "low", "high", "label", "ratio", "note", "grid_value", "data_low",
                                               "data_high")}
        params[name]["truth"] = tr
        params[name]["covered"] = None if tr is None else bool(p["low"] - 1e-9 <= tr <= p["high"] + 1e-9)
        if p.get("data_low") is not None and tr is not None:  # the interval of the data alone, without the grid term
            params[name]["covered_by_data"] = bool(p["data_low"] - 1e-9 <= tr <= p["data_high"] + 1e-9)
    return {"scene": plan["name"], "material": material, "truth": plan["params"],
            **{k: plan[k] for k in ("throw", "shape", "azimuth")}, "v0": list(plan["v0"]),
            "contact": module.contact_normal is not None, "parameters": params, "fit_s": round(total - unc["seconds"], 2),
            "uncertainty_s": round(unc["seconds"], 3), "rollouts": unc["rollouts"], "prior_step": unc["prior_step"].get("taken")}


def tabulate(results: list[dict]) -> tuple[list[dict], str]:
    """Coverage per (parameter, label) and per label; the markdown table."""
    cells: dict = defaultdict(lambda: [0, 0, 0, 0])
    for r in results:
        for name, p in r["parameters"].items():
            if p["covered"] is None or p["note"].startswith("fixed"):
                continue
            for key in ((name, p["label"]), ("all", p["label"])):
                cells[key][0] += 1
                cells[key][1] += int(p["covered"])
                if p.get("covered_by_data") is not None:  # runs before the grid term have no data-only interval
                    cells[key][2] += 1
                    cells[key][3] += int(p["covered_by_data"])
    rows = [{"parameter": k[0], "label": k[1], "n": v[0], "coverage": round(v[1] / v[0], 3),
             "coverage_data_only": round(v[3] / v[2], 3) if v[2] else None} for k, v in sorted(cells.items())]
    fixed = [r for r in results for n, p in r["parameters"].items() if p["note"].startswith("fixed")]
    lines = ["| parameter | label | estimates | 90 % interval contains the truth | without the grid term |", "|---|---|---|---|---|"]
    pct = lambda x: "-" if x is None else f"{100 * x:.0f} %"  # noqa: E731
    lines += [f"| {r['parameter']} | {r['label']} | {r['n']} | {pct(r['coverage'])} | {pct(r['coverage_data_only'])} |"
              for r in rows]
    fit = sum(r["fit_s"] for r in results)
    unc = sum(r["uncertainty_s"] for r in results)
    lines.append("")
    lines.append(f"{len(results)} scenes; v0 along the ground normal fixed at 0 by contact in {len(fixed)} of them. "
                 f"Uncertainty cost: {unc:.1f} s over {fit:.1f} s of fitting ({100 * unc / max(fit, 1e-9):.1f} %).")
    return rows, "\n".join(lines)


def _run_one(plan: dict, out: Path, threads: int) -> tuple[str, dict]:
    import torch

    torch.set_num_threads(threads)
    try:
        return plan["name"], run_scene(plan, out)
    except Exception as err:  # report and go on: one failed scene must not hide the others
        return plan["name"], {"scene": plan["name"], "error": f"{type(err).__name__}: {err}"}


def _run_all(plans: list[dict], out: Path, jobs: int, threads: int):
    """Yield ``(name, record)`` for each plan as it finishes; ``jobs`` > 1 runs them in that many
    processes (spawned: Warp and torch do not survive a fork), each with ``threads`` torch threads."""
    if jobs <= 1:
        for plan in plans:
            yield _run_one(plan, out, threads)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(_run_one, plan, out, threads) for plan in plans]
        for fut in as_completed(futures):
            yield fut.result()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="outputs/uncertainty")
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--first", type=int, default=0, help="index of the first scene (24: a held-out set)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per scene")
    ap.add_argument("--jobs", type=int, default=1, help="scenes fitted at once, each in its own process")
    ap.add_argument("--material", default="neo_hookean", choices=["neo_hookean", *OTHER_TRUTHS],
                    help="material family (neo_hookean: E alone with nu fixed; others: every optimizable parameter)")
    args = ap.parse_args(argv)
    for flag in ("scenes", "jobs", "threads"):
        if getattr(args, flag) < 1:
            ap.error(f"--{flag} must be >= 1, got {getattr(args, flag)}")
    import torch

    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    done_path = out / "results.jsonl"
    done = {}
    if done_path.is_file():
        for line in done_path.read_text().splitlines():
            if line.strip():
                rec = json.loads(line)
                done[rec["scene"]] = rec
    plans = scene_plan(args.scenes, args.first, args.material)
    todo = [p for p in plans if p["name"] not in done]
    for name, rec in _run_all(todo, out, args.jobs, args.threads):
        with done_path.open("a") as f:  # one line per finished scene: a killed run resumes from here
            f.write(json.dumps(rec) + "\n")
        done[name] = rec
    results = []
    for plan in plans:
        rec = done[plan["name"]]
        print(json.dumps(rec), flush=True)
        if "error" not in rec:
            results.append(rec)
    rows, table = tabulate(results)
    for r in rows:
        print(json.dumps({"coverage": r}))
    fit = sum(r["fit_s"] for r in results)
    unc = sum(r["uncertainty_s"] for r in results)
    print(json.dumps({"scenes": len(results), "fit_s": round(fit, 1), "uncertainty_s": round(unc, 2),
                      "uncertainty_fraction": round(unc / max(fit, 1e-9), 4)}))
    write_text(out / "coverage.md", table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

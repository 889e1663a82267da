"""Volume the continuum (``toolkit.scene.continuum.build_continuum``) gives perfect Gaussians.

Separates the continuum procedure's own volume error from stage 0's: the Gaussians here are the
true body (its ``fill_mesh`` lattice at ``--gauss-spacing``, isotropic standard deviation
``0.6 x`` that spacing, opacity ~1), the masks are the true body's silhouettes at frame 0 from
the suite's camera rig (11 cameras at 400 px, 3 training cameras [1, 5, 9] by default), and the
config is the pipeline's (``grid_size = 8 dx / 2 = 0.08``, candidate and final level 3, spacing
0.01 m). The reference is the true body filled by ``fill_mesh`` at the continuum's spacing.

The rig: the scene's cameras frame the whole trajectory (``toolkit.synthetic.scene._cameras_for``);
the trajectory is simulated here at ``dx = 0.02`` (seconds) instead of the suite's 0.008, so the
cameras sit within a few millimetres of the generated scene's.

Variants (``--variants``, default all), one setting changed at a time from ``base``:

* ``base``: the pipeline's config.
* ``n_smooth=K``: K blur/threshold/re-stamp passes at the final level (default 20).
* ``no_centres``: Gaussian centres are not stamped (carved candidates only).
* ``density_min=X``: interior threshold (default 0.5).
* ``all_cams``: every camera of the rig carves (11), not the 3 training ones.
* ``no_coarse``: no coarse-to-fine (grid_size 0.02, levels 1: the volume starts at 0.01 m).
* ``truth_occupancy``: no carving at all: the true body's voxels at 0.01 m go through the
  smoothing (``density_volume``) and the interior threshold of the pipeline's config.
* ``vertex_stamp``: ``centre_stamp=ellipsoid``: centres stamp the lattice vertices inside their
  Gaussian's 1-sigma ellipsoid and every silhouette instead of the vertex nearest them.
* ``opacity=P``: the Gaussians' opacity is P (semi-transparent: the rendered depth averages layers).
* ``KEY=VALUE`` for any :class:`~toolkit.scene.continuum.ContinuumConfig` setting
  (``carve_depth=opaque``, ``depth_margin=-1`` turns the depth test off). Settings join with
  ``+`` (``vertex_stamp+all_cams``).

One JSON line per scene x variant: ``ratio`` = particles / true count; ``carved_ratio`` = carved
candidates / true count (step 3 alone); ``outside`` / ``missing`` = particles outside the true
body / true voxels with no particle; ``shell_mm`` = outside volume / body surface area (the
mean thickness of the excess shell, mm). Usage::

    .venv/bin/python benchmarks/continuum_volume.py                       # 7 default scenes
    .venv/bin/python benchmarks/continuum_volume.py --scenes sand/0 neo_hookean/6 --variants base n_smooth=0

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import pathlib
import sys
import time
from unittest import mock

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

#: family/index -> shape (suite seed 0, pac_nerf shape set): letter_t, letter_l, cross, box, capsule, sphere, banana
DEFAULT_SCENES = ["neo_hookean/0", "neo_hookean/3", "sand/0", "neo_hookean/2", "neo_hookean/6", "sand/4", "neo_hookean/1"]
DEFAULT_VARIANTS = ["base", "n_smooth=0", "n_smooth=5", "no_centres", "density_min=0.75", "all_cams", "no_coarse",
                    "truth_occupancy", "vertex_stamp", "vertex_stamp+all_cams", "opacity=0.3", "opacity=0.3+vertex_stamp"]
PIPELINE = {"grid_size": 0.08, "candidate_level": 3, "final_level": 3}
TRAIN = [1, 5, 9]


def scene_inputs(family: str, index: int, seed: int, gauss_spacing: float):
    """(spec, mesh, cameras (11), masks (1, 11, H, W), perfect Gaussians) of one suite scene at frame 0."""
    import numpy as np
    import torch

    from renderers.base import Gaussians
    from toolkit.synthetic.filling import fill_mesh
    from toolkit.synthetic.mesh_render import MeshRenderer
    from toolkit.synthetic.scene import _cameras_for
    from toolkit.synthetic.suite import sample_scene_spec
    from toolkit.synthetic.truth import build_object, simulate_truth

    spec = sample_scene_spec(family, index, seed, "full", "cpu")
    mesh = build_object(spec)
    truth = simulate_truth(dataclasses.replace(spec, dx=0.02), mesh)  # the trajectory, for the rig only
    cams, _ = _cameras_for(spec, truth)
    grey = lambda p: np.full((len(p), 3), 0.5, np.float32)  # noqa: E731
    renderer = MeshRenderer(mesh.faces, mesh.vertices, grey, device="cpu", supersample=spec.supersample, ground=True)
    masks = torch.stack([torch.from_numpy(renderer.render(cams[c]).alpha) for c in range(len(cams))])[None]
    centres, _ = fill_mesh(mesh, gauss_spacing, device="cpu")
    n = len(centres)
    g = Gaussians(
        means=torch.from_numpy(centres).float(),
        log_scales=torch.full((n, 3), math.log(0.6 * gauss_spacing)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        opacity_logits=torch.full((n,), 5.0),
        colors=torch.full((n, 3), 0.5),
    )
    return spec, mesh, cams, masks, g


def variant_run(name: str, g, cams, masks, true_pts):
    """(particles (N, 3), spacing, carved count or None) of one variant; ``+`` joins settings."""
    import torch

    from renderers.base import Gaussians
    from toolkit.scene import continuum as C

    cfg = dict(PIPELINE)
    fields = C.ContinuumConfig().to_dict()
    cam_ids = list(TRAIN)
    patch = None
    if name == "truth_occupancy":
        pts = torch.as_tensor(true_pts, dtype=torch.float32)
        g_size = cfg["grid_size"]
        lo, hi = pts.min(0).values - g_size, pts.max(0).values + g_size
        vol, h = C.density_volume(pts, lo, hi, g_size, cfg["final_level"], C.ContinuumConfig().n_smooth)
        interior = C._box_blur(vol) >= C.ContinuumConfig().density_min
        return (interior.nonzero().float() * h + lo), h, None
    for part in name.split("+"):
        key, _, value = part.partition("=")
        if key in fields:  # any ContinuumConfig setting, cast to its default's type
            cfg[key] = type(fields[key])(value)
        elif key == "opacity":  # semi-transparent Gaussians: the rendered depth averages layers
            p = float(value)
            g = Gaussians(means=g.means, log_scales=g.log_scales, quats=g.quats,
                          opacity_logits=torch.full_like(g.opacity_logits, math.log(p / (1 - p))), colors=g.colors)
        elif key == "all_cams":
            cam_ids = list(range(len(cams)))
        elif key == "no_coarse":
            cfg.update(grid_size=0.02, candidate_level=1, final_level=1)
        elif key == "no_centres":
            real = C.density_volume
            patch = mock.patch.object(C, "density_volume", lambda points, *a, **k: real(points[:0], *a, **k))
        elif key == "vertex_stamp":  # the name the first measurement used
            cfg["centre_stamp"] = "ellipsoid"
        elif key != "base":
            raise SystemExit(f"unknown variant {part!r}")
    idx = torch.tensor(cam_ids)
    with patch if patch is not None else contextlib.nullcontext():
        res = C.build_continuum(g, cams[idx], masks[:, idx], frames=[0], config=cfg, renderer="warp", device="cpu")
    return res.particles, res.spacing, res.stats["frames"][0].get("carved")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=DEFAULT_SCENES, metavar="FAMILY/INDEX")
    parser.add_argument("--variants", nargs="*", default=DEFAULT_VARIANTS)
    parser.add_argument("--seed", type=int, default=0, help="suite seed (default 0)")
    parser.add_argument("--gauss-spacing", type=float, default=0.005, help="lattice of the perfect Gaussians, m")
    args = parser.parse_args()

    import logging

    logging.disable(logging.WARNING)
    out = sys.stdout
    with contextlib.redirect_stdout(sys.stderr):  # Warp's messages: stdout keeps the JSON lines only
        run(args, out)


def run(args, out) -> None:
    import numpy as np

    from toolkit.synthetic.filling import fill_mesh, inside_mesh

    for item in args.scenes:
        family, index = item.split("/")
        spec, mesh, cams, masks, g = scene_inputs(family, int(index), args.seed, args.gauss_spacing)
        true_cache: dict = {}
        for name in args.variants:
            t0 = time.perf_counter()
            spacing_ref = 0.02 / 2 if "no_coarse" in name.split("+") else PIPELINE["grid_size"] / 2 ** PIPELINE["final_level"]
            if spacing_ref not in true_cache:
                true_cache[spacing_ref] = fill_mesh(mesh, spacing_ref, device="cpu")[0]
            true_pts = true_cache[spacing_ref]
            parts, h, carved = variant_run(name, g, cams, masks, true_pts)
            p = parts.double().numpy()
            n_true = len(true_pts)
            inside = inside_mesh(mesh, p, "cpu") if len(p) else np.zeros(0, bool)
            outside = int((~inside).sum())
            print(json.dumps({
                "benchmark": "continuum_volume", "scene": f"{family}/{int(index):03d}", "shape": spec.shape,
                "variant": name, "spacing": h, "true_count": n_true, "particles": int(len(p)),
                "ratio": round(len(p) / n_true, 3),
                "carved_ratio": None if carved is None else round(carved / n_true, 3),
                "outside": outside, "missing": int(n_true - inside.sum()),
                "shell_mm": round(outside * h**3 / float(mesh.area) * 1e3, 2),
                "gaussians": len(g), "seconds": round(time.perf_counter() - t0, 1),
            }), file=out, flush=True)


if __name__ == "__main__":
    main()

"""Generate one synthetic scene in the PAC-NeRF layout, with honest ground truth.

"Honest" (DESIGN section 8): the truth is not the fitting model itself.

* Simulation: the same MLS-MPM family as the fit, but finer: ``dx`` half the fitting default,
  8x the particles (spacing ``dx / 2`` of a grid twice as fine), at least twice the substeps;
  the particles fill the exact mesh (no Gaussian-informed filling).
* Rendering: a ray-cast textured triangle mesh carried passively by the simulated particles
  (:mod:`toolkit.synthetic.embedding`), with Lambert shading under a fixed light
  (:mod:`toolkit.synthetic.mesh_render`), not Gaussian splatting; colours change with the
  surface orientation.

Example::

    spec = SceneSpec.preset("small", shape="torus", material="neo_hookean", params={"E": 1e5, "nu": 0.3},
                            v0=(1.0, 0.0, 0.0))
    root = generate_scene(spec, "out/torus")      # read back with toolkit.data.read_pac_nerf(root)
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from toolkit.synthetic.layout import all_data_entries, clear_scene_outputs, image_name, to_uint8, write_json, write_png
from toolkit.synthetic.mesh_render import Lighting, MeshRenderer
from toolkit.synthetic.rig import bounding_sphere, check_in_view, orbit_cameras
from toolkit.synthetic.spec import SceneSpec, spec_to_dict, validate_spec
from toolkit.synthetic.texture import ProceduralTexture
from toolkit.synthetic.truth import GROUND_HEIGHT, Truth, build_object, simulate_truth

__all__ = ["SceneSpec", "generate_scene", "scene_is_complete", "GENERATOR_VERSION"]

log = logging.getLogger(__name__)

#: bumped when the generator's output changes for the same spec.
GENERATOR_VERSION = 1
LIGHTING = Lighting()


def _progress(enabled: bool):
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        console=Console(stderr=True), disable=not enabled, transient=True,
    )


def scene_is_complete(out_dir: str | Path, spec: SceneSpec | None = None) -> bool:
    """True if ``out_dir`` holds a fully written scene (generated from ``spec``, when given)."""
    root = Path(out_dir)
    gt_path = root / "ground_truth.json"
    if not gt_path.is_file() or not (root / "all_data.json").is_file():
        return False
    from toolkit.data import read_ground_truth

    try:
        gt = read_ground_truth(gt_path)
        entries = json.loads((root / "all_data.json").read_text())
    except (ValueError, OSError):
        return False
    generator = gt.extra.get("generator", {})
    if spec is not None and (generator.get("spec") != spec_to_dict(spec) or generator.get("version") != GENERATOR_VERSION):
        return False
    files = [root / e["file_path"] for e in entries] + list(gt.point_clouds)
    return all(Path(p).is_file() for p in files)


def _cameras_for(spec: SceneSpec, truth: Truth):
    centre, radius = bounding_sphere(truth.surface_vertices)
    cams, distance, fov = orbit_cameras(
        centre, radius, spec.n_cameras, width=spec.width, height=spec.height, elevations_deg=spec.elevations_deg,
        azimuth_offset_deg=spec.azimuth_offset_deg, fov_y_deg=spec.fov_y_deg, distance=spec.camera_distance,
        ground_height=GROUND_HEIGHT,
    )
    check_in_view(cams, truth.surface_vertices)
    return cams, {"target": centre.tolist(), "distance": distance, "fov_y_deg": fov, "trajectory_radius": radius}


def _ground_truth_extra(spec: SceneSpec, truth: Truth, rig: dict, texture: ProceduralTexture) -> dict:
    from toolkit.mpm import SimConfig

    fit = SimConfig()
    n = truth.particles.shape[1]
    return {
        "density": spec.density,
        "simulation": {
            "solver": "toolkit.mpm MLS-MPM (Warp), forward rollout",
            "dx": spec.dx,
            "substeps": truth.substeps,
            "substeps_requested": spec.substeps,
            "stable_substeps": truth.stable_substeps,
            "viscous_substeps": truth.viscous_substeps,
            "frame_dt": 1.0 / spec.fps,
            "dt": 1.0 / spec.fps / truth.substeps,
            "particle_spacing": spec.spacing,
            "particle_volume": truth.particle_volume,
            "n_particles": n,
            "mesh_volume": truth.mesh_volume,
            "particles_volume": n * truth.particle_volume,
            "boundary": spec.boundary,
            "ground_height": GROUND_HEIGHT,
            "grid": truth.grid,
            "config": truth.sim_config,
            "fit_defaults": {"dx": fit.dx, "substeps": fit.substeps},
            "finer_than_fit_defaults": {"dx": spec.dx < fit.dx, "substeps": truth.substeps > fit.substeps},
        },
        "render": {
            "renderer": "toolkit.synthetic.mesh_render (Warp ray-cast textured triangle mesh)",
            "surface_motion": spec.surface_motion,
            "supersample": spec.supersample,
            "light_direction": list(LIGHTING.direction),
            "ambient": LIGHTING.ambient,
            "ground_plane": spec.ground_plane,
            "n_surface_vertices": int(truth.surface_vertices.shape[1]),
            "n_surface_faces": int(len(truth.surface.faces)),
            "texture": texture.to_dict(),
            "images": "RGBA PNG, straight alpha = object coverage; alpha*rgb is the object on black",
        },
        "object": {
            "shape": None if spec.mesh_path else spec.shape,
            "mesh_path": spec.mesh_path,
            "position": list(spec.position),
            "rotation_deg": list(spec.rotation_deg),
        },
        "frames": {
            "n_frames": spec.n_frames,
            "n_train_frames": spec.n_train_frames,
            "train": list(range(spec.n_train_frames)),
            "future": list(range(spec.n_train_frames, spec.n_frames)),
            "fps": spec.fps,
        },
        "cameras": {
            "n_cameras": spec.n_cameras,
            "sparse_view_indices": [1, 5, 9] if spec.n_cameras >= 10 else None,
            "elevations_deg": list(spec.elevations_deg),
            **rig,
        },
        "effect_options": spec.effect_options,
        "generator": {"name": "toolkit.synthetic", "version": GENERATOR_VERSION, "seed": spec.seed, "spec": spec_to_dict(spec)},
    }


def generate_scene(spec: SceneSpec, out_dir: str | Path, *, progress: bool = True) -> Path:
    """Simulate, render and write one scene (PAC-NeRF layout, see :mod:`toolkit.synthetic.layout`).

    Steps: validate the spec; build and pose the object; fill it with particles and simulate it
    at the truth resolution with its subdivided surface as tracers; place ``n_cameras`` on a
    ring framing the whole trajectory (every frame in view); render every camera x frame and
    the background plates; write ``all_data.json``, the images, the per-frame particle clouds
    and ``ground_truth.json`` (last). Same spec (seed included) -> byte-identical files.

    Args:
        spec: the scene.
        out_dir: folder to write (created; this layout's files in it are replaced).
        progress: show a progress bar.

    Returns:
        ``out_dir`` as a :class:`Path`.

    Raises:
        SpecError: an invalid spec (unknown names, out-of-range values, object below the
            ground) or a trajectory that leaves some camera's image (:class:`FramingError`).
        toolkit.mpm.SimulationError: the truth simulation failed.
    """
    from toolkit.data import GroundTruth, write_ground_truth, write_ply_points

    validate_spec(spec)
    root = Path(out_dir)
    mesh = build_object(spec)
    from rich.console import Console

    console = Console(stderr=True, quiet=not progress)
    with console.status(f"simulating the truth ({spec.material}, dx {spec.dx:g} m)"):
        truth = simulate_truth(spec, mesh)
    cams, rig = _cameras_for(spec, truth)

    root.mkdir(parents=True, exist_ok=True)
    clear_scene_outputs(root)
    times = np.arange(spec.n_frames, dtype=np.float64) / spec.fps
    rest = truth.surface_vertices[0]
    lo, hi = rest.min(0), rest.max(0)
    texture = ProceduralTexture.from_seed(spec.seed, size=float(np.max(hi - lo)), origin=tuple((lo + hi) / 2))
    renderer = MeshRenderer(
        truth.surface.faces, rest, texture, device=spec.device, supersample=spec.supersample, lighting=LIGHTING,
        ground=spec.ground_plane, ground_height=GROUND_HEIGHT,
    )
    data = root / "data"
    with _progress(progress) as bar:
        task = bar.add_task("rendering", total=spec.n_cameras * (spec.n_frames + 1))
        for c in range(spec.n_cameras):
            write_png(data / image_name(c, -1), to_uint8(renderer.render_background(cams[c])))
            bar.advance(task)
        for f in range(spec.n_frames):
            renderer.set_vertices(truth.surface_vertices[f])
            for c in range(spec.n_cameras):
                write_png(data / image_name(c, f), renderer.render(cams[c]).rgba8())
                bar.advance(task)
    write_json(root / "all_data.json", all_data_entries(cams, times))
    # absolute paths: write_ground_truth stores them relative to the JSON's folder
    clouds = [
        write_ply_points(root.resolve() / "gt_points" / f"frame_{f:03d}.ply", truth.particles[f]) for f in range(spec.n_frames)
    ]
    gt = GroundTruth(
        material=spec.material,
        params=_material_params(spec),
        v0=[float(v) for v in spec.v0],
        gravity=[float(g) for g in spec.gravity],
        effects=_effect_params(spec),
        point_clouds=clouds,
        extra=_ground_truth_extra(spec, truth, rig, texture),
    )
    write_ground_truth(root / "ground_truth.json", gt)
    log.debug("wrote %s (%d cameras x %d frames, %d particles)", root, spec.n_cameras, spec.n_frames, truth.particles.shape[1])
    return root


def _material_params(spec: SceneSpec) -> dict[str, float]:
    from materials import get_material

    return get_material(spec.material, **spec.material_options).complete(spec.params)


def _effect_params(spec: SceneSpec) -> dict[str, dict[str, float]]:
    from toolkit.mpm.effects import get_effect

    out = {}
    for name in sorted(set(spec.effects) | set(spec.effect_options)):
        effect = get_effect(name, **spec.effect_options.get(name, {}))
        out[name] = {**effect.defaults(), **{k: float(v) for k, v in spec.effects.get(name, {}).items()}}
    return out

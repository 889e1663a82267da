"""The physical truth of a synthetic scene: the posed object, its particles, and the fine simulation.

:func:`build_object` poses the shape (rotation, then translation of its bounding-box centre to
``spec.position``) and checks it is above the ground; :func:`simulate_truth` fills it with
particles at ``spec.spacing``, subdivides its surface to ``spec.surface_edge`` and simulates
the particles with :class:`toolkit.mpm.MPMSimulator` at the truth resolution. The surface
vertices are carried passively (they never act on the body) and are what the truth renderer
draws: by default through a moving-least-squares embedding in the simulated particles
(:mod:`toolkit.synthetic.embedding`), or, with ``surface_motion="tracers"``, as the
simulator's tracers advected with the grid velocity.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np
import trimesh

from toolkit.synthetic.embedding import SurfaceEmbedding
from toolkit.synthetic.errors import SpecError
from toolkit.synthetic.filling import fill_mesh
from toolkit.synthetic.shapes import build_shape, load_mesh_file
from toolkit.synthetic.spec import SceneSpec

__all__ = ["GROUND_HEIGHT", "Truth", "build_object", "truth_substeps", "simulate_truth"]

log = logging.getLogger(__name__)

#: y of the ground plane (DESIGN section 4), metres.
GROUND_HEIGHT = 0.0


@dataclass
class Truth:
    """The simulated ground truth of one scene.

    Attributes:
        surface: the posed rest surface (closed, subdivided), metres.
        particles: (T, N, 3) float32 particle positions per frame (frame 0 = rest), metres.
        surface_vertices: (T, V, 3) float32 surface vertex positions per frame, metres.
        particle_volume: m^3 per particle.
        mesh_volume: enclosed volume of the rest surface, m^3.
        substeps: substeps per frame actually used.
        stable_substeps: what :meth:`MPMSimulator.stable_substeps` asked for.
        viscous_substeps: what the explicit-viscosity limit asked for (0 without viscosity).
        sim_config: the :class:`SimConfig` as a dict (settings of the truth).
        grid: ``{"origin": [...], "dims": [...], "dx": ...}`` of the simulation grid.
    """

    surface: trimesh.Trimesh
    particles: np.ndarray
    surface_vertices: np.ndarray
    particle_volume: float
    mesh_volume: float
    substeps: int
    stable_substeps: int
    viscous_substeps: int
    sim_config: dict
    grid: dict


def build_object(spec: SceneSpec) -> trimesh.Trimesh:
    """The object's closed rest surface in world coordinates (metres).

    Raises:
        SpecError: unknown shape or bad sizes, unreadable mesh file, or an object that reaches
            below ``GROUND_HEIGHT + dx`` (it would start inside the ground's boundary layer).
    """
    if spec.mesh_path is not None:
        mesh = load_mesh_file(spec.mesh_path, spec.mesh_scale)
        source = f"mesh {spec.mesh_path}"
    else:
        mesh = build_shape(spec.shape, **spec.shape_size)
        if spec.mesh_scale != 1.0:
            mesh.apply_scale(spec.mesh_scale)
        source = f"shape {spec.shape!r}"
    rx, ry, rz = (math.radians(a) for a in spec.rotation_deg)
    R = trimesh.transformations.euler_matrix(rx, ry, rz, axes="sxyz")
    mesh.apply_transform(R)
    lo, hi = mesh.bounds
    mesh.apply_translation(np.asarray(spec.position, np.float64) - (lo + hi) / 2.0)
    lowest = float(mesh.bounds[0, 1])
    need = GROUND_HEIGHT + spec.dx
    if lowest < need:
        raise SpecError(
            f"the object ({source}) reaches below the ground: its lowest point is at y = {lowest:.4f} m, but it must "
            f"start at y >= {need:g} m (ground y = {GROUND_HEIGHT:g} plus one grid cell); raise position[1] to at least "
            f"{spec.position[1] + need - lowest:.4f} m"
        )
    return mesh


def particle_params(material, params: dict, particles: np.ndarray, gradient):
    """Material parameters for the truth: (P,) for a homogeneous body, (N, P) with the moduli
    scaled by ``10^(g . (x - c) / h)`` when a stiffness gradient is given (see SceneSpec)."""
    import torch

    packed = material.pack(params)
    if gradient is None or not any(gradient):
        return packed
    x = torch.as_tensor(np.asarray(particles), dtype=torch.float32)
    c = x.mean(0)
    h = float(((x.max(0).values - x.min(0).values) / 2).max().clamp_min(1e-6))
    factor = torch.pow(10.0, ((x - c) / h) @ torch.tensor(gradient, dtype=torch.float32))
    names = material.param_names
    cols = [names.index("E")] if "E" in names else [names.index(n) for n in ("mu", "kappa") if n in names]
    rows = packed.unsqueeze(0).repeat(len(x), 1)
    rows[:, cols] *= factor.unsqueeze(1)
    return rows


def truth_substeps(spec: SceneSpec, sim, params: dict[str, float]) -> tuple[int, int, int]:
    """``(substeps, stable, viscous)``: the substeps per frame for the truth.

    The maximum of ``spec.substeps``, the elastic-wave estimate of ``sim.stable_substeps`` and,
    for materials with a viscosity ``mu`` (Newtonian fluid), the explicit diffusion limit
    ``dt <= rho dx^2 / (6 mu)``.
    """
    stable = int(sim.stable_substeps(params))
    viscous = 0
    if spec.material == "newtonian" and "mu" in params:
        viscous = int(math.ceil(6.0 * params["mu"] / (spec.density * spec.dx**2) / spec.fps))
    return max(spec.substeps, stable, viscous), stable, viscous


def simulate_truth(spec: SceneSpec, mesh: trimesh.Trimesh | None = None) -> Truth:
    """Fill, subdivide and simulate the scene's object at the truth resolution.

    Args:
        spec: a validated scene specification.
        mesh: the posed rest surface (``build_object(spec)`` if not given).

    Raises:
        SpecError: bad object (see :func:`build_object`).
        toolkit.mpm.SimulationError: the simulation failed even with automatic dt halving
            (the message says where and what to change).
    """
    from materials import get_material
    from toolkit.mpm import MPMSimulator, SimConfig
    from toolkit.mpm.effects import get_effect

    mesh = build_object(spec) if mesh is None else mesh
    particles, particle_volume = fill_mesh(mesh, spec.spacing, device=spec.device)
    verts, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=spec.surface_edge, max_iter=12)
    surface = trimesh.Trimesh(verts, faces, process=False)

    material = get_material(spec.material, **spec.material_options)
    params = material.complete(spec.params)
    effect_names = sorted(set(spec.effects) | set(spec.effect_options))
    effects = [get_effect(name, **spec.effect_options.get(name, {})) for name in effect_names]
    config = SimConfig(
        dx=spec.dx,
        substeps=spec.substeps,
        frame_dt=1.0 / spec.fps,
        density=spec.density,
        particle_volume=particle_volume,
        gravity=tuple(spec.gravity),
        ground_height=GROUND_HEIGHT,
        boundary=spec.boundary,
        margin=0.3,
        auto_dt_halving=True,
        max_dt_halvings=3,
        deterministic=str(spec.device).startswith("cuda"),  # CPU launches are serial, hence reproducible
    )
    substeps, stable, viscous = truth_substeps(spec, MPMSimulator(material, config, device=spec.device), params)
    config = dataclasses.replace(config, substeps=substeps)
    sim = MPMSimulator(material, config, effects=effects, device=spec.device)
    log.info(
        "truth: %d particles (spacing %.4g m), %d surface vertices, dx %.4g m, %d substeps/frame (stable %d, viscous %d)",
        len(particles), spec.spacing, len(surface.vertices), spec.dx, substeps, stable, viscous,
    )
    use_tracers = spec.surface_motion == "tracers"
    out = sim.rollout(
        particles,
        v0=np.asarray(spec.v0, np.float32),
        params=particle_params(material, params, particles, spec.stiffness_gradient),
        gravity=np.asarray(spec.gravity, np.float32),
        effect_params=sim.pack_effects(spec.effects),
        n_frames=spec.n_frames - 1,
        tracers=np.asarray(surface.vertices, np.float32) if use_tracers else None,
    )
    positions = out.positions.cpu().numpy()
    if use_tracers:
        surface_vertices = out.tracers.cpu().numpy()
    else:
        surface_vertices = SurfaceEmbedding(particles, surface.vertices)(positions)
    cfg = config.to_dict()
    cfg["substeps"] = int(out.substeps)
    grid = sim.grid
    return Truth(
        surface=surface,
        particles=positions,
        surface_vertices=surface_vertices,
        particle_volume=float(particle_volume),
        mesh_volume=float(mesh.volume),
        substeps=int(out.substeps),
        stable_substeps=stable,
        viscous_substeps=viscous,
        sim_config=cfg,
        grid={"origin": list(grid.origin), "dims": list(grid.dims), "dx": grid.dx},
    )

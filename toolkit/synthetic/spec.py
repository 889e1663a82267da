"""What a synthetic scene is made of: :class:`SceneSpec`, its size presets, and its validation.

The truth is simulated FINER than any fit by default (DESIGN section 8): grid spacing
``dx = 0.008`` m (2.5x finer than the fitting default ``SimConfig().dx = 0.02``), particles at
``dx / 2`` spacing (about 16x as many as a fit at its default), and 200 substeps per frame (twice
the fitting default 100; more when :meth:`MPMSimulator.stable_substeps` or the viscous limit asks
for it). The truth's grid is deliberately *not* a power-of-two refinement of the fitting grid: a
fit refined to half its spacing (``--refine-grid``, 0.01 m) would otherwise run on the truth's own
lattice and recover the truth exactly, which no real capture allows (an inverse crime; scenes
generated before 2026-11-26 used 0.01 m).
The ``small`` preset (CPU-sized, for tests and demos) uses ``dx = 0.02``, i.e. the fitting
default: fits of small scenes should use a coarser grid (``ground_truth.json`` records the
settings, and ``simulation.finer_than_fit_defaults`` says where the truth is finer).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Optional

from toolkit.synthetic.errors import SpecError

__all__ = ["SceneSpec", "SIZE_PRESETS", "SURFACE_MOTIONS", "validate_spec", "spec_to_dict", "spec_from_dict"]

SURFACE_MOTIONS = ("particles", "tracers")

#: preset name -> SceneSpec fields. ``full`` is PAC-NeRF scale, ``small`` runs on a laptop CPU in seconds.
SIZE_PRESETS: dict[str, dict[str, Any]] = {
    "full": dict(width=400, height=400, n_frames=20, n_train_frames=14, n_cameras=11, dx=0.008, substeps=200),
    "small": dict(width=64, height=64, n_frames=10, n_train_frames=7, n_cameras=10, dx=0.02, substeps=200),
}


@dataclass
class SceneSpec:
    """Everything that defines one synthetic scene (SI units; angles in degrees).

    The truth-resolution defaults are finer than the fitting defaults (see the module docstring).

    Object:
        shape: registered shape name (:data:`toolkit.synthetic.shapes.SHAPES`); ignored when
            ``mesh_path`` is given.
        shape_size: the shape's size parameters (metres), defaults for the missing ones.
        mesh_path: a closed mesh file to use instead of a built-in shape.
        mesh_scale: file units -> metres.
        position: (3,) centre of the object's bounding box at rest, metres (y up).
        rotation_deg: (3,) rotation of the object about the world x, y, z axes, applied in that
            order (extrinsic XYZ Euler angles), degrees, before the translation.

    Physics:
        material: registered material name; ``material_options`` its options (e.g.
            ``{"yield_rule": "pacnerf"}`` for plasticine).
        params: material parameters (physical units); missing ones take the material's defaults.
        density: kg/m^3.
        v0: (3,) initial velocity of the whole body, m/s.
        gravity: (3,) m/s^2.
        effects: ``{effect: {param: value}}`` (``toolkit.mpm.effects``); ``effect_options``
            ``{effect: {option: value}}`` (e.g. a wall's ``normal``).
        boundary: ground contact mode (``sticky``, ``slip``, ``separate``); the ground is y = 0.
        stiffness_gradient: (3,) decades of stiffness change per half-extent of the body along x, y,
            z: each particle's moduli (E, or mu and kappa for fluids) are multiplied by
            ``10^(g . (x - c) / h)`` with c the rest centre and h the largest half-extent. ``None``
            (default): a homogeneous body.

    Video and cameras:
        fps: frames per second; frame ``t`` is at ``t / fps`` seconds.
        n_frames: frames written (frame 0 is the initial state); ``n_train_frames`` of them
            are for fitting, the rest is the future to predict.
        n_cameras: cameras on a ring around and above the object (PAC-NeRF: 11; the sparse
            protocol fits cameras 1, 5, 9, so use >= 10 for it).
        width, height: image size, pixels.
        fov_y_deg, camera_distance: vertical field of view and distance to the target; leave
            one (or both) ``None`` to frame the whole trajectory automatically.
        elevations_deg: camera elevations, cycled over the ring.
        azimuth_offset_deg: azimuth of camera 0 (from +z toward +x).
        supersample: ray samples per pixel side (2 = 2x2 anti-aliasing).
        ground_plane: render the ground (checker) into the images and plates.

    Truth resolution:
        dx: grid spacing, metres.
        particle_spacing: lattice pitch of the particles, metres (``None``: ``dx / 2``).
        substeps: minimum substeps per frame (raised to what stability needs).
        mesh_edge: longest edge of the rendered/traced surface mesh, metres (``None``: ``dx``).
        surface_motion: how the surface vertices follow the body: ``"particles"`` (default; a
            moving-least-squares embedding in the simulated particles,
            :mod:`toolkit.synthetic.embedding`) or ``"tracers"`` (the simulator's passive
            tracers, advected with the grid velocity; they can detach at impacts).

    Misc:
        seed: drives the texture (and nothing else random here): same seed, same files.
        device: Warp device for simulation and rendering.
    """

    shape: str = "torus"
    shape_size: dict[str, float] = field(default_factory=dict)
    mesh_path: Optional[str] = None
    mesh_scale: float = 1.0
    position: tuple[float, float, float] = (0.0, 0.35, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    material: str = "neo_hookean"
    material_options: dict[str, Any] = field(default_factory=dict)
    params: dict[str, float] = field(default_factory=dict)
    density: float = 1000.0
    v0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gravity: tuple[float, float, float] = (0.0, -9.8, 0.0)
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    effect_options: dict[str, dict[str, Any]] = field(default_factory=dict)
    stiffness_gradient: Optional[tuple[float, float, float]] = None
    boundary: str = "sticky"
    fps: float = 24.0
    n_frames: int = 20
    n_train_frames: int = 14
    n_cameras: int = 11
    width: int = 400
    height: int = 400
    fov_y_deg: Optional[float] = 40.0
    camera_distance: Optional[float] = None
    elevations_deg: tuple[float, ...] = (15.0, 35.0)
    azimuth_offset_deg: float = 0.0
    supersample: int = 2
    ground_plane: bool = True
    dx: float = 0.008
    particle_spacing: Optional[float] = None
    substeps: int = 200
    mesh_edge: Optional[float] = None
    surface_motion: str = "particles"
    seed: int = 0
    device: str = "cpu"

    @classmethod
    def preset(cls, size: str = "full", **overrides: Any) -> "SceneSpec":
        """A spec with the ``size`` preset (:data:`SIZE_PRESETS`) and ``overrides`` applied."""
        if size not in SIZE_PRESETS:
            raise SpecError(f"unknown size preset {size!r}; choose one of {sorted(SIZE_PRESETS)}")
        known = {f.name for f in fields(cls)}
        unknown = set(overrides) - known
        if unknown:
            raise SpecError(f"SceneSpec has no field(s) {sorted(unknown)}")
        return cls(**{**SIZE_PRESETS[size], **overrides})

    def replace(self, **changes: Any) -> "SceneSpec":
        return replace(self, **changes)

    @property
    def spacing(self) -> float:
        """Particle lattice pitch, metres."""
        return self.particle_spacing if self.particle_spacing is not None else self.dx / 2.0

    @property
    def surface_edge(self) -> float:
        """Longest edge of the traced surface mesh, metres."""
        return self.mesh_edge if self.mesh_edge is not None else self.dx


def spec_to_dict(spec: SceneSpec) -> dict:
    """JSON-ready dict (tuples become lists), the form stored in ``ground_truth.json``."""
    return json.loads(json.dumps(asdict(spec)))


def spec_from_dict(d: dict) -> SceneSpec:
    """Inverse of :func:`spec_to_dict` (unknown keys raise :class:`SpecError`)."""
    known = {f.name for f in fields(SceneSpec)}
    unknown = set(d) - known
    if unknown:
        raise SpecError(f"SceneSpec has no field(s) {sorted(unknown)}")
    d = dict(d)
    for key in ("position", "rotation_deg", "v0", "gravity", "elevations_deg", "stiffness_gradient"):
        if key in d and d[key] is not None:
            d[key] = tuple(d[key])
    return SceneSpec(**d)


def _vec3(value: Any, name: str) -> tuple[float, float, float]:
    try:
        v = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise SpecError(f"{name} must be 3 numbers, got {value!r}") from None
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise SpecError(f"{name} must be 3 finite numbers, got {value!r}")
    return v


def _positive(value: Any, name: str, unit: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise SpecError(f"{name} must be a positive number{unit}, got {value!r}")


def _int_at_least(value: Any, name: str, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise SpecError(f"{name} must be an integer >= {low}, got {value!r}")


def validate_spec(spec: SceneSpec) -> None:
    """Check every field that can be checked without building anything.

    Raises:
        SpecError: naming the field, the bad value and what is expected (unknown shape,
            material, effect or parameter names list the known ones).
    """
    from materials import MATERIALS
    from materials.base import MaterialError
    from toolkit.mpm.config import BOUNDARY_MODES
    from toolkit.mpm.effects import EFFECTS, EffectError
    from toolkit.registry import UnknownNameError
    from toolkit.synthetic.shapes import get_shape

    if spec.mesh_path is None:
        get_shape(spec.shape).complete(spec.shape_size)
    _positive(spec.mesh_scale, "mesh_scale", "")
    _vec3(spec.position, "position")
    _vec3(spec.rotation_deg, "rotation_deg")
    _vec3(spec.v0, "v0")
    _vec3(spec.gravity, "gravity")

    try:
        material = MATERIALS.get(spec.material)(**spec.material_options)
        full = material.complete(spec.params)
        material.validate(full)
    except UnknownNameError as exc:
        raise SpecError(str(exc)) from None
    except MaterialError as exc:
        raise SpecError(f"material {spec.material!r}: {exc}") from None
    _positive(spec.density, "density", " of kg/m^3")
    if spec.boundary not in BOUNDARY_MODES:
        raise SpecError(f"boundary must be one of {BOUNDARY_MODES}, got {spec.boundary!r}")

    if not isinstance(spec.effects, dict) or not all(isinstance(v, dict) for v in spec.effects.values()):
        raise SpecError(f"effects must map effect names to {{param: value}} dicts, got {spec.effects!r}")
    for name in set(spec.effects) | set(spec.effect_options):
        try:
            effect = EFFECTS.get(name)(**spec.effect_options.get(name, {}))
            effect.validate(spec.effects.get(name, {}))
        except UnknownNameError as exc:
            raise SpecError(str(exc)) from None
        except EffectError as exc:
            raise SpecError(f"effect {name!r}: {exc}") from None

    _positive(spec.fps, "fps", " of frames per second")
    _int_at_least(spec.n_frames, "n_frames", 1)
    _int_at_least(spec.n_train_frames, "n_train_frames", 1)
    if spec.n_train_frames > spec.n_frames:
        raise SpecError(f"n_train_frames ({spec.n_train_frames}) must not exceed n_frames ({spec.n_frames})")
    _int_at_least(spec.n_cameras, "n_cameras", 1)
    _int_at_least(spec.width, "width", 8)
    _int_at_least(spec.height, "height", 8)
    if spec.fov_y_deg is not None and not (isinstance(spec.fov_y_deg, (int, float)) and 1.0 <= spec.fov_y_deg <= 150.0):
        raise SpecError(f"fov_y_deg must be in [1, 150] degrees or None (automatic), got {spec.fov_y_deg!r}")
    if spec.camera_distance is not None:
        _positive(spec.camera_distance, "camera_distance", " of metres")
    if not spec.elevations_deg or not all(-89.0 <= float(e) <= 89.0 for e in spec.elevations_deg):
        raise SpecError(f"elevations_deg must be a non-empty list of angles in [-89, 89] degrees, got {spec.elevations_deg!r}")
    if not isinstance(spec.supersample, int) or not 1 <= spec.supersample <= 8:
        raise SpecError(f"supersample must be an integer in 1..8, got {spec.supersample!r}")

    _positive(spec.dx, "dx", " of metres")
    if spec.particle_spacing is not None:
        _positive(spec.particle_spacing, "particle_spacing", " of metres")
        if spec.particle_spacing > spec.dx:
            raise SpecError(f"particle_spacing ({spec.particle_spacing:g} m) must not exceed dx ({spec.dx:g} m)")
    _int_at_least(spec.substeps, "substeps", 1)
    if spec.mesh_edge is not None:
        _positive(spec.mesh_edge, "mesh_edge", " of metres")
    if spec.surface_motion not in SURFACE_MOTIONS:
        raise SpecError(f"surface_motion must be one of {SURFACE_MOTIONS}, got {spec.surface_motion!r}")
    _int_at_least(spec.seed, "seed", 0)
    if not isinstance(spec.device, str) or not spec.device:
        raise SpecError(f"device must be a Warp device name such as 'cpu' or 'cuda:0', got {spec.device!r}")

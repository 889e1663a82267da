"""The library of candidate missing effects.

Each :class:`Candidate` says how it enters the model, which strength parameter(s) it adds
(zero = absent), what extra parameters a search has to scan (where the strength's gradient at
zero tells nothing, e.g. where a wall stands), and whether it is a **control**: a change that
must not be reported as missing physics (density, not identifiable from gravity-only motion;
camera-pose error, which is an error of the observation).

How each candidate is added (``kind``):

========================= ============ ==============================================================
candidate                 kind         how it enters the model
========================= ============ ==============================================================
``ground_friction``       effect       ``ground_friction`` effect, strength ``mu``
``air_drag``              effect       ``air_drag`` effect, strengths ``linear`` (1/s), ``quadratic`` (1/m)
``extra_acceleration``    effect       ``extra_acceleration`` effect (wind / gravity error), ``ax, ay, az``
``wall``                  effect       ``wall`` effect (separating plane), strength in [0, 1]; the
                                       search scans its normal (+-x, +-z) and offset
``internal_damping``      material     Kelvin-Voigt viscosity ``eta`` (Pa s) added to the stress
                                       (:class:`~toolkit.discovery.materials.AugmentedMaterial`)
``plastic_yield``         material     the elastic model becomes ``plasticine`` (von Mises on Hencky
                                       strain); strength = yield stress, absent at infinity; the
                                       search scans log10 tau_Y
``timing``                observation  observed frame k is simulation time ``k (1 + rate) + offset``
                                       frames (time offset / frame-rate error)
``stiffness_gradient``    field        per-particle stiffness ``10^(g . (x - c) / h)`` times the
                                       modulus (h: the body's half extent), strengths ``gx, gy, gz``
``density``               control      stress scaled by ``exp(-s)`` (true density ``rho e^s``)
``camera_pose``           control      a translation per fitted camera (metres)
========================= ============ ==============================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

__all__ = ["Strength", "Candidate", "LIBRARY", "library", "candidate", "ELASTIC_MATERIALS", "WALL_NORMALS"]

#: base materials without plasticity, for which ``plastic_yield`` is a candidate.
ELASTIC_MATERIALS = ("neo_hookean", "neo_hookean_simplicits")
#: wall normals scanned by the wall search (horizontal planes facing the body).
WALL_NORMALS: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, -1.0))


@dataclass(frozen=True)
class Strength:
    """One strength parameter of a candidate.

    Attributes:
        name: short name (``mu``, ``ax``, ...); the library parameter is ``<candidate>.<name>``.
        step: finite-difference step and the unit of the Levenberg-Marquardt scaling, in the
            parameter's units.
        low, high: bounds (``low = 0`` for one-sided strengths such as a friction coefficient).
        units: units for reports.
    """

    name: str
    step: float
    low: float = -math.inf
    high: float = math.inf
    units: str = ""


@dataclass(frozen=True)
class Candidate:
    """A candidate missing effect (see the module docstring).

    Attributes:
        name: library name.
        kind: ``effect``, ``material``, ``observation``, ``field`` or ``control``.
        strengths: its strength parameters (all zero = absent).
        control: True for changes that must not be reported as physics.
        search: True when the strength's gradient at zero says nothing without choosing an
            extra parameter first (wall position, yield stress): the ranking scans a grid.
        effect: the simulator effect it adds (``kind == "effect"``).
        description: one line for reports.
        observation: True for controls that point at the observation (camera pose), False for
            the unidentifiable ones (density).
    """

    name: str
    kind: str
    strengths: tuple[Strength, ...]
    control: bool = False
    search: bool = False
    effect: Optional[str] = None
    description: str = ""
    observation: bool = False

    def parameter_names(self, n_cameras: int = 0) -> list[str]:
        """The library parameter names of this candidate's strengths."""
        if self.name == "camera_pose":
            return [f"camera_pose.c{c}.{a}" for c in range(n_cameras) for a in "xyz"]
        return [f"{self.name}.{s.name}" for s in self.strengths]

    def applicable(self, material: str, base_effects: Sequence[str] = ()) -> bool:
        """Whether the candidate can be added to a base model of ``material`` with ``base_effects``."""
        if self.effect is not None and self.effect in base_effects and self.effect != "wall":
            return False  # already in the model
        if self.name == "plastic_yield":
            return material in ELASTIC_MATERIALS
        return True


def _c(name, kind, strengths, **kw) -> Candidate:
    return Candidate(name, kind, tuple(strengths), **kw)


#: every candidate of the library, in report order.
LIBRARY: tuple[Candidate, ...] = (
    _c("ground_friction", "effect", [Strength("mu", 0.05, 0.0, 10.0)], effect="ground_friction",
       description="Coulomb friction with the ground"),
    _c("air_drag", "effect", [Strength("linear", 0.2, 0.0, 1e3, "1/s"), Strength("quadratic", 0.2, 0.0, 1e3, "1/m")],
       effect="air_drag", description="linear and quadratic air drag"),
    _c("extra_acceleration", "effect", [Strength(a, 0.2, -100.0, 100.0, "m/s^2") for a in ("ax", "ay", "az")],
       effect="extra_acceleration", description="constant extra acceleration (wind, gravity error)"),
    _c("wall", "effect", [Strength("strength", 0.2, 0.0, 1.0)], effect="wall", search=True,
       description="a wall or obstacle plane (normal and offset searched)"),
    _c("internal_damping", "material", [Strength("eta", 1.0, 0.0, math.inf, "Pa s")],
       description="internal (Kelvin-Voigt) damping"),
    _c("plastic_yield", "material", [Strength("log10_yield_stress", 0.05, 0.0, 12.0, "log10 Pa")], search=True,
       description="von Mises plastic yield (elastic model -> plasticine)"),
    _c("timing", "observation", [Strength("offset", 0.05, -2.0, 2.0, "frames"), Strength("rate", 0.01, -0.3, 0.3)],
       description="time offset / frame-rate error of the video"),
    _c("stiffness_gradient", "field", [Strength(a, 0.05, -2.0, 2.0, "decades") for a in ("gx", "gy", "gz")],
       description="stiffness varying linearly (in log) across the body"),
    _c("density", "control", [Strength("log_ratio", 0.02 * math.log(10.0), -3.0, 3.0)], control=True,
       description="density error (control: only E/rho is identifiable)"),
    _c("camera_pose", "control", [Strength("shift", 0.002, -0.2, 0.2, "m")], control=True, observation=True,
       description="camera pose error of a fitted camera (control: an observation error)"),
)


def library(names: Sequence[str] | None = None) -> list[Candidate]:
    """The candidates called ``names`` (all of :data:`LIBRARY` when ``None``), in library order.

    Raises:
        ValueError: an unknown name (the message lists the library).
    """
    if names is None:
        return list(LIBRARY)
    known = {c.name: c for c in LIBRARY}
    bad = [n for n in names if n not in known]
    if bad:
        raise ValueError(f"unknown discovery candidate(s) {bad}; the library has {sorted(known)}")
    return [c for c in LIBRARY if c.name in set(names)]


def candidate(name: str) -> Candidate:
    """One candidate by name."""
    return library([name])[0]

"""A benchmark suite of synthetic scenes across the five PAC-NeRF material families.

Layout: ``<out>/<family>/<index:03d>/`` (one PAC-NeRF-layout scene each) and ``<out>/suite.json``
(the index: settings, parameter ranges, and every scene's draw). Scene ``i`` of family ``f`` is
drawn from ``numpy.random.SeedSequence([seed, family_id(f), i])``, so a scene does not change
when other families or more scenes are added. Rerunning skips scenes already complete (same
spec, all files present) and retries failed ones.

Parameter ranges (uniform in the given scale). PAC-NeRF's repository ships only the *starting
guesses* of its fits (``configs/<family>/default.py``: elastic E = 10^5.5, nu = 0.25; Newtonian
mu = 10, kappa = 1e4; non-Newtonian mu = 100, kappa = 1e5, tau_Y = 10, eta = 1; plasticine
E = 1e4, nu = 0.25, tau_Y = 1e3; sand E = 1e6, nu = 0.3 fixed, phi = 10 deg); the per-scene ground
truth ships with its data. The ranges are chosen around those guesses (1-2 decades on each
side where the guess sits, as PAC-NeRF's scenes span), so a fit starting from the guesses
has real work to do:

=============== ========================================================================
family          parameters
=============== ========================================================================
neo_hookean     log10 E in [4.5, 6.0] Pa, nu in [0.2, 0.45]
newtonian       log10 mu in [-1.0, 1.5] Pa s, log10 kappa in [4.0, 5.0] Pa
non_newtonian   log10 mu in [2.0, 4.0] Pa, log10 kappa in [4.5, 5.5] Pa,
                log10 tau_Y in [1.0, 3.0] Pa, log10 eta in [-1.0, 1.0] Pa s
plasticine      log10 E in [4.5, 6.0] Pa, nu in [0.2, 0.4], log10 tau_Y in [2.5, 4.0] Pa
sand            friction angle in [20, 45] deg (E = 1e6 Pa, nu = 0.3 fixed, as PAC-NeRF)
=============== ========================================================================

Throws: a random shape of :data:`SUITE_SHAPES` (or the shape set's, :data:`SHAPE_SETS`) scaled by [0.8, 1.2], a random orientation,
released with its lowest point 0.12-0.35 m above the ground (PAC-NeRF: the object hits the
ground around frame 5) at a horizontal speed of 0.3-1.5 m/s in a random direction plus a
vertical speed in [-1.0, 0.5] m/s; gravity (0, -9.8, 0); sticky ground; no extra effects.

Sizes: ``full`` = PAC-NeRF scale (400x400, 11 cameras, 20 frames = 14 training + 6 future,
truth dx 0.008 m); ``small`` = CPU scale (64x64, 10 cameras, 10 frames = 7 + 3, truth dx 0.02 m,
about 1-4k particles).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Collection, Optional, Sequence

import numpy as np
import trimesh

from toolkit.synthetic.errors import SpecError
from toolkit.synthetic.layout import write_json
from toolkit.synthetic.scene import generate_scene, scene_is_complete
from toolkit.synthetic.shapes import SHAPES
from toolkit.synthetic.spec import SIZE_PRESETS, SceneSpec

__all__ = ["FAMILY_RANGES", "SUITE_SHAPES", "SPRING_GAUS_SHAPES", "SHAPE_SETS", "THROW", "sample_scene_spec", "generate_suite"]

log = logging.getLogger(__name__)

#: family (material name) -> parameter -> (scale, low, high); scale "log10" draws log10(value).
FAMILY_RANGES: dict[str, dict[str, tuple[str, float, float]]] = {
    "neo_hookean": {"E": ("log10", 4.5, 6.0), "nu": ("linear", 0.2, 0.45)},
    "newtonian": {"mu": ("log10", -1.0, 1.5), "kappa": ("log10", 4.0, 5.0)},
    "non_newtonian": {
        "mu": ("log10", 2.0, 4.0),
        "kappa": ("log10", 4.5, 5.5),
        "yield_stress": ("log10", 1.0, 3.0),
        "plastic_viscosity": ("log10", -1.0, 1.0),
    },
    "plasticine": {"E": ("log10", 4.5, 6.0), "nu": ("linear", 0.2, 0.4), "yield_stress": ("log10", 2.5, 4.0)},
    "sand": {"friction_angle": ("linear", 20.0, 45.0)},
}

SUITE_SHAPES: tuple[str, ...] = ("torus", "box", "sphere", "cross", "capsule", "letter_l", "letter_t", "banana")

#: named shape sets: ``pac_nerf`` (the default) draws a random shape of :data:`SUITE_SHAPES` for
#: each scene; ``spring_gaus`` takes the seven Spring-Gaus objects in turn (scene ``i`` is
#: ``SPRING_GAUS_SHAPES[i % 7]``: apple, banana, chess, cream, cross, paste, torus), built by
#: :mod:`toolkit.synthetic.revolved_shapes` and :mod:`toolkit.synthetic.shapes` (stand-ins: the
#: Spring-Gaus meshes are not in this repository).
SPRING_GAUS_SHAPES: tuple[str, ...] = ("apple", "banana", "chess", "cream", "cross", "paste", "torus")
SHAPE_SETS: dict[str, tuple[str, ...]] = {"pac_nerf": SUITE_SHAPES, "spring_gaus": SPRING_GAUS_SHAPES}

#: how objects are thrown (see the module docstring).
THROW = {
    "shape_scale": (0.8, 1.2),
    "release_height": (0.12, 0.35),
    "horizontal_speed": (0.3, 1.5),
    "vertical_speed": (-1.0, 0.5),
    "gravity": (0.0, -9.8, 0.0),
}


def _draw_params(family: str, rng: np.random.Generator) -> dict[str, float]:
    out = {}
    for name, (scale, lo, hi) in FAMILY_RANGES[family].items():
        x = float(rng.uniform(lo, hi))
        out[name] = float(f"{10.0**x if scale == 'log10' else x:.6g}")
    return out


def _check_shape_set(shape_set: str) -> None:
    if shape_set not in SHAPE_SETS:
        raise SpecError(f"unknown shape set {shape_set!r}; choose from {', '.join(SHAPE_SETS)}")


def sample_scene_spec(
    family: str, index: int, seed: int = 0, size: str = "small", device: str = "cpu", *, shape_set: str = "pac_nerf",
    **overrides
) -> SceneSpec:
    """The spec of scene ``index`` of ``family`` in a suite with ``seed`` (see the module docstring);
    ``shape_set`` names the shapes (:data:`SHAPE_SETS`); ``overrides`` replace fields of the
    result (e.g. ``width=32`` for a quick look). Every draw but the shape is the same in every
    shape set."""
    if family not in FAMILY_RANGES:
        raise SpecError(f"unknown material family {family!r}; choose from {', '.join(FAMILY_RANGES)}")
    if size not in SIZE_PRESETS:
        raise SpecError(f"unknown size {size!r}; choose 'small' or 'full'")
    _check_shape_set(shape_set)
    family_id = list(FAMILY_RANGES).index(family)
    ss = np.random.SeedSequence([int(seed), family_id, int(index)])
    rng = np.random.default_rng(ss)
    drawn = SUITE_SHAPES[int(rng.integers(len(SUITE_SHAPES)))]
    shape = drawn if shape_set == "pac_nerf" else SHAPE_SETS[shape_set][int(index) % len(SHAPE_SETS[shape_set])]
    scale = float(rng.uniform(*THROW["shape_scale"]))
    sizes = {k: (v if k.endswith("_deg") else round(v * scale, 4)) for k, v in SHAPES[shape].defaults.items()}
    rotation = tuple(round(float(a), 2) for a in rng.uniform(0.0, 360.0, size=3))
    mesh = SHAPES[shape](**sizes)
    R = trimesh.transformations.euler_matrix(*(math.radians(a) for a in rotation), axes="sxyz")
    mesh.apply_transform(R)
    half_height = float(mesh.extents[1]) / 2.0
    bottom = float(rng.uniform(*THROW["release_height"]))
    heading = float(rng.uniform(0.0, 2 * math.pi))
    speed = float(rng.uniform(*THROW["horizontal_speed"]))
    vy = float(rng.uniform(*THROW["vertical_speed"]))
    v0 = (round(speed * math.sin(heading), 4), round(vy, 4), round(speed * math.cos(heading), 4))
    return SceneSpec.preset(
        size,
        shape=shape,
        shape_size=sizes,
        position=(0.0, round(bottom + half_height, 4), 0.0),
        rotation_deg=rotation,
        material=family,
        params=_draw_params(family, rng),
        v0=v0,
        gravity=THROW["gravity"],
        seed=int(ss.generate_state(1)[0] % (2**31)),
        device=device,
        **overrides,
    )


def generate_suite(
    out_dir: str | Path,
    families: Sequence[str] = tuple(FAMILY_RANGES),
    scenes_per_family: int = 2,
    seed: int = 0,
    size: str = "small",
    device: str = "cpu",
    *,
    spec_overrides: dict | None = None,
    shape_set: str = "pac_nerf",
    progress: bool = True,
    only: Optional[Collection[str]] = None,
) -> dict:
    """Generate (or complete) a benchmark suite; returns the ``suite.json`` index.

    Args:
        out_dir: root folder of the suite.
        families: material families (keys of :data:`FAMILY_RANGES`).
        scenes_per_family: scenes per family.
        seed: suite seed.
        size: ``"small"`` or ``"full"`` (:data:`SIZE_PRESETS`).
        device: Warp device.
        spec_overrides: :class:`SceneSpec` fields to override in every scene (e.g. a smaller
            image size for a quick look); recorded in the index.
        shape_set: the shapes (:data:`SHAPE_SETS`: ``pac_nerf``, drawn at random, or
            ``spring_gaus``, the seven Spring-Gaus objects in turn); recorded in the index.
        progress: show progress.
        only: names (``family/index``) of the scenes to generate; the others are indexed as they
            are on disk (a missing one with ``complete: false``, so a benchmark on the suite leaves
            it out) and not generated. None: every scene.

    Raises:
        SpecError: unknown family or size, bad count. A scene whose generation fails is
            recorded in the index with its error (and retried on the next run), not raised.
    """
    from toolkit.mpm import SimulationError

    families = list(families)
    unknown = [f for f in families if f not in FAMILY_RANGES]
    if unknown:
        noun = "family" if len(unknown) == 1 else "families"
        raise SpecError(f"unknown material {noun} {unknown}; choose from {', '.join(FAMILY_RANGES)}")
    if not families:
        raise SpecError("give at least one material family")
    if isinstance(scenes_per_family, bool) or not isinstance(scenes_per_family, int) or scenes_per_family < 1:
        raise SpecError(f"scenes_per_family must be an integer >= 1, got {scenes_per_family!r}")
    if size not in SIZE_PRESETS:
        raise SpecError(f"unknown size {size!r}; choose 'small' or 'full'")
    _check_shape_set(shape_set)
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    scenes = []
    for family in families:
        for i in range(scenes_per_family):
            spec = sample_scene_spec(family, i, seed, size, device, shape_set=shape_set, **(spec_overrides or {}))
            name = f"{family}/{i:03d}"
            path = root / family / f"{i:03d}"
            entry = {
                "name": name, "path": f"{family}/{i:03d}", "family": family, "shape": spec.shape,
                "shape_size": spec.shape_size, "params": spec.params, "v0": list(spec.v0),
                "rotation_deg": list(spec.rotation_deg), "position": list(spec.position), "seed": spec.seed,
            }
            if scene_is_complete(path, spec):
                log.info("%s: complete, skipped", name)
            elif only is not None and name not in only:
                entry["not_generated"] = "not selected"
                scenes.append({**entry, "complete": False})
                continue
            else:
                if progress:
                    log.info("%s: generating (%s, %s)", name, spec.shape, spec.params)
                try:
                    generate_scene(spec, path, progress=progress)
                except (SpecError, SimulationError) as exc:
                    log.error("%s failed: %s", name, exc)
                    entry["error"] = f"{type(exc).__name__}: {exc}"
            entry["complete"] = "error" not in entry
            scenes.append(entry)
    index = {
        "format": "projo4d-synthetic-suite",
        "version": 1,
        "seed": seed,
        "size": size,
        "size_preset": SIZE_PRESETS[size],
        "spec_overrides": dict(spec_overrides or {}),
        "families": families,
        "scenes_per_family": scenes_per_family,
        "ranges": {f: {p: {"scale": s, "low": lo, "high": hi} for p, (s, lo, hi) in FAMILY_RANGES[f].items()} for f in families},
        "throw": {k: list(v) for k, v in THROW.items()},
        "shape_set": shape_set,
        "shapes": list(SHAPE_SETS[shape_set]),
        "reference": "ranges around PAC-NeRF's starting guesses (xuan-li/PAC-NeRF configs/<family>/default.py); "
        "see toolkit.synthetic.suite",
        "scenes": scenes,
    }
    write_json(root / "suite.json", index)
    return index

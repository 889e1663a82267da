"""Tiny generated scenes for the uncertainty tests: a frictionless slide and a toss with impact."""

from __future__ import annotations

from pathlib import Path

from toolkit.mpm import SimConfig

#: the slide: a soft box set down on a slip ground, moving horizontally (issue #24's puck, CPU-sized)
SLIDE_TRUTH = {"E": 3e4, "nu": 0.3}
SLIDE_V0 = (0.9, 0.0, 0.2)
SLIDE_SIZE = {"size_x": 0.12, "size_y": 0.08, "size_z": 0.1}


def slide_scene(root: Path, n_frames: int = 6) -> Path:
    """A box resting on a slip ground (its lowest point one truth grid cell, 2 cm, above it: touching the ground nodes), sliding at ``SLIDE_V0``; 10 cameras, 32 px."""
    from toolkit.synthetic import SceneSpec, generate_scene

    if (root / "ground_truth.json").exists():
        return root
    spec = SceneSpec.preset(
        "small", shape="box", shape_size=SLIDE_SIZE, material="neo_hookean", params=SLIDE_TRUTH, v0=SLIDE_V0,
        position=(-0.08, SLIDE_SIZE["size_y"] / 2 + 0.0201, 0.0), n_frames=n_frames, n_train_frames=n_frames - 1, width=32,
        height=32, dx=0.02, particle_spacing=0.01, substeps=80, supersample=1, ground_plane=False, boundary="slip",
    )
    generate_scene(spec, root)
    return root


def slide_sim() -> SimConfig:
    return SimConfig(dx=0.04, substeps=30, auto_dt_halving=True, boundary="slip")


def slide_input(root: Path):
    """The slide's oracle physics input (true geometry, particles at 2 cm), generating the scene in
    ``root`` if it is not there."""
    from toolkit.physics.oracle import oracle_input

    return oracle_input(slide_scene(root), particle_spacing=0.02)


def slide_module_at_truth(inp, sim: SimConfig | None = None):
    """An E module on the slide's input at the true material, not fitted (``sim``: default
    :func:`slide_sim`); v0 starts at the module's default."""
    from toolkit.physics import InversePhysicsModule

    return InversePhysicsModule(inp, curriculum="XAS:1,XASM:1", sim=sim or slide_sim(), renderer="warp",
                                optimize_params=["E"], initial_params=dict(SLIDE_TRUTH), material_init="given")


def toss_module_at_truth(inp):
    """An E-and-v0 module on the falling box of ``tests.physics_fixtures`` (its oracle input ``inp``),
    set to the true E and v0 without fitting (start E 1e4, no coarse search)."""
    import math

    import torch

    from tests.physics_fixtures import TRUTH, V0, fit_sim
    from toolkit.physics import InversePhysicsModule

    m = InversePhysicsModule(inp, curriculum="XAS:1,XASM:1", sim=fit_sim(), renderer="warp", optimize_params=["E"],
                             initial_params={"E": 1e4, "nu": TRUTH["nu"]}, material_init="given")
    with torch.no_grad():
        m.material_raw["E"].fill_(math.log10(TRUTH["E"]))
        m.v0.copy_(torch.tensor(V0, dtype=m.v0.dtype))
    return m

"""A tiny generated scene and its oracle physics input, shared by the physics tests."""

from __future__ import annotations

from pathlib import Path

from toolkit.mpm import SimConfig

#: the fit's simulator: coarse enough for 2 CPU cores (the truth below is finer in particles and substeps)
FIT_SIM = dict(dx=0.04, substeps=30, auto_dt_halving=True)
TRUTH = {"E": 3e4, "nu": 0.3}
V0 = (0.6, -0.8, 0.3)


def tiny_scene(root: Path, height: float = 0.16, dx: float = 0.04) -> Path:
    """A falling elastic box seen by 10 cameras at 32 px, 6 frames (5 for fitting); its centre starts
    ``height`` m above the ground (at 0.16 it lands at frame 3); the truth is simulated on a grid of
    spacing ``dx`` (m; the default is the fit's, :data:`FIT_SIM`) with particles at 1 cm or finer."""
    from toolkit.synthetic import SceneSpec, generate_scene

    if (root / "ground_truth.json").exists():
        return root
    spec = SceneSpec.preset(
        "small", shape="box", shape_size={"size_x": 0.12, "size_y": 0.08, "size_z": 0.1}, material="neo_hookean", params=TRUTH, v0=V0,
        position=(0.0, height, 0.0), n_frames=6, n_train_frames=5, width=32, height=32, dx=dx, particle_spacing=min(0.01, dx / 4),
        substeps=80, supersample=1, ground_plane=False,
    )
    generate_scene(spec, root)
    return root


def fit_sim() -> SimConfig:
    return SimConfig(**FIT_SIM)

"""``projo4d export RUN``: a fitted run as files other tools read, and as a digital twin.

Written to ``OUT`` (default ``RUN/export``)::

    gaussians.ply             the refined Gaussians at frame 0, 3DGS PLY (INRIA layout; splat viewers read it)
    sequence/particles_XXX.ply   predicted particles of frame XXX (x y z, float32)
    sequence/gaussians_XXX.ply   the Gaussians moved with them (3DGS PLY)
    twin.npz                  the digital twin (:mod:`toolkit.twin.format`)
    twin.json                 a readable copy of the twin's metadata
    twin.schema.json          the JSON schema of that metadata

Everything is in the simulator's canonical world (metres, ``+y`` up, ground ``y = 0``); the twin's
``world`` field holds the map back to the dataset's frame. "Refined" means the Gaussians after the
physics fit (groups X and A), not stage 0's ``stage0/gaussians.ply``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from toolkit.atomic import write_text
from toolkit.twin.format import TWIN_FORMAT, TWIN_SCHEMA, TWIN_VERSION, UNITS, DigitalTwin

__all__ = ["twin_from_module", "export_run", "write_sequence"]


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


@torch.no_grad()
def twin_from_module(module, source: Optional[dict] = None) -> DigitalTwin:
    """The digital twin of a fitted :class:`~toolkit.physics.InversePhysicsModule`.

    Stores exactly the float32 tensors the module simulates with (``x0 = particles0 + offset``,
    the physical material vector, v0, gravity, effect parameters), its simulator settings, grid and
    kept dt halvings, so re-simulating the twin with the fitted v0 gives the module's prediction.
    """
    from toolkit import __version__

    est = module.estimate()
    x0 = module.particles0 + module.particle_offset
    means0 = module.gaussian_means0 + module.gaussian_offset
    inp = module.input
    sim = module.simulator  # restores the checkpoint's grid and dt floor
    grid = sim.grid
    arrays = {
        "particles": _np(x0).astype(np.float32),
        "material_params": _np(module.material_params()).astype(np.float32),
        "effect_params": _np(module.effect_params).astype(np.float32).reshape(-1),
        "gaussian_means": _np(means0).astype(np.float32),
        "gaussian_log_scales": _np(module.log_scales).astype(np.float32),
        "gaussian_quats": _np(module.quats).astype(np.float32),
        "gaussian_opacity_logits": _np(module.opacity_logits).astype(np.float32),
        "embed_index": _np(module.embed_index).astype(np.int64),
        "embed_weight": _np(module.embed_weight).astype(np.float32),
        "times": _np(inp.times).astype(np.float32),
        "camera_K": _np(inp.cameras.K).astype(np.float32),
        "camera_w2c": _np(inp.cameras.w2c).astype(np.float32),
    }
    if module.deform_index.numel():
        arrays["deform_index"] = _np(module.deform_index).astype(np.int64)
        arrays["deform_gradient"] = _np(module.deform_gradient).astype(np.float32)
    if module.sh is not None:
        arrays["gaussian_sh"] = _np(module.sh).astype(np.float32)
    else:
        arrays["gaussian_colors"] = _np(module.colors).astype(np.float32)
    cams = inp.cameras
    meta = {
        "format": TWIN_FORMAT,
        "version": TWIN_VERSION,
        "units": dict(UNITS),
        "material": {"name": module.material.registry_name or type(module.material).__name__,
                     "options": dict(module.material.options), "param_names": list(module.material.param_names)},
        "params": {k: float(v) for k, v in est["params"].items()},
        "v0": [float(v) for v in _np(module.v0).astype(np.float32)],
        "gravity": [float(v) for v in _np(module.gravity).astype(np.float32)],
        "effects": est["effects"],
        "effect_order": [e.name for e in sim.effects],
        "sim": module.sim_config.to_dict(),
        "grid": None if grid is None else {"origin": list(grid.origin), "dims": list(grid.dims), "dx": grid.dx},
        "substeps_floor": int(sim.substeps_floor),
        "n_train": int(inp.n_train),
        "renderer": module.renderer_name,
        "cameras": {"width": cams.width, "height": cams.height, "near": cams.near, "far": cams.far,
                    "train": [int(c) for c in inp.train_cameras]},
        "world": (inp.meta or {}).get("world"),
        "source": {"toolkit": f"projo4d {__version__}", "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                   **(source or {})},
    }
    twin = DigitalTwin(meta=meta, arrays=arrays)
    twin.validate("twin of the fitted module")
    return twin


def write_sequence(out_dir: str | Path, twin: DigitalTwin, positions: np.ndarray, means: np.ndarray,
                   deformations: Optional[np.ndarray] = None) -> list[Path]:
    """Per-frame PLY files: ``particles_XXX.ply`` ((N, 3) positions) and ``gaussians_XXX.ply`` (3DGS).

    Args:
        positions: (T, N, 3) particle positions, m.
        means: (T, G, 3) Gaussian centres, m (the rest of each Gaussian is the twin's).
        deformations: (T, G, 3, 3) the Gaussians' deformations when they deform: each frame's file
            then holds the deformed shapes as plain scales and rotations
            (:func:`renderers.base.bake_deformation`), which any 3DGS viewer reads.
    """
    from renderers.torch_reference import bake_deformation
    from toolkit.data.ply import write_ply_points
    from toolkit.scene.export import save_ply
    from toolkit.twin.simulate import twin_gaussians

    out = Path(out_dir)
    written = []
    for t in range(len(positions)):
        written.append(write_ply_points(out / f"particles_{t:03d}.ply", positions[t]))
        A = None if deformations is None else torch.as_tensor(deformations[t])
        written.append(save_ply(out / f"gaussians_{t:03d}.ply",
                                bake_deformation(twin_gaussians(twin, torch.as_tensor(means[t]), deformation=A))))
    return written


def export_run(run: str | Path, out: Optional[str | Path] = None, sequence: bool = True, device: str = "cpu") -> dict:
    """Export a fitted run folder (see the module docstring); returns ``{"twin": path, ...}``.

    The per-frame sequence is the run's stored prediction (``evaluation/prediction.npz``) when there
    is one, else the twin simulated over the run's frames.
    """
    from toolkit.pipeline import load_fitted_module
    from toolkit.scene.export import save_ply
    from toolkit.twin.simulate import simulate_twin, twin_deformations, twin_gaussians

    run = Path(run)
    if not run.is_dir():
        raise FileNotFoundError(f"{run}: no such run folder")
    out = Path(out) if out is not None else run / "export"
    module = load_fitted_module(run, device=device)
    twin = twin_from_module(module, source={"run": str(run.resolve())})
    files = {"twin": twin.save(out / "twin.npz")}
    write_text(out / "twin.json", json.dumps(twin.meta, indent=2, sort_keys=True) + "\n")
    write_text(out / "twin.schema.json", json.dumps(TWIN_SCHEMA, indent=2) + "\n")
    files["gaussians"] = save_ply(out / "gaussians.ply", twin_gaussians(twin))
    if sequence:
        pred = run / "evaluation" / "prediction.npz"
        if pred.is_file():
            with np.load(pred) as z:
                positions, means = z["positions"], z["means"]
        else:
            traj = simulate_twin(twin, device=device)
            positions, means = traj.positions.numpy(), traj.means.numpy()
        deform = twin_deformations(twin, torch.as_tensor(positions))
        seq = write_sequence(out / "sequence", twin, positions, means, None if deform is None else deform.numpy())
        files["sequence"] = out / "sequence"
        files["sequence_files"] = len(seq)
    return files

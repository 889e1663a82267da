"""Load a fitted :class:`~toolkit.physics.InversePhysicsModule` from a run folder or a checkpoint.

A pipeline run folder holds ``physics_input.pt`` (the stage-0 output) and ``physics/`` with
``checkpoints/last.ckpt`` and ``estimate.json``. The module is rebuilt from the checkpoint's
hyper-parameters (``material``, ``material_options``, ``curriculum`` as a schedule string,
``sim`` as a dict, and every other constructor argument that was saved), then its state dict
is loaded and its checkpoint hook restores the simulation grid.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Optional

import torch

__all__ = ["load_fitted_module", "run_paths"]


def run_paths(run_dir: str | Path) -> tuple[Path, Path]:
    """``(physics_input.pt, last.ckpt)`` of a run folder.

    Raises:
        FileNotFoundError: naming the missing file and the expected layout.
    """
    run = Path(run_dir)
    inp = run / "physics_input.pt"
    ckpt = run / "physics" / "checkpoints" / "last.ckpt"
    for p, what in ((inp, "the physics input written after stage 0"), (ckpt, "the physics stage's last checkpoint")):
        if not p.is_file():
            raise FileNotFoundError(
                f"{p} does not exist ({what}); a run folder holds physics_input.pt and physics/checkpoints/last.ckpt"
            )
    return inp, ckpt


def load_fitted_module(run_dir: Optional[str | Path] = None, *, input_path: Optional[str | Path] = None,
                       checkpoint: Optional[str | Path] = None, device: str = "cpu"):
    """A fitted module from a run folder, or from an input file and a checkpoint.

    Args:
        run_dir: a run folder (``physics_input.pt`` + ``physics/checkpoints/last.ckpt``).
        input_path: the physics input (``.pt``) when not using ``run_dir`` (or a
            :class:`~toolkit.physics.PhysicsInput`).
        checkpoint: the checkpoint when not using ``run_dir``.
        device: torch device to put the module on.

    Returns:
        The :class:`~toolkit.physics.InversePhysicsModule` with the checkpoint's parameters.
    """
    from toolkit.mpm import SimConfig
    from toolkit.physics import InversePhysicsModule

    if run_dir is not None:
        input_path, checkpoint = run_paths(run_dir)
    if input_path is None or checkpoint is None:
        raise ValueError("give a run folder, or both input_path and checkpoint")
    ckpt = torch.load(str(checkpoint), map_location="cpu", weights_only=False)
    hp = dict(ckpt.get("hyper_parameters", {}))
    accepted = set(inspect.signature(InversePhysicsModule.__init__).parameters) - {"self", "input_path"}
    kwargs = {k: v for k, v in hp.items() if k in accepted}
    kwargs.setdefault("fit_ranges", "valid")  # runs saved before fit ranges existed had none
    if isinstance(kwargs.get("sim"), dict):
        sim = dict(kwargs["sim"])
        if sim.get("domain") is not None:
            sim["domain"] = tuple(tuple(c) for c in sim["domain"])
        kwargs["sim"] = SimConfig(**sim)
    module = InversePhysicsModule(input_path, **kwargs)
    module.load_state_dict(ckpt["state_dict"])
    module.on_load_checkpoint(ckpt)
    return module.to(device)

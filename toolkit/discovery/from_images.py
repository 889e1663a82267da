"""Discovery from images: the geometry comes from stage 0 and is held still in the physics stages.

The oracle workflow (:meth:`~toolkit.discovery.hidden.HiddenScene.physics_input`) starts the
physics from the *true* body. A user has only images: stage 0 (4D Gaussians) gives the
geometry, the particle continuum fills it, and the base model is fitted to that. Two rules make
discovery on such a geometry trustworthy:

1. **Positions stay out of the physics stages** (no ``X`` group): with free positions the
   body reshapes itself to imitate a missing effect (on the full-size hidden-friction scene the
   box grew from 7 to 14 cm tall and friction went unnamed). The base fit here uses
   :data:`STAGE0_CURRICULA` (``AS`` then ``ASM``); discovery refits only a rigid shift of the
   body (``shift.x|y|z``), which cannot change its shape.
2. **Stage 0's geometric uncertainty is carried** (:func:`geometry_floor`): the base model's
   misfit at frame 0, where every candidate starts from the same state and no missing effect
   has acted yet, is the part of each validation loss that comes from the stage-0 geometry and
   appearance, not from the physics. The validation improvements are measured against the
   loss *plus* that floor (:func:`toolkit.discovery.workflow.validation_components`), so a
   candidate that only absorbs a small geometry mismatch is not named.

:func:`stage0_physics_input` runs stage 0 and the continuum through the pipeline's own
:func:`toolkit.pipeline.build_physics_input` (resumable: a finished ``physics_input.pt`` is
reused, so every candidate of a scene shares one stage-0 run), then applies the hidden scene's
observation errors (:meth:`~toolkit.discovery.hidden.HiddenScene.observe`).

A camera-pose error reaches stage 0 as a user's would (:func:`observed_scene`, since
2026-11-27): the wrong camera is written into the scene that stage 0 reads, so stage 0 fits its
geometry to it, and the physics input inherits it from there. Before, the error was applied to
the physics input only, and stage 0 had seen the true camera. A timing error is still applied to
the physics input only, because stage 0 orders frames by index and does not read their times.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import numpy as np

__all__ = ["STAGE0_CURRICULA", "STAGE0_SCHEDULES", "observed_scene", "stage0_physics_input", "fit_base_from_images", "geometry_floor"]

#: base-fit curricula without the position group ``X``, per hidden-scene size (the oracle
#: curricula of :data:`toolkit.discovery.hidden.SIZES` with ``X`` removed)
STAGE0_CURRICULA = {"tiny": "AS:20@3,ASM:80", "full": "AS:60@3,ASM:300"}

#: stage-0 schedules per hidden-scene size (:attr:`toolkit.run_settings.RunSettings.stage0`). The
#: ``tiny`` preset as such diverged on the tiny slide (32 px, 3 fitted cameras, the box moving
#: 6 cm a frame): the deformation sent the Gaussians metres away from frame 1 on, no Gaussian
#: centre was covered in every view and the continuum had no surface after frame 0. With the
#: deformation learning rate lowered 4x (8e-4 -> 8e-5) and the frames introduced over 300
#: iterations instead of 170, every training frame has a surface (80-89 points; 32 s on one core).
STAGE0_SCHEDULES: dict[str, Union[str, dict]] = {
    "tiny": {"preset": "tiny", "deform_lr_init": 8e-4, "deform_lr_final": 8e-5, "frame_curriculum": 300},
    "full": "full",
}


def observed_scene(hs, scene_root: Union[str, Path], out: Union[str, Path], cameras="sparse") -> Path:
    """The scene as a user with the hidden scene's camera-pose error has it on disk.

    For a ``camera_pose`` scene, ``out`` gets the scene's files as symbolic links, except
    ``all_data.json``. That file is rewritten with the perturbed fitted camera's centre moved by
    the hidden shift, in metres in the scene's world frame: ``c2w[:3, 3] += e``, the same change
    :meth:`~toolkit.discovery.hidden.HiddenScene.observe` makes to a physics input. For every
    other effect, ``scene_root`` itself is returned unchanged.

    Args:
        hs: the :class:`~toolkit.discovery.hidden.HiddenScene`.
        scene_root: the generated scene (PAC-NeRF layout: ``all_data.json``, images named
            ``r_<camera>_<frame>.png``).
        out: folder for the observed scene; links already there are kept and
            ``all_data.json`` is written atomically, so a call on a finished run changes nothing.
        cameras: the fitting cameras, as in :attr:`toolkit.run_settings.RunSettings.cameras`.

    Returns:
        The folder that stage 0 should read.
    """
    import json

    from toolkit.atomic import write_json
    from toolkit.data.datamodule import resolve_cameras
    from toolkit.data.layout import load_scene
    from toolkit.data.pac_nerf import camera_and_frame
    from toolkit.discovery.hidden import PERTURBED_CAMERA

    root = Path(scene_root)
    if hs.effect != "camera_pose":
        return root
    camera = resolve_cameras(load_scene(root), cameras)[PERTURBED_CAMERA]
    shift = np.asarray(hs.truth_strengths_vector(), dtype=np.float64)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for f in root.iterdir():
        link = out / f.name
        if f.name != "all_data.json" and not link.exists():
            link.symlink_to(f.resolve())
    entries = json.loads((root / "all_data.json").read_text())
    moved = 0
    for e in entries:
        cf = camera_and_frame(e["file_path"])
        if cf is not None and cf[0] == camera:
            e["c2w"][0][3] += float(shift[0])
            e["c2w"][1][3] += float(shift[1])
            e["c2w"][2][3] += float(shift[2])
            moved += 1
    if not moved:
        raise ValueError(f"{root / 'all_data.json'}: no image of camera {camera} (expected files named r_{camera}_<frame>.png)")
    write_json(out / "all_data.json", entries, indent=None)
    return out


def stage0_physics_input(hs, scene_root: Union[str, Path], run_dir: Union[str, Path], stage0: Union[str, dict, None] = None,
                         cameras="sparse", device: str = "cpu", seed: int = 0):
    """The :class:`~toolkit.physics.PhysicsInput` of a hidden scene built from its images.

    Args:
        hs: the :class:`~toolkit.discovery.hidden.HiddenScene`.
        scene_root: the generated scene (images, cameras; its ground truth is used only for
            the scores, never for the geometry).
        run_dir: run folder; ``run_dir/stage0``, ``run_dir/continuum`` and
            ``run_dir/physics_input.pt`` are written, and reused when present.
        stage0: the stage-0 schedule (``"tiny"``, ``"full"`` or a dict, as
            :attr:`toolkit.run_settings.RunSettings.stage0`); default :data:`STAGE0_SCHEDULES` of
            the scene's size.
        cameras: fitting cameras (``"sparse"``: 3 of the scene's cameras; the others are
            held out and judge the candidates).
        device: ``cpu`` or ``cuda``.
        seed: stage 0's seed.

    Returns:
        The physics input with the scene's observation errors applied and the hidden truth in
        ``ground_truth["hidden_effect"]`` (``meta["source"] == "stage0"``).
    """
    from toolkit.discovery.hidden import SIZES
    from toolkit.physics.inputs import PhysicsInput
    from toolkit.pipeline import RunSettings, build_physics_input

    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    dx = float(SIZES[hs.size]["fit"]["dx"])
    stage0 = STAGE0_SCHEDULES[hs.size] if stage0 is None else stage0
    scene = observed_scene(hs, scene_root, run / "observed_scene", cameras)
    settings = RunSettings(scene=str(scene), out=str(run), stage0=stage0, geometry="stage0", cameras=cameras,
                           sim={"dx": dx}, device=device, seed=seed, renderer="auto")
    path = build_physics_input(settings, run, {})
    return hs.observe(PhysicsInput.load(path), cameras_observed=scene != Path(scene_root))


def fit_base_from_images(inp, out_dir: Union[str, Path], hs, accelerator: str = "cpu", curriculum: Optional[str] = None):
    """The base model fitted to a stage-0 input with the particle positions held still
    (:data:`STAGE0_CURRICULA`; see :func:`toolkit.discovery.hidden.fit_base`)."""
    from toolkit.discovery.hidden import fit_base

    return fit_base(inp, out_dir, material=hs.material, size=hs.size, accelerator=accelerator,
                    curriculum=curriculum or STAGE0_CURRICULA[hs.size])


def geometry_floor(lib, q: np.ndarray, cams_held_out: list[int], all_cams: list[int]) -> dict[str, float]:
    """Stage 0's geometric uncertainty as a loss floor per validation component.

    At frame 0 every refit (base or candidate) starts from the same body, so what remains of
    the loss there is the geometry/appearance mismatch of stage 0, not missing physics. Returns
    ``{"held_out_cameras": image loss of the held-out cameras at frame 0, "held_out_frames":
    image loss of every camera at frame 0, "held_out_surfaces": Chamfer (m^2, as
    :func:`toolkit.metrics.geometry.chamfer_loss`) of the body to the stage-0 surface at frame 0}``,
    computed at the library parameters ``q`` (the fitted base). Components without data are left out.
    """
    from toolkit.metrics.geometry import chamfer_loss

    out: dict[str, float] = {}
    if cams_held_out:
        out["held_out_cameras"] = float(lib.image_losses(q, [0], cams_held_out).mean())
    out["held_out_frames"] = float(lib.image_losses(q, [0], all_cams).mean())
    if lib.module.lambda_geometry > 0 and len(lib.input.surfaces[0]):
        x0, pos = lib.trajectory(q, [0])
        out["held_out_surfaces"] = float(chamfer_loss(pos[0][lib.module.surface_index], lib.input.surfaces[0].to(pos.device)))
    return out

"""The settings of one run (:func:`toolkit.pipeline.run_pipeline`), with their checks.

Kept apart from the pipeline so that a command can build and check its settings without
importing torch, Lightning or Warp: a mistake a user can see without the scene's contents (a
folder that does not exist, a bad field) is reported in a fraction of a second
(:meth:`RunSettings.check_fields`), the rest before any work (:meth:`RunSettings.validate`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Union

__all__ = ["RunSettings"]


@dataclass
class RunSettings:
    """Settings of :func:`toolkit.pipeline.run_pipeline`.

    Attributes:
        scene: scene folder (any supported layout, see :func:`toolkit.data.load_scene`).
        out: run folder.
        material: registered material name; ``material_options`` its options.
        initial_params: starting guesses (default: the material's defaults, GIC's guesses).
        optimize_params: material parameters to optimize (default: those the material marks).
        curriculum: strategy name, schedule string (``progressive`` is ProJo4D) or the import path
            of a :class:`~strategies.Strategy` subclass (``my_pkg.module.MyStrategy``).
        curriculum_options: options of a named strategy (e.g. ``{"stage2_iterations": 60}``).
        cameras: fitting cameras: ``"sparse"`` (1-based 2, 6, 10), ``"all"`` or 0-based indices.
        n_train: training frames (default: the scene's split, else min(14, T)).
        downscale: integer image downscale factor.
        stage0: ``"full"`` (GIC: 40k iterations), ``"tiny"`` (tests, demo) or a dict of
            :class:`toolkit.scene.stage0_schedule.Stage0Schedule` fields (plus ``preset``: the network and
            initialization preset they modify, default ``"full"``).
        geometry: ``"stage0"`` (the method) or ``"oracle"`` (ground-truth geometry, for ablations).
        sim: :class:`toolkit.mpm.SimConfig` fields for the physics stages.
        continuum: :class:`toolkit.scene.continuum.ContinuumConfig` fields (default: a lattice at
            ``sim.dx / 2``).
        lambda_geometry: weight of the geometric loss.
        optimize_gravity: learn gravity too (group S; ProJo4D does for the Spring-Gaus real
            capture). Gravity starts from the scene's world (canonical frame), or ``sim.gravity``.
        learning_rates: overrides of the physics learning rates.
        model_options: the other :class:`~toolkit.physics.InversePhysicsModule` arguments
            (``effects``, ``v0_init``, ``lambda_image``, ``ssim_weight``, ``warmup_fraction``,
            ``embedding_neighbours``), passed to the module as given (``None``: its defaults;
            see :mod:`toolkit.run_config`).
        renderer: renderer name or ``"auto"``.
        device: ``"auto"``, ``"cpu"`` or ``"cuda"``.
        checkpoint_every: physics iterations between checkpoints.
        report_cameras: cameras shown in the video (default: two fitted and two held-out ones).
        seed: seed of stage 0 and of the batch sampling.
        refine_grid: when the estimate depends on the grid (the grid check fails, or the uncertainty's
            grid term moves a fitted material parameter by more than its standard deviation;
            :func:`toolkit.grid_refinement.refinement_reason`), fit again at half the
            grid spacing in ``out/refined`` from the estimate, sharing stage 0
            (:mod:`toolkit.grid_refinement`); the summary's ``refined`` holds that run's summary.
            ``"auto"`` (default): on a CUDA device only, where it costs 1.4-3.4x the physics
            stage (more the fuller the card; 8x on CPU); ``True``: on any device; ``False``: never;
            ``"always"``: every fit whose grid check ran, whatever it found, on any device.
        refine_iterations: the refined fit runs each stage of the curriculum for this fraction of
            its iterations, in (0, 1] (it starts at the estimate;
            :func:`toolkit.grid_refinement.refined_curriculum`).
        threads: CPU threads of this run (torch intra-/inter-op, OpenMP, BLAS), on CPU and CUDA
            alike. ``None``: ``PROJO4D_THREADS`` if set, else the affinity-mask cores divided by
            ``PROJO4D_CONCURRENT_RUNS`` (runs sharing the machine, default 1), at most 8 on CUDA
            and 1 on a CPU device (see :mod:`toolkit.threads`). Set it (or those variables) when
            starting several runs on one machine yourself.
    """

    scene: str
    out: str = "runs/run"
    material: str = "neo_hookean"
    material_options: dict = field(default_factory=dict)
    initial_params: Optional[dict] = None
    optimize_params: Optional[list[str]] = None
    curriculum: str = "progressive"
    curriculum_options: dict = field(default_factory=dict)
    cameras: Union[str, list[int]] = "sparse"
    n_train: Optional[int] = None
    downscale: int = 1
    stage0: Union[str, dict] = "full"
    geometry: str = "stage0"
    sim: dict = field(default_factory=dict)
    continuum: dict = field(default_factory=dict)
    lambda_geometry: float = 1.0
    optimize_gravity: bool = False
    learning_rates: Optional[dict] = None
    model_options: Optional[dict] = None  # None, not {}: run folders recorded before the field keep their identity
    renderer: str = "auto"
    device: str = "auto"
    checkpoint_every: int = 50
    report_cameras: Optional[list[int]] = None
    seed: int = 0
    threads: Optional[int] = None
    refine_grid: bool | str = "auto"
    refine_iterations: float = 1.0

    def check_fields(self) -> None:
        """The checks that need neither the scene's contents nor torch: the thread count, the
        module options, ``refine_grid``, the scene folder's existence and the plain fields, in the
        order :meth:`validate` makes them (so the first mistake is the same one either way).

        Raises:
            toolkit.run_validation.SettingsError: naming the field, the value and what is valid.
        """
        from toolkit.run_validation import check_plain_fields

        self._check_options()
        check_plain_fields(self)

    def validate(self) -> dict:
        """Check every setting against the scene before any work (nothing is written).

        Raises:
            toolkit.run_validation.SettingsError: naming the field, the value and what is valid.
        """
        from toolkit.run_validation import validate_run_settings

        self._check_options()
        return validate_run_settings(self)  # the plain fields first, then the scene's contents

    def _check_options(self) -> None:
        from toolkit.run_config import check_model_options
        from toolkit.run_validation import SettingsError, check_refine_iterations

        if self.threads is not None:  # needs no scene: checked first
            from toolkit.threads import parse_count

            parse_count(self.threads, "RunSettings.threads (--threads)")
        check_model_options(self.model_options)
        if not (isinstance(self.refine_grid, bool) or self.refine_grid in ("auto", "always")):
            raise SettingsError("refine_grid", self.refine_grid, "true, false, 'auto' or 'always'")
        check_refine_iterations(self.refine_iterations)

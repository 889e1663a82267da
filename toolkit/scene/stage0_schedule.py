"""Stage 0's schedule: iterations, learning rates, loss weights and densification settings.

:class:`Stage0Schedule` holds GIC's full schedule as its defaults; :meth:`Stage0Schedule.full`
adds this project's changes (frame curriculum, silhouette anchor, Gaussian cap),
:meth:`Stage0Schedule.tiny` is the CPU-sized one and :meth:`Stage0Schedule.compressed` scales
every iteration count to a shorter run. Used by :class:`toolkit.scene.stage0.Gaussians4DModule`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from toolkit.scene.gaussian_model import DensificationConfig
from toolkit.settings import DictSettings

__all__ = ["Stage0Schedule", "compressed_settings", "ITERATION_COUNT_FIELDS", "FULL_FRAME_CURRICULUM", "FULL_LAMBDA_ANCHOR",
           "FULL_GAUSSIANS_PER_OBSERVED_PIXEL"]


#: the fields of :class:`Stage0Schedule` that count iterations (scaled by :meth:`Stage0Schedule.compressed`)
ITERATION_COUNT_FIELDS = ("warmup", "position_lr_max_steps", "deform_lr_max_steps", "densify_from", "densify_until",
                          "densify_interval", "opacity_reset_interval", "sh_increase_interval", "frame_curriculum")

#: :meth:`Stage0Schedule.full`'s frame curriculum: the first third of GIC's dynamic phase (37k iterations)
FULL_FRAME_CURRICULUM = 12_300
#: :meth:`Stage0Schedule.full`'s silhouette-anchor weight (:mod:`toolkit.scene.silhouette_anchor`)
FULL_LAMBDA_ANCHOR = 1.0
#: :meth:`Stage0Schedule.full`'s cap: one Gaussian per observed object pixel
FULL_GAUSSIANS_PER_OBSERVED_PIXEL = 1.0


@dataclass
class Stage0Schedule(DictSettings):
    settings_name = "Stage0Schedule settings"

    """Iterations, learning rates, loss weights and densification settings of stage 0.

    Iteration numbers follow GIC's 1-based convention: iteration ``it = step + 1``.

    Attributes:
        iterations: Total iterations (GIC 40k).
        warmup: Static iterations on frame 0 before the deformation is used (GIC 3k).
        position_lr_init, position_lr_final, position_lr_max_steps: Exponential decay of the
            canonical positions' lr (GIC 1.6e-4 x 5 -> 1.6e-6 x 5 over 30k).
        deform_lr_init, deform_lr_final, deform_lr_max_steps: Same for the deformation network
            (GIC: same values over 40k).
        feature_lr: lr of the SH DC coefficients (GIC 2.5e-3); higher bands use 1/20 of it.
        opacity_lr: lr of the opacity logits (GIC 0.1; 3DGS 0.05).
        scaling_lr: lr of the log-scales (GIC 1e-3 x 5).
        rotation_lr: lr of the quaternions (GIC 1e-3; anisotropic Gaussians only).
        lambda_dssim: SSIM weight λ (0.2).
        lambda_alpha: Weight of the alpha-mask L1 (GIC ``reg_alpha``: 1).
        lambda_scale: Weight of the mean scale (metres) after the warm-up (GIC ``reg_scale``: 10).
        lambda_anchor: Weight of the silhouette anchor after the warm-up
            (:mod:`toolkit.scene.silhouette_anchor`; GIC: none): the projected mean of the
            Gaussians is drawn toward each mask's centroid, so a frame the deformation carried off
            the object still has a gradient back. 0 (GIC) turns it off; :meth:`full` and
            :meth:`tiny` use 1.
        anchor_tolerance: The anchor's dead zone, as a fraction of the image size.
        densify_from, densify_until, densify_interval: Densify at iterations ``it`` with
            ``densify_from < it < densify_until`` and ``it % densify_interval == 0``.
        opacity_reset_interval: Reset opacities at multiples of this after the warm-up (and
            before ``densify_until``); screen-size pruning starts after the first interval.
        sh_increase_interval: One more active SH degree every this many iterations.
        frame_curriculum: Iterations after the warm-up during which the frames drawn grow from
            the first one to all training frames (frames ``[0, w)`` with ``w`` rising linearly);
            0 (GIC) draws from all frames at once. Helps when the motion is larger than the
            object: far frames then do not overlap the undeformed Gaussians, and their offsets
            can overshoot out of every view and be lost.
        gaussians_per_observed_pixel: Cap on the number of Gaussians, per object pixel the
            training views observe (mask > 0.5, summed over every training frame and fitting
            camera); 0 (GIC) leaves the count to the gradient threshold. :meth:`full` uses 1:
            more Gaussians than observed object pixels cannot be told apart by the images, and
            every physics iteration renders them all. The cap also bounds the initial count and
            combines with ``densification.max_gaussians`` (the smaller wins).
        ground: Gaussians the deformation puts below the dataset's ground plane are rendered on it
            (the views' ``ground``; a projection whose gradient passes straight through, so the
            images can still lift them). The training cameras look down at the object, so nothing
            in the images stops a deformed body from sinking into the ground once it lands: without
            this (GIC, the default), small-size models put 6-34 % of their opaque Gaussians up to
            5-10 cm below it in the last training frame. Opt-in: on three small fits it moved the
            torus's E by +0.1 decade (with a worse future), the sand letter T's friction angle by
            0.3 degrees toward the truth and left the apple's E
            (``docs/results/continuum_volume.md``); the continuum's ``ground_clip`` (default) removes
            what lies below the ground either way.
        densification: Thresholds (:class:`DensificationConfig`).
        log_every: Log losses every this many iterations (each log is a host synchronization).
    """

    iterations: int = 40_000
    warmup: int = 3_000
    position_lr_init: float = 1.6e-4 * 5
    position_lr_final: float = 1.6e-6 * 5
    position_lr_max_steps: int = 30_000
    deform_lr_init: float = 1.6e-4 * 5
    deform_lr_final: float = 1.6e-6 * 5
    deform_lr_max_steps: int = 40_000
    feature_lr: float = 2.5e-3
    opacity_lr: float = 0.1
    scaling_lr: float = 1e-3 * 5
    rotation_lr: float = 1e-3
    lambda_dssim: float = 0.2
    lambda_alpha: float = 1.0
    lambda_scale: float = 10.0
    lambda_anchor: float = 0.0
    anchor_tolerance: float = 0.02
    densify_from: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    opacity_reset_interval: int = 3_000
    sh_increase_interval: int = 1_000
    frame_curriculum: int = 0
    gaussians_per_observed_pixel: float = 0.0
    ground: bool = False
    densification: DensificationConfig = field(default_factory=DensificationConfig)
    log_every: int = 100

    def __post_init__(self) -> None:
        self.densification = DensificationConfig.from_dict(self.densification)
        if self.iterations < 1 or self.warmup < 0:
            raise ValueError(f"iterations must be >= 1 and warmup >= 0, got {self.iterations}, {self.warmup}")
        if self.densify_interval < 1 or self.opacity_reset_interval < 1 or self.sh_increase_interval < 1:
            raise ValueError("densify_interval, opacity_reset_interval and sh_increase_interval must be >= 1")
        if not isinstance(self.ground, bool):
            raise ValueError(f"stage 0 ground must be true or false, got {self.ground!r}")
        for name in ("frame_curriculum", "lambda_anchor", "anchor_tolerance", "gaussians_per_observed_pixel"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")

    @classmethod
    def full(cls) -> "Stage0Schedule":
        """GIC's schedule for full-size scenes (the defaults), with three changes: the frames of the
        dynamic phase are introduced in time order over its first third
        (``frame_curriculum`` = :data:`FULL_FRAME_CURRICULUM`; GIC draws from all frames at once),
        the silhouette anchor is on (``lambda_anchor`` = :data:`FULL_LAMBDA_ANCHOR`), and the
        number of Gaussians is capped at one per observed object pixel
        (``gaussians_per_observed_pixel`` = :data:`FULL_GAUSSIANS_PER_OBSERVED_PIXEL`).

        Without it the deformation lost the object on fast throws: at 96 px and 2500 iterations
        (:meth:`compressed`), 12 of the 30 sliding-box scenes of the discovery benchmark fell to
        25-28 dB right after the warm-up and stayed there, with their Gaussians carried metres out
        of every view (the black background alone scores about 27 dB); 3 of them left the
        continuum empty. On two of them the curriculum alone still lost the last three frames;
        with the anchor no frame was lost (``docs/limits.md``, "Stage 0 losing the object").

        Without the cap the same 96 px scenes, whose object covers about 90 pixels a view,
        grew 27k-104k Gaussians, 100-400 per observed pixel, and every physics iteration
        rendered them all (no base fit finished in 17 minutes on a CPU core)."""
        return cls(frame_curriculum=FULL_FRAME_CURRICULUM, lambda_anchor=FULL_LAMBDA_ANCHOR,
                   gaussians_per_observed_pixel=FULL_GAUSSIANS_PER_OBSERVED_PIXEL)

    @classmethod
    def tiny(cls) -> "Stage0Schedule":
        """A CPU-sized schedule (tests, demo): 600 iterations, 80 of them static warm-up, on
        48-64 px images with 1000-2500 Gaussians (about 35 s on one CPU core at 64 px).
        Learning rates are raised (x4 for positions and the deformation network, x4 for colours)
        and decay 10x over the run, so the short run converges; densification runs every 40
        iterations until about halfway through the dynamic phase (GIC: until 15k of 40k) and is
        capped at 2500 Gaussians; no opacity reset (recovering from one takes thousands of
        iterations). The frames of the dynamic phase are introduced progressively over its first
        third (``frame_curriculum``): drawing far frames from the start made Adam overshoot their
        offsets in some runs until those frames left every view (1 run in 4 on the test scene),
        after which no gradient could bring them back. The silhouette anchor is on
        (``lambda_anchor`` 1, as in :meth:`full`): without it, a 64 px scene imaged as particle
        discs with mask noise lost frames 2-6 that way even with the curriculum; with it, no
        frame of 12 CPU scenes was lost (``docs/results/paper_size.md``)."""
        return cls(
            iterations=600,
            warmup=80,
            position_lr_init=3.2e-3,
            position_lr_final=3.2e-4,
            position_lr_max_steps=600,
            deform_lr_init=3.2e-3,
            deform_lr_final=3.2e-4,
            deform_lr_max_steps=600,
            feature_lr=1e-2,
            opacity_lr=0.05,
            scaling_lr=5e-3,
            densify_from=40,
            densify_until=320,
            densify_interval=40,
            opacity_reset_interval=100_000,
            sh_increase_interval=100_000,
            frame_curriculum=170,
            lambda_anchor=FULL_LAMBDA_ANCHOR,
            densification=DensificationConfig(grad_threshold=1.5e-4, max_gaussians=2500),
            log_every=50,
        )

    @classmethod
    def compressed(cls, iterations: int) -> "Stage0Schedule":
        """:meth:`full`'s schedule with every iteration count (:data:`ITERATION_COUNT_FIELDS`: warm-up,
        learning-rate decay lengths, densification window and interval, opacity resets, SH steps,
        frame curriculum)
        scaled by ``iterations / 40_000``; rates, thresholds and loss weights unchanged.
        ``compressed(40_000) == full()``. Counts round to the nearest iteration, at least 1.
        ``projo4d run --stage0-iterations N`` and ``projo4d benchmark --stage0-iterations N`` use it
        (through :func:`compressed_settings`; a cheaper, less converged stage 0:
        ``benchmarks/whole_scene.py`` measures the trade, issue #16).

        Raises:
            ValueError: ``iterations`` is not an integer >= 100.
        """
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 100:
            raise ValueError(f"iterations must be an integer >= 100, got {iterations!r}")
        base = cls.full()
        f = iterations / base.iterations
        scaled = {key: max(1, int(round(getattr(base, key) * f))) if getattr(base, key) else 0 for key in ITERATION_COUNT_FIELDS}
        return cls(**{**base.to_dict(), "iterations": iterations, **scaled})

    @classmethod
    def defaults(cls) -> "Stage0Schedule":
        return cls.full()


def compressed_settings(iterations: int) -> dict:
    """:meth:`Stage0Schedule.compressed` as a ``RunSettings.stage0`` mapping: ``preset`` "full",
    ``iterations``, the scaled :data:`ITERATION_COUNT_FIELDS`, the anchor weight and the Gaussian cap (so that the
    mapping alone, without the preset, gives the same schedule).

    Raises:
        ValueError: ``iterations`` is not an integer >= 100.
    """
    schedule = Stage0Schedule.compressed(iterations)
    return {"preset": "full", "iterations": schedule.iterations,
            **{key: getattr(schedule, key) for key in ITERATION_COUNT_FIELDS}, "lambda_anchor": schedule.lambda_anchor,
            "gaussians_per_observed_pixel": schedule.gaussians_per_observed_pixel}

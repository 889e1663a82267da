"""Rough wall-time estimates of benchmark jobs, refined by the jobs that finish.

The model counts the work of each job (stage-0 iterations x image size; physics iterations x
simulated frames x substeps; rendered views; EMD assignments) and prices it with a
:class:`DeviceProfile`. The CUDA profile's prices come from the measurements in ``docs/limits.md``
(Warp MPM at 10^4-10^5 particles: about 0.1 ms per forward substep, forward + backward 4-8x
that; Warp rasterizer about 0.5 ms per 400x400 view forward + backward) plus guesses for the
per-iteration overhead and for stage 0 (no measured number yet): treat the first estimates as
order-of-magnitude. Once jobs finish, :class:`Calibration` rescales the estimates of each job kind
(``generate``, ``prepare``, ``fit:<strategy>``) by the measured / estimated ratio of the finished
ones, also across reruns (the markers keep both numbers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

__all__ = ["DeviceProfile", "PROFILES", "Calibration", "estimate_job", "scene_info", "format_seconds", "simulate_schedule",
           "sharing_slowdown", "SHARING_OVERLAP", "refinement_estimate", "fit_may_refine"]


@dataclass(frozen=True)
class DeviceProfile:
    """Prices (seconds) of the units of work on one worker.

    Attributes:
        startup: process start, imports, kernel-cache loading, reading the inputs.
        stage0_base, stage0_per_mpix: one stage-0 iteration: fixed part and per megapixel.
        continuum: building the particle continuum.
        substep_base, substep_per_kparticle: one forward MPM substep (fixed, per 1000 particles).
        backward_factor: forward + backward cost / forward cost of a differentiated rollout.
        view_per_mpix: rendering one view forward + backward with its loss, per megapixel.
        iteration_overhead: per physics iteration (Lightning, logging, optimizers).
        emd_frame: one exact EMD (2048 points) and Chamfer distance.
        image_metric_per_mpix: PSNR + SSIM of one image, per megapixel.
        generate_per_frame: simulating and rendering one frame of a synthetic scene (all cameras).
        refine_factor: a fit refined at half the grid spacing (``--refine-grid``) costs this many
            times the first fit's work. Measured on CUDA: a full-size sand fit alone on an H200, 4.1x
            (the whole refit: physics 579 s after 143 s; half the curriculum: 325 s after 154 s,
            rounds 33-34 of ``docs/results/paper_size.md``); 1.8-3.4x, mean 2.7x, with five fits
            sharing an H200, whose first fits did not fill it and whose refined fits did; 1.4x with
            two sharing an H100. About 8x on 2 CPU cores (``docs/limits.md``). The CUDA profile takes
            the fit alone on the card, as ``projo4d run`` and ``--jobs-per-gpu 1`` run it.
    """

    name: str
    startup: float
    stage0_base: float
    stage0_per_mpix: float
    continuum: float
    substep_base: float
    substep_per_kparticle: float
    backward_factor: float
    view_per_mpix: float
    iteration_overhead: float
    emd_frame: float
    image_metric_per_mpix: float
    generate_per_frame: float
    refine_factor: float = 4.0


PROFILES: dict[str, DeviceProfile] = {
    # one H200 (the H100 is close): stage 0 at 400x400 measured 6-10 ms per static and 10-27 ms per dynamic
    # iteration (20k-100k Gaussians, benchmarks/stage0_speed.py); MPM forward 43 us per substep at 10.6k
    # particles, 64 us at 32.8k, 141 us at 97k, forward + backward 4.5-6x that (benchmarks/mpm_throughput.py);
    # the rest (per-iteration overhead, rendering, startup, generation) are estimates
    "cuda": DeviceProfile("cuda", startup=25.0, stage0_base=0.008, stage0_per_mpix=0.04, continuum=30.0,
                          substep_base=3.8e-5, substep_per_kparticle=0.9e-6, backward_factor=5.0, view_per_mpix=3.5e-3,
                          iteration_overhead=0.012, emd_frame=0.4, image_metric_per_mpix=0.1, generate_per_frame=3.0),
    # 2 shared cores, one torch thread per worker (tests, tutorials)
    "cpu": DeviceProfile("cpu", startup=8.0, stage0_base=0.02, stage0_per_mpix=8.0, continuum=5.0,
                         substep_base=2.0e-4, substep_per_kparticle=4.0e-4, backward_factor=3.0, view_per_mpix=2.0,
                         iteration_overhead=0.01, emd_frame=0.35, image_metric_per_mpix=0.5, generate_per_frame=0.5,
                         refine_factor=8.0),
}

#: seconds per history record written into each physics checkpoint (the history grows with the fit)
CHECKPOINT_PER_RECORD = 2e-5


_SCENE_CACHE: dict[str, dict] = {}


def scene_info(path: str, generate_spec: Optional[dict] = None) -> dict:
    """``n_frames``, ``n_cameras``, ``width``, ``height``, ``n_train`` of a scene (or of a spec to generate)."""
    if generate_spec is not None:
        s = generate_spec
        return {"n_frames": s["n_frames"], "n_cameras": s["n_cameras"], "width": s["width"], "height": s["height"],
                "n_train": s.get("n_train_frames") or max(1, min(14, s["n_frames"] - 1))}
    if path not in _SCENE_CACHE:
        from toolkit.data import load_scene
        from toolkit.pipeline import training_frames

        scene = load_scene(path)
        _SCENE_CACHE[path] = {"n_frames": scene.n_frames, "n_cameras": scene.n_cameras, "width": scene.width,
                              "height": scene.height, "n_train": training_frames(scene, None)}
    return _SCENE_CACHE[path]


def _stages(settings: dict, material: str):
    from toolkit.pipeline import resolve_curriculum

    return resolve_curriculum(settings["curriculum"], settings.get("curriculum_options")).stages(material)


def _stage0_iterations(spec) -> int:
    if spec == "tiny":
        return 600
    if spec == "full":
        return 40_000
    if isinstance(spec, dict):
        return int(spec.get("iterations") or (600 if spec.get("preset") == "tiny" else 40_000))
    return 40_000


def estimate_job(job: dict, info: dict, profile: DeviceProfile, n_particles: Optional[int] = None) -> float:
    """Model estimate (seconds) of one job (a :meth:`~toolkit.benchmark.plan.Job.to_dict`).

    Args:
        job: the job.
        info: :func:`scene_info` of its scene.
        profile: prices of the device.
        n_particles: simulation particles when known (from the finished ``prepare`` job).
    """
    p = profile
    s = job.get("settings", {})
    downscale = int(s.get("downscale") or 1)
    mpix = (info["width"] // downscale) * (info["height"] // downscale) / 1e6
    T, n_train, C = info["n_frames"], info["n_train"], info["n_cameras"]
    if job["kind"] == "generate":
        spec = s["spec"]
        full_mpix = spec["width"] * spec["height"] / 1e6
        return p.startup + T * p.generate_per_frame * max(1.0, full_mpix / 0.16) + C * T * 0.01
    if job["kind"] == "variant":  # read, perturb and write every image once
        return p.startup + C * T * 0.02 * max(1.0, mpix / 0.16)
    if job["kind"] == "prepare":
        if s.get("geometry") == "oracle":
            return p.startup + C * T * 0.002 + 2.0
        its = _stage0_iterations(s.get("stage0", "full"))
        return p.startup + its * (p.stage0_base + p.stage0_per_mpix * mpix) + p.continuum + C * T * 0.005
    # fit
    sim = s.get("sim") or {}
    substeps = int(sim.get("substeps", 100))
    n = n_particles or (1500 if mpix < 0.02 else 15000)
    substep = p.substep_base + p.substep_per_kparticle * n / 1000.0
    total = p.startup
    try:
        stages = _stages(s, job["material"])
    except Exception:  # noqa: BLE001 - an unknown strategy fails later with a clear error
        stages = []
    n_evals = 0
    for st in stages:
        window = st.window(n_train)
        frames = min(st.frames_per_step or window, window)
        cams = min(st.cameras_per_step or 3, C)
        sim_cost = 0.0 if not (st.groups & {"X", "S", "M"}) else window * substeps * substep * p.backward_factor
        views = cams * frames if "image" in st.losses else 0
        total += st.iterations * (sim_cost + views * p.view_per_mpix * mpix + p.iteration_overhead)
        pe = job.get("extra", {}).get("periodic_eval")
        n_evals += 1 + (int(pe.get("per_stage", 8)) if pe is not None and not pe.get("every_n_steps") else 0)
    rollout = T * substeps * substep
    future = max(1, T - n_train)
    pe = job.get("extra", {}).get("periodic_eval")
    if pe is not None:
        emd = p.emd_frame * (0.15 if pe.get("emd_points", 2048) <= 1024 else 1.0)
        total += n_evals * (rollout + (future + 1) * emd + future * p.view_per_mpix * mpix)
    iters = sum(st.iterations for st in stages)
    every = max(1, int(job.get("extra", {}).get("checkpoint_every") or s.get("checkpoint_every") or 50))
    total += iters * iters / (2 * every) * CHECKPOINT_PER_RECORD
    # final evaluation: rollout, CD/EMD per frame, every camera rendered and scored
    total += rollout + T * p.emd_frame + C * T * (p.view_per_mpix / 3 + p.image_metric_per_mpix) * mpix + 5.0
    return total


def fit_may_refine(job: dict, profile: DeviceProfile) -> bool:
    """Whether a fit job refits at half the grid spacing when its estimate depends on the grid
    (:func:`toolkit.grid_refinement.refinement_reason`): its
    ``refine_grid`` setting is true, or ``auto`` (the default) on a CUDA profile
    (:func:`toolkit.grid_refinement.refines_on`)."""
    from toolkit.grid_refinement import refines_on

    return job.get("kind") == "fit" and refines_on(job.get("settings", {}).get("refine_grid", "auto"), profile.name)


def refinement_estimate(job: dict, info: dict, profile: DeviceProfile, n_particles: Optional[int] = None) -> float:
    """Model estimate (seconds) of the refined fit a fit job adds when it refines (0 when
    it cannot refine, :func:`fit_may_refine`): the fit's work again, times ``profile.refine_factor``
    and the job's ``refine_iterations`` (the fraction of the curriculum the refit runs; the process,
    its start-up and stage 0 are shared)."""
    if not fit_may_refine(job, profile):
        return 0.0
    fraction = float(job.get("settings", {}).get("refine_iterations", 1.0))
    return max(0.0, estimate_job(job, info, profile, n_particles) - profile.startup) * profile.refine_factor * fraction


class Calibration:
    """Per job kind, the ratio of measured to modelled wall time of the finished jobs."""

    def __init__(self) -> None:
        self._sums: dict[str, list[float]] = {}

    @staticmethod
    def kind_of(job: dict) -> str:
        return f"fit:{job.get('strategy')}" if job["kind"] == "fit" else job["kind"]

    def add(self, job: dict, measured_s: Optional[float], model_s: Optional[float]) -> None:
        if not measured_s or not model_s or measured_s <= 0 or model_s <= 0:
            return
        m = self._sums.setdefault(self.kind_of(job), [0.0, 0.0])
        m[0] += measured_s
        m[1] += model_s

    def ratio(self, job: dict) -> Optional[float]:
        m = self._sums.get(self.kind_of(job))
        if m:
            return m[0] / m[1]
        if job["kind"] == "fit":  # another strategy's fits say something about this one's
            fits = [v for k, v in self._sums.items() if k.startswith("fit:")]
            if fits:
                return sum(v[0] for v in fits) / sum(v[1] for v in fits)
        return None

    def apply(self, job: dict, model_s: float) -> tuple[float, str]:
        r = self.ratio(job)
        return (model_s * r, "calibrated") if r is not None else (model_s, "model")


def format_seconds(s: Optional[float]) -> str:
    if s is None or not math.isfinite(s):
        return "?"
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


#: how much of one more job's work a shared GPU absorbs: with k jobs sharing it, it does
#: ``1 + overlap (k - 1)`` jobs' worth of work at once. Fits (long differentiated rollouts in separate
#: processes, which time-slice the GPU) measured 0.07: over the 124 fits of the committed paper-size
#: rounds that shared a GPU, fits took their alone model times 1.9 (2 a GPU), 2.4 (3), 2.8 (4), 3.8 (5),
#: 5.6 (6) and 5.4 (7) (medians; ``benchmarks/estimate_check.py`` over the event logs), and with 0.07
#: the estimates' median error is 1.01x (10-90 %: 0.74-1.43x; with the earlier guess of 0.6, 2.43x).
#: Generation and stage 0 keep 0.6: their prices were set on runs that already shared the GPUs, and
#: they measure 0.5-1.9x their estimates with it.
SHARING_OVERLAP = {"fit": 0.07, "other": 0.6}


def sharing_slowdown(jobs_per_gpu: int, kind: str = "other") -> float:
    """How much longer one job of ``kind`` (``"fit"`` or any other job kind) takes when
    ``jobs_per_gpu`` jobs share a GPU: ``k / (1 + overlap (k - 1))`` with the measured
    :data:`SHARING_OVERLAP` of its kind."""
    k = max(1, int(jobs_per_gpu))
    overlap = SHARING_OVERLAP["fit" if kind == "fit" else "other"]
    return k / (1.0 + overlap * (k - 1))


def simulate_schedule(jobs: list[dict], seconds: dict[str, float], capacity: int, done: set[str] = frozenset()) -> float:
    """Wall time of running ``jobs`` (with their ``depends``) on ``capacity`` workers, taking each
    ready job in the runner's order (generate, prepare, fit; then planning order) as a worker frees.

    Args:
        jobs: job dicts in planning order.
        seconds: job id -> estimated seconds.
        capacity: workers.
        done: ids already finished.
    """
    import heapq

    kind_rank = {"generate": 0, "variant": 0, "prepare": 1, "fit": 2}
    order = {j["id"]: i for i, j in enumerate(jobs)}
    finished_at = {jid: 0.0 for jid in done}
    pending = [j for j in jobs if j["id"] not in done]
    running: list[tuple[float, str]] = []
    now = 0.0
    while pending or running:
        ready = [j for j in pending if all(d in finished_at and finished_at[d] <= now for d in j.get("depends", []))]
        ready.sort(key=lambda j: (kind_rank.get(j["kind"], 9), order[j["id"]]))
        while ready and len(running) < capacity:
            j = ready.pop(0)
            pending.remove(j)
            heapq.heappush(running, (now + seconds.get(j["id"], 0.0), j["id"]))
        if not running:
            break  # blocked (a dependency outside the list)
        now, jid = heapq.heappop(running)
        finished_at[jid] = now
    return now

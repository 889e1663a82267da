"""``discover(...)``: localize, rank, confirm, decide, add the effect and show the gap shrink.

The steps (each in its own module):

1. **Localize** (:mod:`~toolkit.discovery.residuals`): per-frame, per-region, rigid/non-rigid
   and per-camera residuals of the fitted base model.
2. **Rank** (:mod:`~toolkit.discovery.ranking`): a projected score test of every candidate at
   zero strength, plus a small search for the wall and plastic yield; on the *refit frames*
   (the training frames minus the last ``holdout_frames``).
3. **Confirm** (:mod:`~toolkit.discovery.confirm`): short Levenberg-Marquardt refits of the
   ``top_k`` candidates with the base parameters refitted too (smooth forces as a family: air
   drag with the extra acceleration, and on a slide ground friction), and of the base alone
   (the control), on the refit frames; each is scored on data the refits did not use: the
   held-out cameras on the refit frames, every camera and the stage-0 surfaces on the held-out
   training frames.
4. **Decide** (:mod:`~toolkit.discovery.selection`, :mod:`~toolkit.discovery.calibration`): a
   physics candidate is discovered when its validation improvement over the control, less a
   penalty per extra strength parameter, and its training improvement pass thresholds
   calibrated on null scenes; candidates within the criterion's noise of the winner are all
   named, with the observation that would separate them
   (:mod:`~toolkit.discovery.separation`); a camera-pose error (a control, narrowed to one
   camera by :mod:`~toolkit.discovery.camera`) is reported as an observation problem, never as
   physics. With a stage-0 geometry the validation losses carry stage 0's floor
   (:mod:`~toolkit.discovery.from_images`); candidates whose score test an undetermined base
   parameter absorbed are confirmed too (:mod:`~toolkit.discovery.joint`).
5. **Add and show the gap** (:mod:`~toolkit.discovery.gap`): the winner is refitted on every
   training frame; future-frame Chamfer/EMD/PSNR and the held-out-camera loss before and
   after (and for the true effect, when the scene's ground truth names one).
6. **Report** (:mod:`~toolkit.discovery.report`): Markdown and HTML with figures.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np

from toolkit.discovery.calibration import DEFAULT_THRESHOLDS, Thresholds
from toolkit.discovery.candidates import ELASTIC_MATERIALS, library
from toolkit.discovery.confirm import Refit, lm_refit
from toolkit.discovery.gap import evaluate_state, gap_shrink, ground_truth_clouds
from toolkit.discovery.kinematics import body_force_partners, law_sentence, observed_motion, preferred_candidates
from toolkit.discovery.library import LibraryModel
from toolkit.discovery.ranking import Ranking, rank_candidates
from toolkit.discovery.refits import final_refit, refit_candidate
from toolkit.discovery.residuals import Localization, localize
from toolkit.discovery.selection import (camera_judged, criterion_noise, decide, passes, penalized, relative_improvements,
                                        validation_components)

__all__ = ["DiscoveryResult", "discover", "decide", "refit_frames", "truth_from_ground_truth", "validation_components"]

log = logging.getLogger(__name__)


@dataclass
class DiscoveryResult:
    """Everything :func:`discover` found.

    Attributes:
        verdict: one sentence.
        decision: the discovered candidate, or ``None`` ("no missing effect").
        decision_kind: ``physics``, ``observation`` (camera-pose control) or ``none``.
        indistinguishable: candidates the data cannot tell apart from the decision.
        localization: where the base model and the measurements disagree.
        ranking: the projected score test of every candidate.
        refits: the confirmation refits (``base`` is the control), on the refit frames.
        validation: per refit, the validation components, their relative improvements over the
            control, ``validation`` (their mean), ``fit`` (training improvement), ``passed``.
        final: the decision refitted on every training frame (``None`` without a decision).
        truth_refit: the true candidate refitted likewise, when the ground truth names one that
            differs from the decision.
        metrics: ``before`` (the fitted base model), ``after`` (:attr:`final`), ``truth``
            (:attr:`truth_refit`): :func:`~toolkit.discovery.gap.evaluate_state` outputs.
        gap: the headline numbers: future CD/EMD/PSNR and held-out loss before and after, and the
            fraction of the future Chamfer gap removed (``cd_shrink``).
        params: base parameters (physical) ``before`` and ``after``, and ``truth`` when known.
        thresholds: the decision thresholds used.
        truth: the hidden effect from the ground truth (``candidate``, ``strengths``), if known.
        holdout_frames: the training frames held out from the confirmation refits.
        seconds: wall-clock time per step.
        floors: stage 0's geometric uncertainty per validation component (empty for an oracle
            geometry; :func:`toolkit.discovery.from_images.geometry_floor`).
        separation: per candidate tied with the decision, the observation that would separate
            them (:func:`toolkit.discovery.separation.separating_observation`).
        joint: candidates confirmed because an undetermined base parameter absorbed their score
            test, and that parameter (:mod:`toolkit.discovery.joint`).
        noise: ``{a: {b: standard error}}`` of the difference of two refits' validation
            improvements (:func:`toolkit.discovery.selection.criterion_noise`).
        motion: the observed centroid over the clip's first phase (a flight or a slide) and its
            shape (:meth:`toolkit.discovery.kinematics.ObservedMotion.to_dict`), ``None``
            without enough frames.
        silhouettes: whether the fitted cameras' masks agree
            (:func:`toolkit.discovery.camera.silhouette_check`; ``suspect``: a camera they contradict).
        lib, plastic_lib: the library models (not serialized).
    """

    verdict: str
    decision: Optional[str]
    decision_kind: str
    indistinguishable: list[str]
    localization: Localization
    ranking: Ranking
    refits: dict[str, Refit]
    validation: dict[str, dict]
    final: Optional[Refit]
    truth_refit: Optional[Refit]
    metrics: dict[str, dict]
    gap: dict[str, Any]
    params: dict[str, Any]
    thresholds: Thresholds
    truth: Optional[dict]
    holdout_frames: list[int]
    seconds: dict[str, float] = field(default_factory=dict)
    floors: dict[str, float] = field(default_factory=dict)
    separation: list[dict] = field(default_factory=list)
    joint: dict[str, str] = field(default_factory=dict)
    noise: dict[str, dict[str, float]] = field(default_factory=dict)
    motion: Optional[dict] = None
    silhouettes: Optional[dict] = None
    lib: Optional[LibraryModel] = field(default=None, repr=False)
    plastic_lib: Optional[LibraryModel] = field(default=None, repr=False)

    @property
    def identified(self) -> Optional[bool]:
        """Whether the decision equals what the ground truth expects (``None`` without truth)."""
        if not self.truth or "expected" not in self.truth:
            return None
        return self.decision == self.truth["expected"]

    def to_dict(self) -> dict:
        """JSON-ready dict (``nan`` becomes ``None``)."""
        d = {
            "verdict": self.verdict, "decision": self.decision, "decision_kind": self.decision_kind,
            "indistinguishable": self.indistinguishable, "localization": self.localization.to_dict(),
            "ranking": self.ranking.to_dict(), "refits": {k: v.to_dict() for k, v in self.refits.items()},
            "validation": self.validation, "final": None if self.final is None else self.final.to_dict(),
            "truth_refit": None if self.truth_refit is None else self.truth_refit.to_dict(), "metrics": self.metrics,
            "gap": self.gap, "params": self.params, "thresholds": self.thresholds.to_dict(), "truth": self.truth,
            "identified": self.identified, "holdout_frames": self.holdout_frames, "seconds": self.seconds,
            "floors": self.floors, "separation": self.separation, "joint": self.joint,
            "noise": self.noise, "motion": self.motion, "silhouettes": self.silhouettes,
        }
        return _clean(d)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        from toolkit.atomic import write_json

        return write_json(path, self.to_dict())

    def to_module(self):
        """The base module with the discovered effect added, as a new
        :class:`~toolkit.physics.InversePhysicsModule` at the refitted parameters (see
        :func:`toolkit.discovery.export.module_with_effect`); ``None`` without a physics decision
        or for candidates the module cannot express (``timing``, ``stiffness_gradient``)."""
        from toolkit.discovery.export import module_with_effect

        if self.decision is None or self.decision_kind != "physics" or self.final is None:
            return None
        return module_with_effect(self.final)


def _clean(x):
    if isinstance(x, float):
        return None if (math.isnan(x) or math.isinf(x)) else x
    if isinstance(x, (np.floating,)):
        return _clean(float(x))
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def truth_from_ground_truth(gt: Optional[dict], base_material: str) -> Optional[dict]:
    """The hidden effect a scene's ground truth names, in library terms, or ``None`` when unknown.

    Uses ``gt["hidden_effect"]`` when present (scenes of :mod:`toolkit.discovery.hidden`);
    otherwise infers it from the ground-truth effects with a non-zero strength, a plastic
    truth material under an elastic base, or a non-zero ``damping``. Returns
    ``{"candidate": name or None, "strengths": {...}, "expected": name or None}``.
    """
    if not gt:
        return None
    if gt.get("hidden_effect"):
        h = dict(gt["hidden_effect"])
        h.setdefault("expected", h.get("candidate"))
        return h
    for name, vals in (gt.get("effects") or {}).items():
        strength = {"ground_friction": ["mu"], "air_drag": ["linear", "quadratic"], "extra_acceleration": ["ax", "ay", "az"],
                    "wall": ["strength"]}.get(name, [])
        if any(abs(float(vals.get(s, 0.0))) > 0 for s in strength):
            return {"candidate": name, "strengths": {f"{name}.{s}": float(vals[s]) for s in strength if s in vals},
                    "expected": name}
    if gt.get("material") == "plasticine" and base_material in ELASTIC_MATERIALS:
        tau = float(gt.get("params", {}).get("yield_stress", 0.0))
        return {"candidate": "plastic_yield", "strengths": {"plastic_yield.log10_yield_stress": math.log10(tau)} if tau > 0 else {},
                "expected": "plastic_yield"}
    if float((gt.get("params") or {}).get("damping", 0.0)) > 0:
        return {"candidate": "internal_damping", "strengths": {"internal_damping.eta": float(gt["params"]["damping"])},
                "expected": "internal_damping"}
    if gt.get("material") is not None and gt.get("material") == base_material:
        return {"candidate": None, "strengths": {}, "expected": None}
    return None


def refit_frames(n_train: int, holdout_frames: Optional[int] = None) -> tuple[list[int], list[int]]:
    """The confirmation's split of the training frames ``[0, n_train)``: ``(refit frames, held-out
    frames)``, the last ``holdout_frames`` held out (default a quarter, at least 1 with 4 or more
    training frames, none with fewer); at least 2 frames stay for the refits."""
    H = holdout_frames if holdout_frames is not None else (max(1, round(n_train / 4)) if n_train >= 4 else 0)
    H = int(min(max(H, 0), max(n_train - 2, 0)))
    return list(range(n_train - H)), list(range(n_train - H, n_train))


def discover(source, out_dir: Optional[str | Path] = None, *, candidates: Optional[Sequence[str]] = None, top_k: int = 4,
             holdout_frames: Optional[int] = None, refit_iterations: int = 8, final_iterations: int = 12,
             thresholds: Union[Thresholds, str, Path, None] = None, report: bool = True, emd: bool = True,
             device: Optional[str] = None, geometry_floor: Optional[bool] = None) -> DiscoveryResult:
    """Find, name and add the missing effect of a fitted base model.

    Args:
        source: a fitted :class:`~toolkit.physics.InversePhysicsModule`, or a run folder
            (``physics_input.pt`` + ``physics/checkpoints/last.ckpt``).
        out_dir: where ``discovery.json``, ``report.md``, ``report.html``, the figures and, for a
            physics decision, ``discovered.yaml`` (:func:`toolkit.discovery.export.save_config`) go
            (nothing is written when ``None``).
        candidates: candidate names (default: the whole library).
        top_k: candidates confirmed by refits, best ranked first; searched candidates (wall,
            plastic yield) with a positive score are confirmed in addition.
        holdout_frames: training frames held out from the confirmation (default: a quarter of
            the training frames, at least 1 when there are 4 or more).
        refit_iterations: Levenberg-Marquardt iterations of each confirmation refit.
        final_iterations: iterations of the final refit on every training frame.
        thresholds: :class:`~toolkit.discovery.calibration.Thresholds` or a JSON file; default
            :data:`~toolkit.discovery.calibration.DEFAULT_THRESHOLDS`.
        report: write the Markdown/HTML report (with ``out_dir``).
        emd: compute the EMD in the before/after metrics.
        device: device for a module loaded from a run folder.
        geometry_floor: carry stage 0's geometric uncertainty as a floor under the validation
            losses (:func:`toolkit.discovery.from_images.geometry_floor`); default: when the
            input's geometry comes from stage 0 (``input.meta["source"] == "stage0"``).

    Returns:
        The :class:`DiscoveryResult`.
    """
    from toolkit.physics import InversePhysicsModule

    t_start = time.time()
    if isinstance(source, InversePhysicsModule):
        module = source
    else:
        from toolkit.discovery.loading import load_fitted_module

        module = load_fitted_module(source, device=device or "cpu")
    if thresholds is None:
        thr = DEFAULT_THRESHOLDS
    elif isinstance(thresholds, Thresholds):
        thr = thresholds
    else:
        thr = Thresholds.load(thresholds)
    seconds: dict[str, float] = {}
    inp = module.input
    base_name = module.material.registry_name or type(module.material).__name__
    truth = truth_from_ground_truth(inp.ground_truth, base_name)

    # ------------------------------------------------------------------ 1. localize
    t = time.time()
    lib = LibraryModel(module, candidates)
    lib.calibrate_geometry_weight(lib.q0)
    loc = localize(lib)
    from toolkit.discovery.camera import silhouette_check

    silhouettes = silhouette_check(inp)
    suspect = (silhouettes or {}).get("suspect")
    suspect = suspect if suspect in inp.train_cameras else None
    floors = None
    if geometry_floor if geometry_floor is not None else (inp.meta or {}).get("source") == "stage0":
        from toolkit.discovery.from_images import geometry_floor as _floor

        floors = _floor(lib, lib.q0, list(inp.held_out_cameras), list(range(len(inp.cameras))))
    seconds["localize"] = time.time() - t
    log.info("localization: %s", loc.summary)

    # ------------------------------------------------------------------ 2. rank
    t = time.time()
    n_train = inp.n_train
    fit_frames, val_frames = refit_frames(n_train, holdout_frames)
    lib.fit_frames = fit_frames
    plib = None
    if "plastic_yield" in {c.name for c in library(candidates)} and base_name in ELASTIC_MATERIALS:
        e = lib.physical(lib.q0)["params"].get("E", 1e4)
        plib = LibraryModel(module, candidates, plastic=math.log10(e) - 2.0, geometry_weight=lib.geometry_weight)
        plib.fit_frames = fit_frames
    ranking, state = rank_candidates(lib, plastic_lib=plib)
    motion = observed_motion(lib, lib.q0)
    seconds["rank"] = time.time() - t
    log.info("ranking: %s", ", ".join(f"{s.name} {s.score:.3g}" for s in ranking.scores))

    # ------------------------------------------------------------------ 3. confirm
    t = time.time()
    refits: dict[str, Refit] = {"base": lm_refit(lib, lib.q0, lib.base_names, "base", iterations=refit_iterations)}
    chosen = [s for s in ranking.scores if s.score > 0][:top_k]
    # a searched candidate's score only sees the base trajectory (a wall it does not reach
    # scores zero): any searched candidate with a positive score is confirmed as well
    chosen += [s for s in ranking.scores if s.search is not None and s.score > 0 and s not in chosen]
    # a score test made inconclusive by a base parameter the clip does not determine: refit jointly
    from toolkit.discovery.joint import absorbed_candidates, undetermined_base

    undetermined = undetermined_base(getattr(module, "uncertainty_result", None), lib.base_names)
    joint = absorbed_candidates(ranking, state, lib, undetermined, [s.name for s in chosen])
    chosen += [ranking.get(n) for n in joint]
    # a base fit that absorbed a drag (a slower throw) scores it near zero: smooth forces are
    # confirmed as a family, and the validation decides between a drag, a constant pull, friction
    chosen += [ranking.get(n) for n in body_force_partners([s.name for s in chosen], ranking.names,
                                                           None if motion is None else motion.phase)]
    if suspect is not None and "camera_pose" in ranking.names and "camera_pose" not in {s.name for s in chosen}:
        chosen.append(ranking.get("camera_pose"))  # the masks contradict a camera: confirm the control on it
    for s in chosen:
        refits[s.name] = refit_candidate(lib, plib, state, s, refits["base"], refit_iterations, motion=motion)
    if "camera_pose" in refits:  # narrowed to the one camera that carries the improvement
        from toolkit.discovery.camera import single_camera_refit

        refits["camera_pose"] = single_camera_refit(lib, refits["base"], refits["camera_pose"], refit_iterations,
                                                    camera=suspect)
    seconds["confirm"] = time.time() - t
    validation, noise = _validate(lib, refits, val_frames, ranking, thr, floors)

    # ------------------------------------------------------------------ 4. decide
    decision, kind, indist = decide(validation, {sc.name: sc.dof for sc in ranking.scores}, thr, noise=noise,
                                    single_camera=loc.single_camera if loc.single_camera in inp.train_cameras else None,
                                    prefer=preferred_candidates(motion, list(validation)), silhouette_suspect=suspect)
    separation = []
    if kind == "physics":
        from toolkit.discovery.separation import separating_observation

        for other in indist:
            try:
                separation.append(separating_observation(refits[decision], refits[other]))
            except Exception as exc:  # the advice must not break the discovery
                log.warning("separating %s from %s failed: %s", decision, other, exc)

    # ------------------------------------------------------------------ 5. add the effect, evaluate
    t = time.time()
    lib.fit_frames = list(range(n_train))
    if plib is not None:
        plib.fit_frames = list(range(n_train))
    final = None
    if decision is not None:
        final = final_refit(lib, plib, state, decision, refits[decision], final_iterations)
    truth_refit = None
    tc = truth.get("expected") if truth else None
    if tc is not None and tc != decision and tc in {c.name for c in lib.candidates} | ({"plastic_yield"} if plib else set()):
        try:
            seed_fit = refits.get(tc)
            if seed_fit is None:
                seed_fit = refit_candidate(lib, plib, state, ranking.get(tc), refits["base"], refit_iterations, motion) \
                    if tc in ranking.names else None
            if seed_fit is not None:
                truth_refit = final_refit(lib, plib, state, tc, seed_fit, final_iterations)
        except Exception as exc:  # the reference must not break the discovery
            log.warning("refit of the true candidate %s failed: %s", tc, exc)
    seconds["final"] = time.time() - t
    t = time.time()
    clouds = ground_truth_clouds(lib)
    metrics = {"before": evaluate_state(lib, lib.q0, clouds, emd=emd)}
    if final is not None:
        metrics["after"] = evaluate_state(final.lib, final.q, clouds, emd=emd)
    if truth_refit is not None:
        metrics["truth"] = evaluate_state(truth_refit.lib, truth_refit.q, clouds, emd=emd)
    seconds["evaluate"] = time.time() - t
    gap = _gap(metrics)
    params = {"before": lib.physical(lib.q0), "after": None if final is None else final.lib.physical(final.q)}
    if inp.ground_truth and inp.ground_truth.get("params"):
        params["truth"] = {"params": inp.ground_truth.get("params"), "v0": inp.ground_truth.get("v0")}
    verdict = _verdict(decision, kind, indist, final, gap, validation, loc, separation, refits, motion)
    if kind == "observation" and suspect is not None:
        verdict += f" The masks say so too: {silhouettes['message']}."
        if (inp.meta or {}).get("source") == "stage0":
            verdict += (" Stage 0 fitted the geometry to the same camera and absorbed part of the error, so the refitted "
                        "shift understates it: recalibrate that camera rather than apply the shift.")
    seconds["total"] = time.time() - t_start
    result = DiscoveryResult(verdict=verdict, decision=decision, decision_kind=kind, indistinguishable=indist, localization=loc,
                             ranking=ranking, refits=refits, validation=validation, final=final, truth_refit=truth_refit,
                             metrics=metrics, gap=gap, params=params, thresholds=thr, truth=truth, holdout_frames=val_frames,
                             seconds=seconds, lib=lib, plastic_lib=plib, floors=floors or {}, separation=separation,
                             joint=joint, noise=noise, motion=None if motion is None else motion.to_dict(),
                             silhouettes=silhouettes)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        result.save(out / "discovery.json")
        if kind == "physics" and final is not None:
            from toolkit.discovery.export import save_config

            try:  # the discovered model as a config `projo4d run/fit --config` replays
                save_config(final, out / "discovered.yaml", verdict)
            except Exception as exc:  # pragma: no cover - the config must not break the discovery
                log.warning("could not write %s: %s", out / "discovered.yaml", exc)
        if report:
            from toolkit.discovery.report import write_report

            write_report(result, out)
    return result


def _validate(lib: LibraryModel, refits: dict[str, Refit], val_frames: list[int], ranking: Ranking, thr: Thresholds,
              floors: Optional[dict[str, float]] = None) -> tuple[dict, dict]:
    """Validation statistics per refit (see :mod:`toolkit.discovery.selection`) and the criterion
    noise ``{a: {b: standard error}}`` between the refits."""
    cells: dict[str, dict] = {name: {} for name in refits}
    comps = {name: validation_components(rf.lib or lib, rf.q, val_frames, cells=cells[name]) for name, rf in refits.items()}
    base = comps["base"]
    out: dict[str, dict] = {}
    for name, rf in refits.items():
        # the stage-0 floor is what no force can change at frame 0; a camera pose changes frame 0 too
        rel = relative_improvements(base, comps[name], None if name == "camera_pose" else floors)
        fit = (refits["base"].objective - rf.objective) / max(refits["base"].objective, 1e-30)
        control = name != "base" and ranking.get(name).control
        dof = 0 if name == "base" else ranking.get(name).dof
        judged = camera_judged(rel, floors is not None) if name == "camera_pose" else rel
        mean = float(np.mean(list(judged.values()))) if judged else 0.0
        worst = float(min(judged.values())) if judged else 0.0
        v = {"control": control, "validation": mean, "fit": fit, "worst": worst, "dof": dof}
        if name == "camera_pose" and rf.extra and "concentration" in rf.extra:
            v["concentration"] = float(rf.extra["concentration"])
        actual = (refits["base"].objective - rf.objective) / max(ranking.objective, 1e-30)
        out[name] = {"components": comps[name], "relative": rel, "validation": mean, "worst": worst, "fit": float(fit),
                     "dof": dof, "penalized": penalized(mean, dof, thr.per_parameter), "actual_drop": float(actual),
                     "control": bool(control), "passed": bool(passes(name, v, thr)),
                     **({"concentration": v["concentration"]} if "concentration" in v else {})}
    names = [n for n in refits if n != "base"]
    noise = {a: {b: criterion_noise(cells, a, b, floors=floors) for b in names if b != a} for a in names}
    return out, noise


def _gap(metrics: dict) -> dict:
    b = metrics["before"]
    a = metrics.get("after", b)
    out = {}
    for key in ("cd_future", "emd_future", "psnr_future", "psnr_future_held_out", "held_out_loss_train", "held_out_loss_future"):
        out[f"{key}_before"] = b.get(key)
        out[f"{key}_after"] = a.get(key)
        if "truth" in metrics:
            out[f"{key}_truth_effect"] = metrics["truth"].get(key)
    out["cd_shrink"] = gap_shrink(b.get("cd_future"), a.get("cd_future"))
    out["emd_shrink"] = gap_shrink(b.get("emd_future"), a.get("emd_future"))
    out["held_out_shrink"] = gap_shrink(b.get("held_out_loss_future"), a.get("held_out_loss_future"))
    return out


def _verdict(decision, kind, indist, final, gap, validation, loc, separation=(), refits=None, motion=None) -> str:
    if decision is None:
        return ("No missing effect: no candidate improves the held-out data beyond what the null-scene calibration allows"
                + (f" ({loc.summary})." if loc.first_departure is not None else "."))
    if kind == "observation":
        from toolkit.discovery.camera import camera_shift_text

        where = camera_shift_text((refits or {}).get(decision), loc)
        return (f"The disagreement points at the observation, not the physics: a camera-pose error{where} "
                f"explains it (training objective -{100 * validation[decision]['fit']:.0f} %).")
    s = ", ".join(f"{k.split('.', 1)[1]} = {v:.3g}" for k, v in (final.strengths if final else {}).items())
    extra = f" (cannot be told apart from {', '.join(indist)})" if indist else ""
    shrink = gap.get("cd_shrink")
    tail = f"; the future Chamfer gap shrinks by {100 * shrink:.0f} %" if shrink is not None else ""
    sep = "".join(f" To separate {d['candidates'][0]} from {d['candidates'][1]}: {d['sentence']}" for d in separation)
    why = ""
    if indist and motion is not None and decision in preferred_candidates(motion, [decision]):
        bend = (f"smoothly, as a force acting in {'flight' if motion.phase == 'flight' else 'the slide'} does"
                if motion.shape == "smooth" else "abruptly, as a wall does")
        where = "flight before the first ground contact" if motion.phase == "flight" else "slide"
        why = (f" Chosen among them because the observed {where} (frames {motion.frames[0]}-{motion.frames[-1]}) "
               f"bends {bend}.")
        if motion.shape == "smooth" and motion.law != "either":
            why += law_sentence(motion.to_dict())
    return (f"Missing effect: {decision} ({s}){extra}, improving the held-out data by "
            f"{100 * validation[decision]['validation']:.0f} %{tail}.{why}{sep}")

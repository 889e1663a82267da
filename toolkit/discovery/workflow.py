"""``discover(...)``: localize, rank, confirm, decide, add the effect and show the gap shrink.

The steps (each in its own module):

1. **Localize** (:mod:`~toolkit.discovery.residuals`): per-frame, per-region, rigid/non-rigid
   and per-camera residuals of the fitted base model.
2. **Rank** (:mod:`~toolkit.discovery.ranking`): a projected score test of every candidate at
   zero strength, plus a small search for the wall and plastic yield; on the *refit frames*
   (the training frames minus the last ``holdout_frames``).
3. **Confirm** (:mod:`~toolkit.discovery.confirm`): short Levenberg-Marquardt refits of the
   ``top_k`` candidates with the base parameters refitted too, and of the base alone (the
   control), on the refit frames; each is scored on data the refits did not use: the held-out
   cameras on the refit frames, every camera and the stage-0 surfaces on the held-out training
   frames.
4. **Decide** (:mod:`~toolkit.discovery.calibration`): a physics candidate is discovered when
   its validation and training improvements over the control pass thresholds calibrated on
   null scenes; candidates within noise of the winner are reported as indistinguishable; a
   camera-pose error (a control) is reported as an observation problem, never as physics.
5. **Add and show the gap** (:mod:`~toolkit.discovery.gap`): the winner is refitted on every
   training frame; future-frame Chamfer/EMD/PSNR and the held-out-camera loss before and
   after (and for the true effect, when the scene's ground truth names one).
6. **Report** (:mod:`~toolkit.discovery.report`): Markdown and HTML with figures.
"""

from __future__ import annotations

import json
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
from toolkit.discovery.library import LibraryModel
from toolkit.discovery.ranking import Ranking, rank_candidates
from toolkit.discovery.residuals import Localization, localize

__all__ = ["DiscoveryResult", "discover", "decide", "truth_from_ground_truth", "validation_components"]

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
        }
        return _clean(d)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2))
        return path

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


def validation_components(lib: LibraryModel, q: np.ndarray, val_frames: Sequence[int]) -> dict[str, float]:
    """The validation losses of a refit: ``held_out_cameras`` (image loss of the held-out
    cameras on the refit frames), ``held_out_frames`` (image loss of every camera on
    ``val_frames``) and ``held_out_surfaces`` (Chamfer to the stage-0 surfaces on ``val_frames``)."""
    from toolkit.metrics.geometry import chamfer_loss

    inp = lib.input
    out: dict[str, float] = {}
    if inp.held_out_cameras:
        out["held_out_cameras"] = float(lib.image_losses(q, lib.fit_frames, inp.held_out_cameras).mean())
    if val_frames:
        out["held_out_frames"] = float(lib.image_losses(q, val_frames, list(range(len(inp.cameras)))).mean())
        if lib.module.lambda_geometry > 0:
            x0, pos = lib.trajectory(q, val_frames)
            vals = [float(chamfer_loss(pos[k][lib.module.surface_index], inp.surfaces[f].to(pos.device)))
                    for k, f in enumerate(val_frames) if len(inp.surfaces[f])]
            if vals:
                out["held_out_surfaces"] = float(np.mean(vals))
    return out


def _relative(base: dict[str, float], cand: dict[str, float]) -> dict[str, float]:
    return {k: (base[k] - cand[k]) / base[k] if base[k] > 0 else 0.0 for k in base if k in cand}


def discover(source, out_dir: Optional[str | Path] = None, *, candidates: Optional[Sequence[str]] = None, top_k: int = 4,
             holdout_frames: Optional[int] = None, refit_iterations: int = 8, final_iterations: int = 12,
             thresholds: Union[Thresholds, str, Path, None] = None, report: bool = True, emd: bool = True,
             device: Optional[str] = None) -> DiscoveryResult:
    """Find, name and add the missing effect of a fitted base model.

    Args:
        source: a fitted :class:`~toolkit.physics.InversePhysicsModule`, or a run folder
            (``physics_input.pt`` + ``physics/checkpoints/last.ckpt``).
        out_dir: where ``discovery.json``, ``report.md``, ``report.html`` and the figures go
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
    seconds["localize"] = time.time() - t
    log.info("localization: %s", loc.summary)

    # ------------------------------------------------------------------ 2. rank
    t = time.time()
    n_train = inp.n_train
    H = holdout_frames if holdout_frames is not None else (max(1, round(n_train / 4)) if n_train >= 4 else 0)
    H = int(min(max(H, 0), max(n_train - 2, 0)))
    fit_frames, val_frames = list(range(n_train - H)), list(range(n_train - H, n_train))
    lib.fit_frames = fit_frames
    plib = None
    if "plastic_yield" in {c.name for c in library(candidates)} and base_name in ELASTIC_MATERIALS:
        e = lib.physical(lib.q0)["params"].get("E", 1e4)
        plib = LibraryModel(module, candidates, plastic=math.log10(e) - 2.0, geometry_weight=lib.geometry_weight)
        plib.fit_frames = fit_frames
    ranking, state = rank_candidates(lib, plastic_lib=plib)
    seconds["rank"] = time.time() - t
    log.info("ranking: %s", ", ".join(f"{s.name} {s.score:.3g}" for s in ranking.scores))

    # ------------------------------------------------------------------ 3. confirm
    t = time.time()
    refits: dict[str, Refit] = {"base": lm_refit(lib, lib.q0, lib.base_names, "base", iterations=refit_iterations)}
    chosen = [s for s in ranking.scores if s.score > 0][:top_k]
    # a searched candidate's score only sees the base trajectory (a wall it does not reach
    # scores zero): any searched candidate with a positive score is confirmed as well
    chosen += [s for s in ranking.scores if s.search is not None and s.score > 0 and s not in chosen]
    for s in chosen:
        refits[s.name] = _refit_candidate(lib, plib, state, s, refits["base"], refit_iterations)
    seconds["confirm"] = time.time() - t
    validation = _validate(lib, refits, val_frames, ranking, thr)

    # ------------------------------------------------------------------ 4. decide
    decision, kind, indist = decide(validation, {sc.name: sc.dof for sc in ranking.scores}, thr)

    # ------------------------------------------------------------------ 5. add the effect, evaluate
    t = time.time()
    lib.fit_frames = list(range(n_train))
    if plib is not None:
        plib.fit_frames = list(range(n_train))
    final = None
    if decision is not None:
        final = _final_refit(lib, plib, state, decision, refits[decision], final_iterations)
    truth_refit = None
    tc = truth.get("expected") if truth else None
    if tc is not None and tc != decision and tc in {c.name for c in lib.candidates} | ({"plastic_yield"} if plib else set()):
        try:
            seed_fit = refits.get(tc)
            if seed_fit is None:
                seed_fit = _refit_candidate(lib, plib, state, ranking.get(tc), refits["base"], refit_iterations) \
                    if tc in ranking.names else None
            if seed_fit is not None:
                truth_refit = _final_refit(lib, plib, state, tc, seed_fit, final_iterations)
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
    verdict = _verdict(decision, kind, indist, final, gap, validation, loc)
    seconds["total"] = time.time() - t_start
    result = DiscoveryResult(verdict=verdict, decision=decision, decision_kind=kind, indistinguishable=indist, localization=loc,
                             ranking=ranking, refits=refits, validation=validation, final=final, truth_refit=truth_refit,
                             metrics=metrics, gap=gap, params=params, thresholds=thr, truth=truth, holdout_frames=val_frames,
                             seconds=seconds, lib=lib, plastic_lib=plib)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        result.save(out / "discovery.json")
        if report:
            from toolkit.discovery.report import write_report

            write_report(result, out)
    return result


def _start_point(lib: LibraryModel, base: Refit, score) -> np.ndarray:
    """The base refit with the candidate's strengths at the ranking's prediction, scaled back
    (1, 1/2, 1/4, 0) to the best objective: the linear prediction can overshoot."""
    best_q, best_L = base.q.copy(), base.objective
    for alpha in (1.0, 0.5, 0.25):
        q = base.q.copy()
        for n, v in score.predicted_strength.items():
            if n in lib.index_of:
                q[lib.index_of[n]] = alpha * v
        q = lib.clip(q)
        try:
            L = lib.objective(q)
        except Exception:  # a failing rollout: try a smaller step
            continue
        if L < best_L:
            best_q, best_L = q, L
    return best_q


def _refit_candidate(lib: LibraryModel, plib: Optional[LibraryModel], state: dict, score, base: Refit, iterations: int) -> Refit:
    """Confirmation refit of one candidate, from the base refit's parameters."""
    name = score.name
    if name == "plastic_yield":
        q = plib.q0.copy()
        q[plib.idx(plib.base_names)] = base.q[lib.idx(lib.base_names)]
        q[plib.index_of["plastic_yield.log10_yield_stress"]] = state["yield"]
        rf = lm_refit(plib, q, plib.base_names + ["plastic_yield.log10_yield_stress"], name, iterations=iterations)
        rf.extra = {"yield_stress": float(10 ** rf.q[plib.index_of["plastic_yield.log10_yield_stress"]])}
        return rf
    if name == "wall":
        k, offset = state["wall"]
        lib.set_wall(k, offset)
        q = base.q.copy()
        q[lib.index_of["wall.strength"]] = 1.0
        rf = lm_refit(lib, q, lib.base_names + ["wall.strength"], name, iterations=iterations)
        rf.extra = dict(score.search or {})
        return rf
    lib.assign(base.q)
    q = _start_point(lib, base, score)
    return lm_refit(lib, q, lib.base_names + lib.params_of(name), name, iterations=iterations)


def _final_refit(lib: LibraryModel, plib: Optional[LibraryModel], state: dict, name: str, seed: Refit, iterations: int) -> Refit:
    """The candidate refitted on every training frame from its confirmation refit."""
    target = seed.lib if seed.lib is not None else lib
    if name == "wall":
        k, offset = state["wall"]
        target.set_wall(k, offset)
    free = target.base_names + (target.params_of(name) if name != "plastic_yield" else ["plastic_yield.log10_yield_stress"])
    rf = lm_refit(target, seed.q, free, name, iterations=iterations)
    rf.extra = seed.extra
    if name == "plastic_yield":
        rf.extra = {"yield_stress": float(10 ** rf.q[target.index_of["plastic_yield.log10_yield_stress"]])}
    return rf


def _validate(lib: LibraryModel, refits: dict[str, Refit], val_frames: list[int], ranking: Ranking, thr: Thresholds) -> dict:
    comps = {name: validation_components(rf.lib or lib, rf.q, val_frames) for name, rf in refits.items()}
    base = comps["base"]
    out: dict[str, dict] = {}
    for name, rf in refits.items():
        rel = _relative(base, comps[name])
        fit = (refits["base"].objective - rf.objective) / max(refits["base"].objective, 1e-30)
        control = name != "base" and ranking.get(name).control
        mean = float(np.mean(list(rel.values()))) if rel else 0.0
        worst = float(min(rel.values())) if rel else 0.0
        passed = _passes(name, {"control": control, "validation": mean, "fit": fit, "worst": worst}, thr)
        actual = (refits["base"].objective - rf.objective) / max(ranking.objective, 1e-30)
        out[name] = {"components": comps[name], "relative": rel, "validation": mean, "worst": worst, "fit": float(fit),
                     "actual_drop": float(actual),
                     "control": bool(control), "passed": bool(passed)}
    return out


def decide(validation: dict, dofs: dict[str, int], thr: Thresholds) -> tuple[Optional[str], str, list[str]]:
    """``(decision, kind, indistinguishable)`` from the confirmation's validation statistics
    (:attr:`DiscoveryResult.validation`), the candidates' numbers of strength parameters and the
    thresholds, with the ``passed`` flags recomputed for ``thr``.

    The decision rule (see :mod:`toolkit.discovery.calibration`): among the candidates that
    pass, those within noise of the best validation improvement (``max(threshold, 20 %)`` of it)
    cannot be told apart; of those the one with the fewest strength parameters is chosen
    (parsimony), then the best validation."""
    passing = [n for n, v in validation.items() if _passes(n, v, thr)]
    if passing:
        best = max(validation[n]["validation"] for n in passing)
        tol = max(thr.validation, 0.2 * best)
        tied = [n for n in passing if best - validation[n]["validation"] < tol]
        win = min(tied, key=lambda n: (dofs.get(n, 1), -validation[n]["validation"]))
        return win, "physics", sorted((n for n in tied if n != win), key=lambda n: -validation[n]["validation"])
    cam = validation.get("camera_pose")
    if (cam is not None and cam["fit"] > thr.camera and cam["validation"] > thr.validation
            and cam["worst"] > -thr.max_worsening):
        return "camera_pose", "observation", []
    return None, "none", []


def _passes(name: str, v: dict, thr: Thresholds) -> bool:
    return (name != "base" and not v["control"] and v["validation"] > thr.validation and v["fit"] > thr.fit
            and v["worst"] > -thr.max_worsening)


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


def _verdict(decision, kind, indist, final, gap, validation, loc) -> str:
    if decision is None:
        return ("No missing effect: no candidate improves the held-out data beyond what the null-scene calibration allows"
                + (f" ({loc.summary})." if loc.first_departure is not None else "."))
    if kind == "observation":
        return (f"The disagreement points at the observation, not the physics: a camera-pose error of a fitted camera "
                f"explains it (training objective -{100 * validation[decision]['fit']:.0f} %).")
    s = ", ".join(f"{k.split('.', 1)[1]} = {v:.3g}" for k, v in (final.strengths if final else {}).items())
    extra = f" (cannot be told apart from {', '.join(indist)})" if indist else ""
    shrink = gap.get("cd_shrink")
    tail = f"; the future Chamfer gap shrinks by {100 * shrink:.0f} %" if shrink is not None else ""
    return (f"Missing effect: {decision} ({s}){extra}, improving the held-out data by "
            f"{100 * validation[decision]['validation']:.0f} %{tail}.")

"""Cheap ranking of the candidates: a projected score test at zero strength.

Method (a Gauss-Newton / Rao score test). Linearize the residual vector ``r`` of the base model
(:meth:`~toolkit.discovery.library_objectives.LibraryObjectives.residuals`) at the fitted base point ``q0``
(every strength zero) with a forward-difference Jacobian ``J = [J_theta, J_s]`` (base
parameters, candidate strengths; one rollout per column, in step units). Let ``P`` be the
orthogonal projector that removes the span of ``J_theta`` (the base parameters' directions,
from an SVD). Then

* ``r_perp = P r`` is the residual left after a Gauss-Newton refit of the base parameters
  alone, and ``J_perp = P J_s`` is what each strength can change that the base parameters
  cannot: a strength whose effect is mimicked by the base (density by E) has ``J_perp ~ 0``;
* a candidate ``c`` with strength columns ``S_c`` is scored by the loss drop it predicts when
  added and refitted together with the base parameters,
  ``drop_c = 0.5 (|r_perp|^2 - min_d |r_perp + J_perp[:, S_c] d|^2)`` with ``d`` inside the
  strength bounds (``scipy.optimize.lsq_linear``), reported relative to ``0.5 |r|^2``;
  ``d`` is the predicted strength. This is the score test: its numerator ``J_perp^T r_perp`` is
  the loss gradient with respect to the strengths at zero with the base directions projected
  out; ``J_perp^T J_perp`` (the Schur complement of the Gauss-Newton matrix) normalizes it.
* the autodiff gradient of the fit's own loss (L1/SSIM + Chamfer) with respect to each
  strength at zero is reported next to it, raw and projected
  (``g_s - beta^T g_theta`` with ``beta`` the least-squares coefficients of ``J_s`` on ``J_theta``).

Candidates whose gradient at zero is uninformative until an extra parameter is chosen are
searched (``wall``: normal among :data:`~toolkit.discovery.candidates.WALL_NORMALS` and three
offsets around the farthest the observed body went that way, a rigid wall; ``plastic_yield``: yield
stress on a grid of yield strains): each grid point is one rollout ``r_j``, scored as
``0.5 (|P r_ref|^2 - |P r_j|^2)`` (same linearized base refit; ``r_ref`` the candidate at
"absent").

A base fit without a wall explains a body that stops early by a slow throw (on a slide stopped by a
wall, a horizontal v0 of 0.41 m/s for a true 1.5). Its trajectory then never reaches any wall
placement, and no linearized refit can take v0 back: every wall point scores zero. The wall search
therefore also rolls out each placement from a second start, the base point with its horizontal v0
replaced by the observed body's horizontal velocity before its horizontal motion bends
(:func:`horizontal_start`). A placement rolled out from that start is scored against the better of
the base and the same start without a wall (``0.5 (min(|r_perp|^2, |P r_v|^2) - |P r_j|^2)``), so
the wall is credited only with what it adds to the change of v0. The best placement over both
starts wins, and ``search["start"]`` (``"base"`` or ``"observed_v0"``) and ``search["v0"]`` say
which start, so that the confirmation refit begins there.

Strength profiles: a one-sided strength (friction, drag, damping: zero is absent and negative
values are not allowed) whose linear prediction is clipped at zero scores zero, although the data
may support a finite strength. The linearization at zero can point the wrong way once the base
fit has partly absorbed the effect. Such a candidate is therefore also scored on a short profile:
one rollout per strength at :data:`PROFILE_MULTIPLES` of its finite-difference step, up to its
bound, each scored like a search point (``0.5 (|r_perp|^2 - |P r_j|^2)``). The best point sets the
candidate's score and predicted strength, and ``profile`` records every point. The rigid-wall
search scans :data:`WALL_STRENGTHS` in the same way.

Confusability: for candidates ``a`` and ``b``, the share of ``a``'s predicted residual change
``J_perp[:, S_a] d_a`` that ``b``'s columns can reproduce (1 = indistinguishable from the data,
0 = orthogonal). The most confusable partner of each candidate is reported.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field
from typing import Optional

import numpy as np
import torch

from toolkit.discovery.candidates import WALL_NORMALS
from toolkit.discovery.library import LibraryModel

__all__ = ["CandidateScore", "Ranking", "rank_candidates", "profile_strengths", "horizontal_start", "YIELD_STRAINS", "PROFILE_MULTIPLES", "WALL_STRENGTHS"]

log = logging.getLogger(__name__)

#: yield strains tau_Y / E scanned by the plastic-yield search.
YIELD_STRAINS = (0.003, 0.01, 0.03, 0.1)
#: wall offsets scanned beyond the observed extreme, in particle spacings.
WALL_OFFSETS = (-0.5, 0.5, 1.5)
#: wall strengths scanned at each normal and offset (1 = a rigid wall).
WALL_STRENGTHS = (0.25, 0.5, 1.0)
#: profile points of a one-sided strength whose linear score is zero, in multiples of its
#: finite-difference step (about half a decade apart).
PROFILE_MULTIPLES = (3.0, 10.0, 30.0, 100.0, 300.0)


@dataclass
class CandidateScore:
    """The ranking of one candidate.

    Attributes:
        name: candidate name.
        control: a control (must not be reported as physics).
        dof: number of strength parameters.
        score: predicted relative drop of the Gauss-Newton objective when the candidate is added
            and refitted with the base parameters (``drop / (0.5 |r|^2)``).
        predicted_strength: ``{parameter: value}`` at the predicted optimum (physical units).
        gradient: autodiff gradient of the fit loss with respect to each strength at zero, per
            step of the parameter (loss units).
        projected_gradient: the same with the base parameters' directions projected out.
        search: the chosen extra parameters of a searched candidate (wall normal and offset,
            log10 yield stress), else ``None``.
        partner: the most confusable other candidate, and ``overlap`` its share of this
            candidate's predicted residual change (0..1).
        rank: 1-based position.
        profile: for a candidate scored on a strength profile (see the module docstring), the
            points ``[{"parameter", "value", "score"}]``; else ``None``.
    """

    name: str
    control: bool
    dof: int
    score: float
    predicted_strength: dict[str, float] = field(default_factory=dict)
    gradient: dict[str, float] = field(default_factory=dict)
    projected_gradient: dict[str, float] = field(default_factory=dict)
    search: Optional[dict] = None
    partner: Optional[str] = None
    overlap: float = 0.0
    rank: int = 0
    profile: Optional[list] = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Ranking:
    """All candidates' scores, best first, plus what the confirmation needs.

    Attributes:
        scores: one :class:`CandidateScore` per candidate, sorted by score.
        objective: ``0.5 |r|^2`` at the base point.
        base_refit_objective: the predicted objective after refitting the base alone.
        overlaps: ``{a: {b: overlap}}`` (see the module docstring).
        seconds: wall-clock time of the ranking.
    """

    scores: list[CandidateScore]
    objective: float
    base_refit_objective: float
    overlaps: dict[str, dict[str, float]]
    seconds: float = 0.0

    def get(self, name: str) -> CandidateScore:
        for s in self.scores:
            if s.name == name:
                return s
        raise KeyError(name)

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.scores]

    def to_dict(self) -> dict:
        return {"scores": [s.to_dict() for s in self.scores], "objective": self.objective,
                "base_refit_objective": self.base_refit_objective, "overlaps": self.overlaps, "seconds": self.seconds}


def _projector(J_theta: np.ndarray, tol: float = 1e-7) -> np.ndarray:
    """Orthonormal basis (R, k) of the span of ``J_theta`` (columns with tiny singular values dropped)."""
    if J_theta.shape[1] == 0:
        return np.zeros((J_theta.shape[0], 0))
    U, S, _ = np.linalg.svd(J_theta, full_matrices=False)
    keep = S > tol * max(S.max(), 1e-30)
    return U[:, keep]


def _perp(Q: np.ndarray, X: np.ndarray) -> np.ndarray:
    return X - Q @ (Q.T @ X)


def _projected_drop(lib: LibraryModel, q: np.ndarray, Q: np.ndarray, ref_norm: float, what: str):
    """One rollout at ``q`` scored as a search point: ``(0.5 (ref_norm - |P r_q|^2), P r_q)``, or
    ``None`` when the rollout fails (CFL, NaN), which is no evidence either way (logged with
    ``what``)."""
    try:
        rj = _perp(Q, lib.residuals(q).numpy())
    except Exception as exc:
        log.info("%s failed: %s", what, exc)
        return None
    return 0.5 * (ref_norm - float(rj @ rj)), rj


def _bounded_lsq(A: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """argmin_d |A d - b|^2 with lo <= d <= hi."""
    from scipy.optimize import lsq_linear

    if A.shape[1] == 0 or not np.any(A):
        return np.zeros(A.shape[1])
    lo = np.where(np.isfinite(lo), lo, -np.inf)
    hi = np.where(np.isfinite(hi), hi, np.inf)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    res = lsq_linear(A / scale, b, bounds=(lo * scale, hi * scale), method="bvls" if A.shape[1] <= 12 else "trf")
    return res.x / scale


def rank_candidates(lib: LibraryModel, q0: Optional[np.ndarray] = None, plastic_lib: Optional[LibraryModel] = None,
                    search_wall: bool = True) -> tuple[Ranking, dict]:
    """Rank every candidate of ``lib`` at ``q0`` (default ``lib.q0``).

    Args:
        lib: the library model (its geometric weight already set).
        q0: base point (all strengths zero).
        plastic_lib: the ``plastic_yield`` variant (:class:`LibraryModel` with ``plastic=``),
            scanned when given.
        search_wall: scan wall normals and offsets when the wall is a candidate.

    Returns:
        ``(Ranking, state)``; ``state`` keeps the Jacobian pieces and the search results
        (``wall``: (index, offset); ``yield``: log10 yield stress) for the confirmation.
    """
    import time

    t0 = time.time()
    q0 = lib.q0.copy() if q0 is None else np.asarray(q0, np.float64)
    lib.assign(q0)
    r0 = lib.residuals(q0)
    r = r0.numpy()
    L0 = 0.5 * float(r @ r)
    base = lib.base_names
    strengths = [n for n in lib.names if n not in base and not n.startswith("wall.") and not n.startswith("plastic_yield.")]
    J_theta = lib.jacobian(q0, base, r0)
    J_s = lib.jacobian(q0, strengths, r0)
    Q = _projector(J_theta)
    r_perp = _perp(Q, r)
    L_base = 0.5 * float(r_perp @ r_perp)
    J_perp = _perp(Q, J_s)
    col = {n: i for i, n in enumerate(strengths)}
    # autodiff gradient of the fit loss, in loss units per step
    try:
        grad = lib.gradient(q0) * lib.steps
    except Exception as exc:  # pragma: no cover - a failed backward must not stop the ranking
        log.warning("autodiff gradient failed (%s); reporting the Gauss-Newton gradient only", exc)
        grad = np.full(len(lib.names), np.nan)
    gi = lib.idx(base)
    beta, *_ = np.linalg.lstsq(J_theta, J_s, rcond=None) if J_theta.shape[1] else (np.zeros((0, J_s.shape[1])),)
    proj_grad = grad[lib.idx(strengths)] - (beta.T @ grad[gi] if len(gi) else 0.0)

    scores: list[CandidateScore] = []
    changes: dict[str, np.ndarray] = {}
    spans: dict[str, np.ndarray] = {}
    state: dict = {"r0": r0, "objective": L0, "base_refit_objective": L_base}
    for c in lib.candidates:
        if c.search:
            continue
        names = lib.params_of(c.name)
        cols = [col[n] for n in names]
        A = J_perp[:, cols]
        ii = lib.idx(names)
        lo = (lib.low[ii] - q0[ii]) / lib.steps[ii]
        hi = (lib.high[ii] - q0[ii]) / lib.steps[ii]
        d = _bounded_lsq(A, -r_perp, lo, hi)
        res = r_perp + A @ d
        drop = 0.5 * (float(r_perp @ r_perp) - float(res @ res))
        changes[c.name] = A @ d
        spans[c.name] = A
        sc = CandidateScore(
            name=c.name, control=c.control, dof=len(names), score=max(drop, 0.0) / max(L0, 1e-30),
            predicted_strength={n: float(q0[i] + d[k] * lib.steps[i]) for k, (n, i) in enumerate(zip(names, ii))},
            gradient={n: float(grad[lib.index_of[n]]) for n in names},
            projected_gradient={n: float(proj_grad[col[n]]) for n in names},
        )
        if drop <= 0.0 and not c.control and np.all(lib.low[ii] == 0.0) and np.all(q0[ii] == 0.0):
            points, best = profile_strengths(lib, q0, Q, r_perp, names)
            sc.profile = points
            if best is not None and best[0] > 0.0:
                p_drop, q_best, rj = best
                sc.score = p_drop / max(L0, 1e-30)
                sc.predicted_strength = {n: float(q_best[i]) for n, i in zip(names, ii)}
                changes[c.name] = rj - r_perp
                spans[c.name] = changes[c.name][:, None]
        scores.append(sc)
    # ------------------------------------------------------------------ searched candidates
    if search_wall and "wall" in lib.names_of:
        best = _wall_search(lib, q0, Q, r_perp, L0)
        if best is not None:
            sc, change, span, where = best
            scores.append(sc)
            changes["wall"], spans["wall"] = change, span
            state["wall"] = where
    if plastic_lib is not None:
        best = _yield_search(plastic_lib, Q, L0)
        if best is not None:
            sc, change, span, log_tau = best
            scores.append(sc)
            changes["plastic_yield"], spans["plastic_yield"] = change, span
            state["yield"] = log_tau
    # ------------------------------------------------------------------ confusability
    overlaps: dict[str, dict[str, float]] = {}
    bases = {n: _projector(A, 1e-6) for n, A in spans.items()}
    for a, da in changes.items():
        na = float(np.linalg.norm(da))
        overlaps[a] = {}
        for b, Qb in bases.items():
            if b == a:
                continue
            overlaps[a][b] = float(np.linalg.norm(Qb.T @ da) / na) if na > 0 else 0.0
    for s in scores:
        o = overlaps.get(s.name, {})
        if o:
            s.partner = max(o, key=o.get)
            s.overlap = o[s.partner]
    scores.sort(key=lambda s: -s.score)
    for i, s in enumerate(scores):
        s.rank = i + 1
    state.update(J_theta=J_theta, Q=Q, beta=beta, strengths=strengths, grad=grad)
    return Ranking(scores, L0, L_base, overlaps, time.time() - t0), state


def profile_strengths(lib: LibraryModel, q0: np.ndarray, Q: np.ndarray, r_perp: np.ndarray, names: list[str]):
    """Score one-sided strengths on a profile (see the module docstring).

    For each parameter in ``names``, one rollout at each of :data:`PROFILE_MULTIPLES` times its
    step (clipped at its upper bound; a repeated value is skipped), the other strengths at
    ``q0``. Each point is scored as ``0.5 (|r_perp|^2 - |P r_j|^2)``: the drop of the
    Gauss-Newton objective after the base parameters' linearized refit. ``Q`` is the orthonormal
    basis of the base parameters' Jacobian and ``r_perp`` the base residual with that span removed.

    Returns:
        ``(points, best)``. ``points`` is ``[{"parameter", "value", "score"}]``, where ``score`` is
        the drop relative to ``0.5 |r_perp|^2``. ``best`` is ``(drop, q, P r_j)`` of the largest
        drop, or ``None`` when every rollout failed.
    """
    base_norm = float(r_perp @ r_perp)
    points: list[dict] = []
    best = None
    for n in names:
        i = lib.index_of[n]
        tried: set[float] = set()
        for m in PROFILE_MULTIPLES:
            v = float(min(q0[i] + m * lib.steps[i], lib.high[i]))
            if v in tried:
                continue
            tried.add(v)
            q = q0.copy()
            q[i] = v
            scored = _projected_drop(lib, q, Q, base_norm, f"profile of {n} at {v:g}")
            if scored is None:
                continue
            drop, rj = scored
            points.append({"parameter": n, "value": v, "score": drop / max(0.5 * base_norm, 1e-30)})
            if best is None or drop > best[0]:
                best = (drop, q, rj)
    return points, best


def _wall_search(lib: LibraryModel, q0: np.ndarray, Q: np.ndarray, r_perp: np.ndarray, L0: float):
    """Rigid walls just beyond the farthest the *observed* body (stage-0 surfaces) reached in each
    horizontal direction it moved; the best by predicted drop."""
    frames = lib.train_frames()
    obs = [lib.input.surfaces[f].double().numpy() for f in frames]
    obs = [o for o in obs if len(o)]
    if len(obs) < 2:
        return None
    spacing = float(lib.module.input.particle_volume) ** (1 / 3)
    base_norm = float(r_perp @ r_perp)
    best = None
    i_s = lib.index_of["wall.strength"]
    starts = [("base", q0, base_norm)]
    q_h = horizontal_start(lib, q0)
    scored = None if q_h is None else _projected_drop(lib, q_h, Q, base_norm, "the wall search's observed-v0 start")
    if scored is not None:  # the wall is credited only with what it adds to the v0 change alone
        rh = scored[1]
        starts.append(("observed_v0", q_h, min(base_norm, float(rh @ rh))))
    for k, n in enumerate(WALL_NORMALS):
        proj = [o @ np.asarray(n) for o in obs]
        m0, m_min = float(proj[0].min()), float(min(p.min() for p in proj))
        if m0 - m_min < 2 * spacing:
            continue  # the body did not move toward this side
        for f in WALL_OFFSETS:
            offset = m_min - f * spacing
            lib.set_wall(k, offset)
            for strength in WALL_STRENGTHS:
                for start, q_start, ref_norm in starts:
                    q = q_start.copy()
                    q[i_s] = strength
                    scored = _projected_drop(lib, q, Q, ref_norm, f"wall search at normal {n} offset {offset:.3f} "
                                                                  f"strength {strength:g} ({start} start)")
                    if scored is None:
                        continue
                    drop, rj = scored
                    if best is None or drop > best[0]:
                        best = (drop, k, offset, strength, rj, start, q)
    if best is None:
        return None
    drop, k, offset, strength, rj, start, q = best
    lib.set_wall(k, offset)
    change = rj - r_perp
    v0 = [float(q[lib.index_of[f"v0.{a}"]]) for a in "xyz"]
    sc = CandidateScore(name="wall", control=False, dof=1, score=max(drop, 0.0) / max(L0, 1e-30),
                        predicted_strength={"wall.strength": strength if drop > 0 else 0.0},
                        search={"normal": list(WALL_NORMALS[k]), "offset": offset, "index": k, "strength": strength,
                                "start": start, "v0": v0})
    return sc, change, change[:, None], (k, offset)


def horizontal_start(lib: LibraryModel, q0: np.ndarray, min_change: float = 0.02) -> Optional[np.ndarray]:
    """``q0`` with its horizontal v0 (x, z; m/s) replaced by the velocity of the observed body
    (stage-0 surfaces, training frames) before its horizontal motion bends, or ``None`` when there
    is no estimate or it differs from ``q0``'s by less than ``min_change`` m/s.

    Gravity and a frictionless ground do not act horizontally, so the centroid's x and z move on a
    straight line until something pushes sideways (a wall, friction, wind). The estimate is
    :func:`~toolkit.physics.initial_velocity.estimate_initial_velocity` on the surfaces with their
    height removed, zero gravity and no ground: a linear fit over the frames before the first
    that leaves the line by more than a grid cell (and stays off it). The vertical component is
    kept: the searched walls are vertical planes."""
    from toolkit.physics.initial_velocity import estimate_initial_velocity

    inp = lib.input
    flat = torch.tensor([1.0, 0.0, 1.0])
    try:
        est = estimate_initial_velocity([sf.detach().cpu().float() * flat for sf in inp.surfaces], inp.times,
                                        gravity=(0.0, 0.0, 0.0), ground_height=None, dx=float(lib.sim.config.dx),
                                        max_frames=int(inp.n_train))
    except Exception as exc:  # no estimate is no reason to stop the search
        log.info("no horizontal v0 estimate for the wall search: %s", exc)
        return None
    if est is None:
        return None
    q = np.asarray(q0, np.float64).copy()
    for a, v in zip("xz", (est.v0[0], est.v0[2])):
        q[lib.index_of[f"v0.{a}"]] = v
    q = lib.clip(q)
    if float(np.abs(q - q0).max()) < min_change:
        return None
    return q


def _yield_search(plib: LibraryModel, Q: np.ndarray, L0: float):
    """Plasticine at a grid of yield stresses against plasticine without yield; the best by drop."""
    q = plib.q0.copy()
    i = plib.index_of["plastic_yield.log10_yield_stress"]
    e = plib.mref
    plib.assign(q)
    q[i] = 12.0
    ref = _perp(Q, plib.residuals(q).numpy()) if Q.shape[0] else None
    ref_norm = float(ref @ ref)
    best = None
    for strain in YIELD_STRAINS:
        q[i] = math.log10(strain * e)
        scored = _projected_drop(plib, q, Q, ref_norm, f"yield search at strain {strain:g}")
        if scored is None:
            continue
        drop, rj = scored
        if best is None or drop > best[0]:
            best = (drop, q[i], rj)
    if best is None:
        return None
    drop, log_tau, rj = best
    change = rj - ref
    sc = CandidateScore(name="plastic_yield", control=False, dof=1, score=max(drop, 0.0) / max(L0, 1e-30),
                        predicted_strength={"plastic_yield.log10_yield_stress": float(log_tau)},
                        search={"log10_yield_stress": float(log_tau), "yield_strain": float(10 ** log_tau / e)})
    return sc, change, change[:, None], float(log_tau)

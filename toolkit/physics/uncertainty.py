"""How sure is the estimate: a Laplace (Gauss-Newton) posterior, 90 % intervals and identifiability labels.

After a fit, every physics parameter the fit optimized (material parameters in their raw space:
log10 E, tanh-bounded nu, ...; the components of v0 in m/s; gravity and effect strengths when they
are optimized) gets

* a 90 % interval (``low``, ``high``, physical units), and
* a label: ``determined``, ``weakly determined`` or ``not determined by this clip``.

Method (issue #24; chosen over profile likelihoods, which need refits, and multi-start spread,
which measures the optimizer rather than the data):

1. The geometric term of the fit, ``lambda_geo * sum_f chamfer(simulated surface_f, target_f) / F``
   over the fitted frames after frame 0, is a sum of squared residuals once each point's nearest
   neighbour is fixed (:class:`_Residuals`; a test checks it against ``chamfer_loss``). Its
   Jacobian ``J`` with respect to the K parameters (raw space) is taken by central finite
   differences through the simulator (forward rollouts only; the substeps are pinned to the finest
   plan any perturbed state needs, so a re-plan does not show up as a jump).
2. Re-matching nearest neighbours lets points slide along the surface, so the real chamfer loss is
   flatter than the fixed matches say, and bumpy below the point spacing. Each column of ``J`` is
   scaled to the curvature of the re-matched loss measured over a step that moves the surface by
   about one point spacing (:data:`WIDE_STEP_MAX` caps it).
3. Residual noise comes from the fit's own misfit, ``s^2 = SSR / (n_eff - K)``: the residuals of
   one frame are strongly correlated, so each frame counts as :data:`CLUSTERS_PER_FRAME`
   independent observations (calibrated on ``benchmarks/uncertainty.py``), not thousands.
4. With a weak Gaussian prior on the raw parameters centred on the initial guess (:data:`PRIOR_STD`),
   the posterior covariance is ``C = (J^T J / s^2 + diag(1 / prior_std^2))^-1``; the interval is
   ``raw +- t(0.5 + level / 2, n_eff - K) sqrt(C_kk)`` mapped to physical units, and the label comes
   from ``ratio = sqrt(C_kk) / prior_std`` (:func:`label_for`).
5. A nonlinear parameter (log10, tanh) may be bounded on one side only (a soft body sags visibly,
   any stiff one looks the same): the ends of its interval are simulated, and a side where the loss
   rises less than :data:`OPEN_SIDE_FRACTION` of the prediction is open: the interval extends to
   the prior there and the label is at best ``weakly determined``.
6. One MAP Gauss-Newton step with the prior (``prior_step``) moves the parameters the data do not
   constrain (labelled *not determined* by step 4) back toward their initial guess instead of
   leaving them wherever the optimizer stopped; the others stay where the fit put them (a joint
   step let a geometry bias trade their fitted values for prior mass: on the demo it moved v0 by
   0.24 m/s and nu by 0.2 away from the fit). It is taken only if it lowers the MAP objective
   (re-matched), halving it up to three times, and kept only if the fit's own loss (image and
   geometric terms over every training frame and camera) rises by at most
   :data:`FIT_LOSS_TOLERANCE`: otherwise the images determine what the geometric term leaves free,
   the fitted values stay, and those parameters are labelled *weakly determined* with a note. With
   ``fine_guard`` (off by default) a rise above the tolerance is checked on a grid of half the
   spacing too: if the same two states differ there by at most the tolerance, the objection is the
   coarse grid's own error, not the images', and the step is kept with a note (at the paper's
   size, below its truth, non-Newtonian eta's score falls toward zero on the fitting grid and rises
   on the truth's own; ``docs/limits.md``, "The viscosities"). When
   no step lowers the MAP objective, the re-matched geometric loss itself holds them near the fit
   (the linear estimate understated it): they stay, and those away from their prior (more than
   :data:`AT_PRIOR` prior standard deviations) and bounded on at least one side by step 5 are
   labelled *weakly determined* with a note, so a *not determined* label means the estimate is at
   its prior. (Seen at full size: a Newtonian capsule's viscosity, 1.2 decades from its prior.)
7. The grid term (``grid_term``, :mod:`toolkit.physics.grid_term`): the estimate is simulated on a
   grid of half the spacing as well, the change of the residuals is projected onto ``J`` (one
   Gauss-Newton step with the prior), and each interval is widened to cover the estimate shifted
   by that offset too. The intervals of steps 1-6 measure the data's spread around the minimum of
   the fit's loss; a grid too coarse for the body moves the minimum (on the calibration benchmark
   stiff tosses fitted at twice the truth's dx ended 0.3-0.5 decades soft, outside their
   intervals). The record is the grid check's, kept for the pipeline to reuse.

Cost: 4K + 1 rollouts for steps 1-2, 2 per nonlinear parameter for step 5 and at most 7 for step
6 (with ``fine_guard``, when the fit's loss objects to the step, two more on each grid), all
forward (a fit iteration is a forward and a backward pass, 4.5-6x a forward): 16-22 rollouts for E
and v0, 5-7 % of the fit in the benchmark. Step 7 adds one rollout on the fit's grid
and one on the fine grid (8x the particles). The initial velocity's component along the ground
normal of a body resting on a non-separating ground is fixed at 0 (:mod:`toolkit.physics.contact`)
and reported with a note.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from toolkit.physics.grid_term import GRID_SHIFT_SD
from toolkit.physics.uncertainty_probes import _fine_fit_loss_rise, _fit_loss_rise, _geometric_ssr, _map_step, _open_sides, _Residuals, _simulate

__all__ = ["LABELS", "DETERMINED_BELOW", "NOT_DETERMINED_ABOVE", "PRIOR_STD", "CLUSTERS_PER_FRAME", "ParameterUncertainty",
           "Uncertainty", "estimate_uncertainty", "label_for"]

#: the three identifiability labels
LABELS = ("determined", "weakly determined", "not determined by this clip")
#: posterior std / prior std below this: determined (the data narrow the prior at least 5x). Chosen
#: with :data:`NOT_DETERMINED_ABOVE` on ``benchmarks/uncertainty.py``: E of a toss with an impact has
#: ratios 0.06-0.15 there (determined), E of a box sliding on a frictionless ground or of a lob that
#: lands after the fitted frames 0.5-1.0 (not determined).
DETERMINED_BELOW = 0.2
#: a parameter within this many prior standard deviations of its prior mean is at its prior (a refused
#: prior step leaves it labelled not determined there; farther away it is relabelled weakly determined)
AT_PRIOR = 0.25
#: posterior std / prior std above this: not determined (the 90 % interval is most of the prior's)
NOT_DETERMINED_ABOVE = 0.45
#: prior std in the raw (optimized) space, by material transform: 1 decade for log10 parameters,
#: 0.25 for tanh-bounded ones (nu: a quarter of its range); linear ones use max(|initial|, 1)
PRIOR_STD = {"log10": 1.0, "tanh": 0.25}
#: prior std of each v0 component (m/s) and gravity component (m/s^2)
V0_PRIOR_STD = 1.0
GRAVITY_PRIOR_STD = 1.0
#: independent observations each fitted frame is worth (its residuals are correlated): calibrated on
#: ``benchmarks/uncertainty.py`` (24 CPU-sized scenes), where 3 gave 100 % coverage of the 90 %
#: intervals (all too wide, the truth within 0.36 half-widths in 90 % of the cases) and 11 gives
#: about 90 %; validated on 24 other scenes (docs/tutorials/uncertainty.md)
CLUSTERS_PER_FRAME = 11
#: an interval side where the simulated rise of the data term is below this fraction of the
#: linearized prediction is open (the data do not bound the parameter there)
OPEN_SIDE_FRACTION = 0.25
#: finite-difference steps in the raw space
FD_STEP = {"log10": 0.02, "tanh": 0.01, "linear": 0.01}
#: the MAP prior step is undone when it raises the fit's own loss (image and geometric terms) by more
#: than this fraction: the geometric term alone may leave free what the images determine (on the
#: 64 px five-family benchmark it reset fitted plasticine and Newtonian parameters to their starts).
#: The same 1 % as the coarse search's MIN_GAIN, the other way round.
FIT_LOSS_TOLERANCE = 0.01
#: largest step of the curvature measurement (which aims at moving the surface by one point spacing)
WIDE_STEP_MAX = {"log10": 0.5, "tanh": 0.3, "linear": 0.5}


def label_for(ratio: float) -> str:
    """The label of a posterior/prior std ``ratio`` (see :data:`DETERMINED_BELOW`, :data:`NOT_DETERMINED_ABOVE`)."""
    if ratio < DETERMINED_BELOW:
        return LABELS[0]
    if ratio <= NOT_DETERMINED_ABOVE:
        return LABELS[1]
    return LABELS[2]


@dataclass
class ParameterUncertainty:
    """One parameter's estimate, interval and label.

    Attributes:
        name: ``E``, ``nu``, ..., ``v0_x``, ``v0_y``, ``v0_z``, ``gravity_x``, ..., ``effect.param``.
        value: the estimate, physical units.
        low, high: the interval at the report's ``level``, physical units.
        label: one of :data:`LABELS`.
        ratio: posterior std / prior std in the raw space (0: fixed by data, 1: the prior alone).
        space: where the Gaussian lives: ``log10``, ``tanh`` or ``linear``.
        std: posterior std in that space.
        prior: prior mean (the initial guess), physical units.
        note: why a parameter is fixed (e.g. ground contact), else empty.
        grid_offset: the grid term (:mod:`toolkit.physics.grid_term`): how far a grid of half the
            spacing moves the estimate, in the raw space; the interval covers both; 0 when not run.
        grid_value: the estimate moved by ``grid_offset``, physical units (None when not run).
        data_low, data_high: the interval of the data alone (steps 1-6, before the grid term widens
            it), physical units.
    """

    name: str
    value: float
    low: float
    high: float
    label: str
    ratio: float
    space: str
    std: float
    prior: float
    note: str = ""
    grid_offset: float = 0.0
    grid_value: Optional[float] = None
    data_low: Optional[float] = None
    data_high: Optional[float] = None


@dataclass
class Uncertainty:
    """All parameters' uncertainty plus how it was computed."""

    parameters: list[ParameterUncertainty]
    level: float
    noise_std: float
    dof: int
    frames: int
    rollouts: int
    seconds: float
    prior_step: dict = field(default_factory=dict)
    grid: dict = field(default_factory=dict)

    def by_name(self) -> dict[str, ParameterUncertainty]:
        return {p.name: p for p in self.parameters}

    def to_dict(self) -> dict:
        d = asdict(self)
        d["parameters"] = {p["name"]: p for p in d["parameters"]}
        return d


@dataclass
class _Param:
    name: str
    space: str
    prior_mean: float
    prior_std: float
    get: Callable[[], float]
    set: Callable[[float], None]
    physical: Callable[[float], float]


def _parameters(module) -> list[_Param]:
    """The fitted physics parameters as scalar handles in their raw space."""
    out: list[_Param] = []
    mat = module.material
    for i, n in enumerate(mat.param_names):
        if n not in module.material_raw:
            continue
        p = mat.param(n)
        t = module.material_raw[n]
        mean = float(module.material_raw_fixed[i])
        std = PRIOR_STD.get(p.transform) or max(abs(mean), 1.0)
        # probes and interval ends stay inside the fit range (the valid range unless narrower)
        rlo, rhi = p.raw_fit_bounds(getattr(module, "fit_bounds", {}).get(n, (p.low, p.high)))
        setter = (lambda v, t=t, rlo=rlo, rhi=rhi: t.data.fill_(min(max(v, rlo), rhi)))
        if p.transform == "linear":
            physical = (lambda v, rlo=rlo, rhi=rhi: float(min(max(v, rlo), rhi)))
        else:
            physical = (lambda v, p=p, rlo=rlo, rhi=rhi: float(p.to_physical(torch.tensor(min(max(v, rlo), rhi)))))
        out.append(_Param(n, p.transform, mean, std, (lambda t=t: float(t.detach())), setter, physical))
    v0_init = getattr(module, "v0_start", None) or module.hparams.get("v0_init") or [0.0, 0.0, 0.0]
    normal = getattr(module, "contact_normal", None)
    for i, c in enumerate("xyz"):
        if normal is not None and abs(normal[i]) > 0.5:
            continue  # fixed at 0 by the ground (reported separately)
        out.append(_Param(f"v0_{c}", "linear", float(v0_init[i]), V0_PRIOR_STD, (lambda i=i: float(module.v0.detach()[i])),
                          (lambda v, i=i: module.v0.data.__setitem__(i, v)), float))
    if module.optimize_gravity:
        g0 = list(module.sim_config.gravity)
        for i, c in enumerate("xyz"):
            out.append(_Param(f"gravity_{c}", "linear", float(g0[i]), GRAVITY_PRIOR_STD, (lambda i=i: float(module.gravity.detach()[i])),
                              (lambda v, i=i: module.gravity.data.__setitem__(i, v)), float))
    if module.effect_names:
        init = module.simulator.pack_effects(module.effect_init).cpu().tolist()
        for i, n in enumerate(module.effect_names):
            out.append(_Param(str(n), "linear", float(init[i]), max(abs(init[i]), 1.0), (lambda i=i: float(module.effect_params.detach()[i])),
                              (lambda v, i=i: module.effect_params.data.__setitem__(i, v)), float))
    return out


def _frames(module) -> list[int]:
    """Fitted frames after the first whose target surface is not empty."""
    return [f for f in range(1, module.input.n_train) if len(module.input.surfaces[f])]


def check_uncertainty_options(options: Optional[dict]) -> dict:
    """``options`` for :func:`estimate_uncertainty` as a dict (``{}`` for ``None``), checked
    before any work: names must be its keyword parameters, ``level`` a number in (0, 1) and the
    switches True or False. Raises ValueError naming the option and what is expected."""
    import inspect

    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ValueError(f"uncertainty_options must be a mapping such as {{'fine_guard': True}}, got {options!r}")
    valid = [n for n in inspect.signature(estimate_uncertainty).parameters if n != "module"]
    for name, value in options.items():
        if name not in valid:
            raise ValueError(f"uncertainty_options.{name}: unknown option; valid: {', '.join(valid)}")
        if name == "level":
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
                raise ValueError(f"uncertainty_options.level = {value!r}: expected a number in (0, 1), e.g. 0.9")
        elif not isinstance(value, bool):
            raise ValueError(f"uncertainty_options.{name} = {value!r}: expected true or false")
    return dict(options)


def estimate_uncertainty(module, level: float = 0.9, prior_step: bool = True, grid_term: bool = True,
                         fine_guard: bool = False) -> Uncertainty:
    """Intervals and labels for ``module``'s current estimate (see the module docstring).

    Args:
        module: a fitted :class:`~toolkit.physics.InversePhysicsModule`.
        level: coverage of the intervals (0.9: 90 %).
        prior_step: take one MAP Gauss-Newton step with the prior first (moves parameters the clip
            does not determine back toward their initial guess); ``False`` only reports.
        grid_term: widen each interval to cover the estimate a grid of half the spacing would give
            (:mod:`toolkit.physics.grid_term`; step 7 of the module docstring). Its record, the
            grid check, is ``grid`` of the result.
        fine_guard: when the prior step raises the fit's own loss by more than
            :data:`FIT_LOSS_TOLERANCE`, ask a grid of half the spacing too and keep the step if the
            rise there is within the tolerance (the objection is the coarse grid's). Off by default:
            its effect on the benchmarks is not measured yet, and the finer grid is the better
            judge only when the truth is finer than the fit's grid (``docs/tutorials/uncertainty.md``,
            "When only the coarse grid objects"). Costs two rollouts at 8x the particles when asked.

    Returns:
        :class:`Uncertainty`; the module's parameters are changed only by an accepted prior step.

    Raises:
        ValueError: if ``level`` is not in (0, 1) or the clip has no fitted frame after frame 0
            with a target surface.
    """
    from scipy.stats import t as student_t

    if not 0 < level < 1:
        raise ValueError(f"estimate_uncertainty: level must be in (0, 1), got {level!r}")
    if not isinstance(fine_guard, bool):
        raise TypeError(f"estimate_uncertainty: fine_guard must be True or False, got {fine_guard!r}")
    frames = _frames(module)
    if not frames:
        raise ValueError(f"estimate_uncertainty: no fitted frame after frame 0 has a target surface "
                         f"(n_train = {module.input.n_train}); nothing constrains the physics")
    start = time.perf_counter()
    params = _parameters(module)
    K, n = len(params), max(frames)
    theta = np.array([p.get() for p in params])
    steps = np.array([FD_STEP[p.space] for p in params])
    sim = module.simulator
    floor = sim.substeps_floor
    rollouts = 0
    try:
        # pin the substeps to the finest plan any perturbed state needs (a re-plan would be a jump)
        pinned = floor
        for k in range(K):
            for sign in (1, -1):
                params[k].set(theta[k] + sign * steps[k])
                plan = sim.plan_substeps(module.material_params().detach(), module.v0.detach(), module.gravity.detach())
                pinned = max(pinned, plan.substeps)
            params[k].set(theta[k])
        sim.substeps_floor = pinned
        base = _simulate(module, n)
        rollouts += 1
        residuals = _Residuals(module, frames, base)
        r0 = residuals(base)
        J = torch.zeros(len(r0), K, dtype=torch.float64)
        ssr0 = float((r0 ** 2).sum())
        spacing = float(module.input.particle_volume) ** (1 / 3)
        curv, grad_data, wide = np.zeros(K), np.zeros(K), np.zeros(K)
        for k in range(K):
            cols, moved, at = [], [], []
            for sign in (1, -1):
                params[k].set(theta[k] + sign * steps[k])
                at.append(params[k].get())  # a bounded parameter's probe may be clamped: use where it went
                pos = _simulate(module, n)
                cols.append(residuals(pos))
                moved.append(pos[:, module.surface_index].double())
                rollouts += 1
            span = max(at[0] - at[1], 1e-12)
            J[:, k] = (cols[0] - cols[1]) / span
            # the re-matched loss is bumpy below the point spacing: measure its curvature over a step
            # that moves the surface by about one spacing
            speed = float((moved[0] - moved[1]).norm(dim=-1).max()) / span  # m per unit of theta_k
            wide[k] = float(np.clip(spacing / max(speed, 1e-12), steps[k], WIDE_STEP_MAX[params[k].space]))
            ssr, at = [], []
            for sign in (1, -1):
                params[k].set(theta[k] + sign * wide[k])
                at.append(params[k].get())
                try:
                    ssr.append(_geometric_ssr(module, frames, _simulate(module, n)))
                except Exception:  # the simulator rejects that state: treat as strongly disfavoured
                    ssr.append(math.inf)
                rollouts += 1
            params[k].set(theta[k])
            # three-point derivatives on the (possibly clamped, so unequal) spacings b above and a below
            b, a = at[0] - theta[k], theta[k] - at[1]
            if all(map(math.isfinite, ssr)) and a > 1e-12 and b > 1e-12:
                curv[k] = 2 * ((ssr[0] - ssr0) / b - (ssr0 - ssr[1]) / a) / (a + b)
                grad_data[k] = (ssr[0] - ssr[1]) / (2 * (a + b))
            else:
                curv[k], grad_data[k] = math.inf, 0.0
        J_fixed = J.cpu().numpy()  # fixed-match derivatives: the grid term projects onto these
        # re-matching nearest neighbours lets points slide along the surface: the chamfer loss is
        # flatter than the fixed-match residuals say; scale each column to the measured curvature
        gn = 2 * (J_fixed ** 2).sum(axis=0)
        kappa = np.clip(np.divide(curv, gn, out=np.zeros(K), where=gn > 0), 0.0, 1.0)
        J_np = J_fixed * np.sqrt(kappa)
        n_eff = CLUSTERS_PER_FRAME * len(frames)
        dof = max(n_eff - K, 1)
        s2 = max(ssr0 / dof, 1e-30)
        prior_mean = np.array([p.prior_mean for p in params])
        prior_prec = np.array([1.0 / p.prior_std ** 2 for p in params])
        H = J_np.T @ J_np / s2 + np.diag(prior_prec)
        cov = np.linalg.inv(H)
        step_info: dict = {"taken": False}
        free = [k for k in range(K) if math.sqrt(max(cov[k, k], 0.0)) / params[k].prior_std > NOT_DETERMINED_ABOVE]
        image_held: dict[int, float] = {}
        grid_objected: dict[int, tuple[float, float]] = {}
        clip_held: set[int] = set()
        if prior_step and free:
            before = theta
            theta, step_info, extra = _map_step(module, params, frames, n, theta, grad_data, s2, H, prior_mean, prior_prec,
                                                free)
            rollouts += extra
            if step_info.get("taken"):
                rise, extra = _fit_loss_rise(module, params, n, before, theta)
                rollouts += extra
                step_info["fit_loss_rise"] = rise
                fine_rise = None
                if rise > FIT_LOSS_TOLERANCE and fine_guard:  # does a finer grid object too?
                    fine_rise, extra = _fine_fit_loss_rise(module, params, before, theta)
                    rollouts += extra
                    step_info["fine_fit_loss_rise"] = fine_rise
                if rise > FIT_LOSS_TOLERANCE and fine_rise is not None and fine_rise <= FIT_LOSS_TOLERANCE:
                    step_info["reason"] = (
                        f"kept: the step changed the fit's own loss by {100 * rise:+.1f} % on the fit's grid but by "
                        f"{100 * fine_rise:+.1f} % on a grid of half the spacing, so the objection is the coarse grid's, "
                        f"not the images'")
                    grid_objected = {k: (rise, fine_rise) for k in free}
                elif rise > FIT_LOSS_TOLERANCE:  # the fit's whole loss (images too) objects: keep the fit
                    for p, v in zip(params, before):
                        p.set(float(v))
                    theta = before
                    fine = "" if fine_rise is None else f", and by {100 * fine_rise:+.1f} % on a grid of half the spacing"
                    step_info.update(taken=False, reason=(
                        f"reverted: the step raised the fit's own loss (image and geometric terms) by "
                        f"{100 * rise:.1f} % (> {100 * FIT_LOSS_TOLERANCE:.0f} %){fine}, so the images constrain what "
                        f"the geometric term leaves free"))
                    image_held = {k: rise for k in free}
            else:  # no step toward the prior lowers the MAP objective: the re-matched geometric term objects
                step_info["reason"] = ("refused: every step toward the prior raised the clip's own geometric loss more than "
                                       "the prior gained, so the clip holds these parameters where the fit put them")
                clip_held = set(free)
        elif prior_step:
            step_info = {"taken": False, "reason": "every parameter is determined or weakly determined by the clip"}
        q = float(student_t.ppf(0.5 + level / 2, dof))
        sds = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        open_sides, extra = _open_sides(module, params, frames, n, theta, sds, q, np.diag(J_np.T @ J_np), s2)
        rollouts += extra
    finally:
        sim.substeps_floor = floor
        module._cached_positions = None
    offsets, grid = None, {}
    if grid_term:
        from toolkit.physics.grid_term import grid_offsets

        for p, v in zip(params, theta):
            p.set(float(v))
        offsets, grid = grid_offsets(module, residuals, J_fixed, s2, prior_prec)
        module._cached_positions = None
        rollouts += 2
    out = []
    for k, p in enumerate(params):
        sd = float(sds[k])
        ends = [theta[k] - q * sd, theta[k] + q * sd]
        ratio = sd / p.prior_std
        label, note = label_for(ratio), ""
        sides = open_sides.get(k, ())
        for side in sides:  # the data do not bound this side: the prior does
            i = 0 if side < 0 else 1
            ends[i] = theta[k] + side * q * max(sd, p.prior_std)
        if sides:
            label = LABELS[2] if len(sides) == 2 else LABELS[max(1, LABELS.index(label))]
            note = ("the clip bounds it on neither side within the interval" if len(sides) == 2 else
                    f"the clip bounds it only from {'below' if sides[0] > 0 else 'above'}")
        if k in clip_held and label == LABELS[2] and len(sides) < 2 and abs(theta[k] - p.prior_mean) > AT_PRIOR * p.prior_std:
            label = LABELS[1]
            note = "; ".join(x for x in (note, "the linear estimate calls it free, but no step toward its prior lowers the "
                                               "clip's loss: the clip holds it near the fit's value") if x)
        if k in grid_objected:
            note = "; ".join(x for x in (note, (
                f"moved toward its prior: the fit's grid objected ({100 * grid_objected[k][0]:+.1f} % loss), a grid of "
                f"half the spacing did not ({100 * grid_objected[k][1]:+.1f} %)")) if x)
        if k in image_held:
            label = LABELS[1]
            note = (f"the geometric term leaves it free (interval from it alone), but moving it to its prior "
                    f"raises the fit's loss by {100 * image_held[k]:.1f} %: the images constrain it")
        data_low, data_high = sorted((p.physical(ends[0]), p.physical(ends[1])))
        off, moved_to = 0.0, None
        if offsets is not None:
            off = float(offsets[k])
            moved_to = p.physical(theta[k] + off)
            ends = [min(ends[0], ends[0] + off), max(ends[1], ends[1] + off)]  # the fine grid's answer too
            if abs(off) > GRID_SHIFT_SD * sd:
                note = "; ".join(x for x in (note, f"a grid of half the spacing moves it to {moved_to:.3g} (the interval "
                                                   f"covers both grids)") if x)
        lo, hi = sorted((p.physical(ends[0]), p.physical(ends[1])))
        out.append(ParameterUncertainty(p.name, p.physical(theta[k]), lo, hi, label, ratio, p.space, sd,
                                        p.physical(p.prior_mean), note, off, moved_to, data_low, data_high))
    normal = getattr(module, "contact_normal", None)
    if normal is not None:
        i = max(range(3), key=lambda j: abs(normal[j]))
        out.append(ParameterUncertainty(f"v0_{'xyz'[i]}", 0.0, 0.0, 0.0, LABELS[2], 1.0, "linear", 0.0, 0.0,
                                        note="fixed at 0: the body starts on a non-separating ground"))
        group = lambda o: (1, o.name) if o.name.startswith("v0_") else (2, "") if o.name.startswith("gravity_") else (  # noqa: E731
            0, "") if o.name in module.material.param_names else (3, "")
        out.sort(key=group)  # stable: material, v0 x y z, gravity, effects
    return Uncertainty(out, level, math.sqrt(s2), int(dof), len(frames), rollouts, time.perf_counter() - start, step_info,
                       grid)


def annotate_rows(rows: list[dict], result: Optional[dict]) -> list[dict]:
    """Add ``low``, ``high``, ``label``, ``note``, ``grid_value`` (the estimate on a grid of half the
    spacing, :mod:`toolkit.physics.grid_term`) and ``grid_shift_sd`` (how far that grid moves the
    estimate, in posterior standard deviations of the raw space; None without the grid term) to
    summary rows (``{"parameter": name, ...}``) from an :meth:`Uncertainty.to_dict` result;
    parameters the fit did not optimize get ``label = "fixed (not fitted)"``. Rows are changed in
    place and returned."""
    params = (result or {}).get("parameters", {})
    for row in rows:
        p = params.get(row["parameter"])
        if p is not None:
            shift = None
            if p.get("grid_value") is not None and p.get("std"):
                shift = abs(float(p.get("grid_offset") or 0.0)) / float(p["std"])
            row.update(low=p["low"], high=p["high"], label=p["label"], note=p.get("note", ""), grid_value=p.get("grid_value"),
                       grid_shift_sd=shift)
        elif result is not None:
            row.update(low=None, high=None, label="fixed (not fitted)", note="")
    return rows


def format_interval(low: Optional[float], high: Optional[float]) -> str:
    """``[low, high]`` with 3 significant digits, or ``-``."""
    if low is None or high is None:
        return "-"
    return f"[{low:.3g}, {high:.3g}]"

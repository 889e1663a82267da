"""How far the prediction moves across the parameters' intervals: the forecast spread (issue #20).

The uncertainty step (:mod:`toolkit.physics.uncertainty`) gives each fitted parameter an interval
the clip cannot narrow. Two values inside one interval can fit the training frames equally well
and still predict different futures: a box that lands a second time after the clip ends bounces
one way or the other with Poisson's ratio (``docs/results/paper_size.md``, "Where the elastic
row's future CD comes from"). This module measures that: each parameter in turn is put at the low
and at the high end of its interval (the others at the estimate), every frame is simulated, and
each particle's distance from where the estimate puts it is averaged over the body.

Returned per frame (``spread_mm``, length T, frame 0 first): the largest such mean distance over
the 2K rollouts, in millimetres, with the parameter and end that gave it at the last frame
(``driver``). ``train_mm`` and ``future_mm`` are the largest values over the fitted frames and over
the frames after them. Before ground contact a change of v0 by ``dv`` moves every particle by
``abs(dv) t``, and a material parameter moves none (the tests check both).

Cost: two forward rollouts of the whole clip per parameter with an interval (material parameters,
v0's components, optimized gravity and effect strengths), about 2-5 % of a fit.
"""

from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np
import torch


def _raw_of(module, name: str, value: float) -> Optional[float]:
    """The raw (optimized-space) value of parameter ``name`` at physical ``value``; None when it
    cannot be represented (an interval end at a log10 parameter's zero)."""
    if name in getattr(module, "material_raw", {}):
        p = module.material.param(name)
        if p.transform == "log10" and not value > 0:
            return None
        raw = float(p.to_raw(value))
        return raw if math.isfinite(raw) else None
    return float(value)


def forecast_spread(module, uncertainty: Optional[dict] = None, n_frames: Optional[int] = None,
                    base: Optional[np.ndarray] = None) -> Optional[dict]:
    """The forecast spread of a fitted module across its parameters' intervals.

    Args:
        module: a fitted :class:`~toolkit.physics.InversePhysicsModule`.
        uncertainty: its :meth:`~toolkit.physics.InversePhysicsModule.uncertainty` result (default:
            ``module.uncertainty_result``); ``None`` there means nothing to spread: returns None.
        n_frames: frames to predict (default: the clip's, training and future).
        base: the estimate's own prediction, (T, N, 3) metres, when the caller has it already
            (the evaluation's ``prediction.npz``); simulated here otherwise.

    Returns:
        ``{"spread_mm": [T floats], "train_mm", "future_mm", "n_train", "driver": {"parameter",
        "end", "value", "mm"}, "per_parameter": {name: [low-end mm, high-end mm] at the last frame},
        "rollouts", "seconds"}``, or None without an uncertainty result or an interval to spread.
        The module's parameters are restored.
    """
    from toolkit.physics.uncertainty import _parameters

    unc = uncertainty if uncertainty is not None else getattr(module, "uncertainty_result", None)
    if not unc or not unc.get("parameters"):
        return None
    intervals = unc["parameters"]
    handles = [h for h in _parameters(module) if h.name in intervals]
    T = int(n_frames or module.input.n_frames)
    n_train = int(module.input.n_train)
    t0 = time.perf_counter()
    start = [h.get() for h in handles]
    rollouts = 0
    try:
        with torch.no_grad(), module.substeps_unlogged():
            if base is None:
                _, base = module.simulate(T - 1, frozenset())
            base = torch.as_tensor(base, device=module.v0.device).double()
            spread = np.zeros(T)
            driver = {"parameter": None, "end": None, "value": None, "mm": 0.0}
            per_parameter: dict[str, list[float]] = {}
            for h, value0 in zip(handles, start):
                ends = []
                for end in ("low", "high"):
                    phys = intervals[h.name].get(end)
                    raw = None if phys is None else _raw_of(module, h.name, float(phys))
                    if raw is None or abs(raw - value0) < 1e-12:
                        ends.append(0.0)
                        continue
                    h.set(raw)
                    _, pos = module.simulate(T - 1, frozenset())
                    rollouts += 1
                    h.set(value0)
                    moved = (pos.double() - base).norm(dim=-1).mean(dim=-1).cpu().numpy() * 1e3  # (T,) mm
                    spread = np.maximum(spread, moved)
                    ends.append(float(moved[-1]))
                    if moved[-1] > driver["mm"]:
                        driver = {"parameter": h.name, "end": end, "value": float(phys), "mm": float(moved[-1])}
                per_parameter[h.name] = ends
    finally:
        for h, v in zip(handles, start):
            h.set(v)
        module._cached_positions = None
    if not per_parameter:
        return None
    return {"spread_mm": [float(x) for x in spread], "n_train": n_train,
            "train_mm": float(spread[:n_train].max()), "future_mm": float(spread[n_train:].max()) if T > n_train else None,
            "driver": driver, "per_parameter": per_parameter, "rollouts": rollouts,
            "seconds": round(time.perf_counter() - t0, 2)}


def describe_spread(spread: Optional[dict]) -> Optional[str]:
    """One sentence for the run's summary, or None without a spread."""
    if not spread:
        return None
    d = spread["driver"]
    tail = "" if d["parameter"] is None else (
        f"; at the last frame the most from {d['parameter']} at its interval's {d['end']} end "
        f"({d['value']:.4g}: {d['mm']:.1f} mm)")
    future = "" if spread["future_mm"] is None else f", the future frames by up to {spread['future_mm']:.1f} mm"
    return (f"across the parameters' intervals the prediction moves the fitted frames by up to {spread['train_mm']:.1f} mm"
            f"{future}{tail}")

"""Physical-parameter errors (the paper's MAE rows).

Per parameter, for one scene (the paper then averages over scenes):

* ``|log10 pred - log10 gt|`` for the names in :data:`LOG_PARAMS` (E, viscosity mu, bulk modulus
  kappa, yield stress tau_Y, plastic viscosity eta);
* ``|pred - gt|`` for everything else (nu; friction angle in degrees);
* vector-valued parameters (initial velocity ``v0``, or any list) give the mean absolute error
  of their components.

Names are the materials' keys: ``E``, ``nu``, ``mu``, ``kappa``, ``yield_stress``,
``plastic_viscosity``, ``friction_angle`` and ``v0``. The public datasets' own spellings (PAC-NeRF
``v``/``ys``/``eta``/``fa``, Spring-Gaus ``NU``/``INIT_VELOCITY``, Vid2Sim ``yms``/``prs``) are
mapped by :func:`canonical_param_name`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

__all__ = ["LOG_PARAMS", "PARAM_ALIASES", "canonical_param_name", "parameter_errors"]

LOG_PARAMS: set[str] = {"E", "mu", "kappa", "yield_stress", "plastic_viscosity"}

PARAM_ALIASES: dict[str, str] = {
    "v": "v0",
    "vel": "v0",
    "INIT_VELOCITY": "v0",
    "init_velocity": "v0",
    "ys": "yield_stress",
    "eta": "plastic_viscosity",
    "fa": "friction_angle",
    "NU": "nu",
    "yms": "E",
    "prs": "nu",
}


def canonical_param_name(name: str) -> str:
    """Map a dataset's spelling of a parameter to the toolkit's name (unknown names unchanged)."""
    return PARAM_ALIASES.get(name, name)


def _numeric(value) -> np.ndarray | None:
    """Return the value as a float array, or None for non-numeric entries (e.g. material names)."""
    if isinstance(value, (str, bytes, Mapping)) or value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr


def parameter_errors(pred: Mapping, gt: Mapping) -> dict:
    """Absolute errors of estimated parameters against the ground truth of one scene.

    Args:
        pred: Estimated parameters, ``name -> float`` (or a 3-vector for ``v0``).
        gt: Ground-truth parameters with the same names.

    Returns:
        ``name -> error`` (float) for every numeric name present on both sides, plus
        ``"missing"``: the sorted ground-truth names with no estimate (always present, possibly
        empty). Names only in ``pred`` are skipped silently (no ground truth, e.g. a fixed E for
        sand); non-numeric entries (strings, dicts, None) on either side are ignored.

    Raises:
        ValueError: A log-scale parameter is not positive, or vector lengths differ.
    """
    pred_n = {k: v for k, v in pred.items() if _numeric(v) is not None}
    gt_n = {k: v for k, v in gt.items() if _numeric(v) is not None}
    errors: dict = {}
    for name in gt_n:
        if name not in pred_n:
            continue
        p, g = _numeric(pred_n[name]), _numeric(gt_n[name])
        if p.shape != g.shape:
            raise ValueError(f"parameter {name!r}: prediction shape {p.shape} != truth {g.shape}")
        if name in LOG_PARAMS:
            if np.any(p <= 0) or np.any(g <= 0):
                raise ValueError(f"parameter {name!r} is log-scale but not positive: {p} vs {g}")
            err = np.abs(np.log10(p) - np.log10(g))
        else:
            err = np.abs(p - g)
        errors[name] = float(err.mean()) if err.size else math.nan
    errors["missing"] = sorted(set(gt_n) - set(pred_n))
    return errors

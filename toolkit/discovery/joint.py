"""Candidates whose score test is inconclusive because an undetermined base parameter absorbs them.

The ranking's score test (:mod:`toolkit.discovery.ranking`) projects the base parameters'
directions out of each candidate's effect on the residuals. When a base parameter is *not
determined by the clip* (the Laplace labels of issue #24, :mod:`toolkit.physics.uncertainty`),
its direction is nearly free, and a candidate whose effect resembles it loses most of its score
to the projection: the test is inconclusive, not negative. Such a candidate is confirmed anyway,
by a refit in which the undetermined base parameter and the candidate's strengths are fitted
jointly (every confirmation refit frees the base parameters; here it is what lets the
candidate be judged on held-out data at all).

A candidate is *absorbed* by base parameter ``u`` when ``u`` is labelled "not determined",
the candidate's raw gradient is not negligible and the projection removed at least
:data:`ABSORBED_SHARE` of it, and ``u`` carries the largest share of the removed part
(``|beta[u, j] grad_u|``, ``beta`` the least-squares coefficients of the candidate's Jacobian
column on the base columns).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ["ABSORBED_SHARE", "undetermined_base", "absorbed_candidates"]

#: share of a candidate's gradient the base projection must remove for the test to be inconclusive
ABSORBED_SHARE = 0.5
_NOT_DETERMINED = "not determined by this clip"


def library_name(name: str) -> str:
    """The library parameter of an uncertainty row (``E`` -> ``mat.E``, ``v0_x`` -> ``v0.x``,
    ``gravity_y`` -> ``gravity.y``)."""
    for head in ("v0", "gravity"):
        if name.startswith(head + "_") and name[-1] in "xyz":
            return f"{head}.{name[-1]}"
    return f"mat.{name}"


def undetermined_base(uncertainty: Optional[dict], base_names: list[str]) -> list[str]:
    """Library names of the base parameters labelled "not determined by this clip" in an
    uncertainty result (``module.uncertainty_result``: ``{"parameters": {name: {"label": ...}}}``)."""
    if not uncertainty:
        return []
    params = uncertainty.get("parameters") or {}
    rows = params.values() if isinstance(params, dict) else params
    out = []
    for p in rows:
        if p.get("label") == _NOT_DETERMINED:
            n = library_name(p["name"])
            if n in base_names:
                out.append(n)
    return out


def absorbed_candidates(ranking, state: dict, lib, undetermined: list[str], chosen: list[str]) -> dict[str, str]:
    """``{candidate: undetermined base parameter}`` for candidates not in ``chosen`` whose score
    test an undetermined base parameter made inconclusive (see the module docstring)."""
    if not undetermined or "beta" not in state:
        return {}
    beta, strengths, grad = state["beta"], state["strengths"], state["grad"]
    base = lib.base_names
    col = {n: i for i, n in enumerate(strengths)}
    out: dict[str, str] = {}
    g_scale = float(np.nanmax(np.abs(grad[lib.idx(strengths)]))) if strengths else 0.0
    for s in ranking.scores:
        if s.name in chosen or s.control or s.search is not None or not s.gradient:
            continue
        n = max(s.gradient, key=lambda k: abs(s.gradient[k]))
        g, pg = abs(s.gradient[n]), abs(s.projected_gradient.get(n, 0.0))
        if not np.isfinite(g) or g <= 1e-3 * g_scale or n not in col or pg > (1.0 - ABSORBED_SHARE) * g:
            continue
        removed = np.abs(beta[:, col[n]] * grad[lib.idx(base)])
        u = base[int(np.nanargmax(removed))]
        if u in undetermined:
            out[s.name] = u
    return out

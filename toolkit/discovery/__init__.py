"""Discrepancy discovery: find where simulation and measurements disagree, name the missing effect,
add it, and show the gap shrink.

>>> from toolkit.discovery import discover
>>> result = discover(fitted_module)            # or discover("RUN_DIR"), or `projo4d discover RUN_DIR`
>>> result.decision, result.gap["cd_shrink"]

Modules, one job each:

* :mod:`~toolkit.discovery.candidates`: the library of candidate effects and controls;
* :mod:`~toolkit.discovery.materials`: the material wrapper of internal damping and density;
* :mod:`~toolkit.discovery.library`: the fitted model extended by every candidate (one parameter vector);
* :mod:`~toolkit.discovery.residuals`: localization (regions, phases, rigid/non-rigid, cameras);
* :mod:`~toolkit.discovery.ranking`: projected score test at zero strength, wall and yield searches;
* :mod:`~toolkit.discovery.confirm`: Levenberg-Marquardt refits of the top candidates;
* :mod:`~toolkit.discovery.selection`: held-out criterion, per-parameter penalty, ties within noise;
* :mod:`~toolkit.discovery.separation`: the observation that would separate tied candidates;
* :mod:`~toolkit.discovery.joint`: candidates absorbed by an undetermined base parameter, refitted jointly;
* :mod:`~toolkit.discovery.camera`: the camera-pose control narrowed to one camera;
* :mod:`~toolkit.discovery.calibration`: decision thresholds calibrated on null scenes;
* :mod:`~toolkit.discovery.gap`: future-frame metrics before and after;
* :mod:`~toolkit.discovery.workflow`: :func:`discover` and :class:`DiscoveryResult`;
* :mod:`~toolkit.discovery.export`: the base module with the discovered effect added;
* :mod:`~toolkit.discovery.report`: Markdown/HTML report with figures;
* :mod:`~toolkit.discovery.loading`: a fitted module from a run folder;
* :mod:`~toolkit.discovery.hidden`: scenes with a hidden effect (tests, benchmark);
* :mod:`~toolkit.discovery.from_images`: their geometry from stage 0, held still in the physics;
* :mod:`~toolkit.discovery.consensus`: whether several runs of one scene name the same effect;
* :mod:`~toolkit.discovery.commands`: ``projo4d discover RUN_DIR [RUN_DIR ...]``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

__all__ = ["discover", "DiscoveryResult", "LIBRARY", "Candidate", "Thresholds", "load_fitted_module"]

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.discovery.calibration import Thresholds
    from toolkit.discovery.candidates import LIBRARY, Candidate
    from toolkit.discovery.loading import load_fitted_module
    from toolkit.discovery.workflow import DiscoveryResult, discover

_LAZY = {
    "discover": "toolkit.discovery.workflow",
    "DiscoveryResult": "toolkit.discovery.workflow",
    "LIBRARY": "toolkit.discovery.candidates",
    "Candidate": "toolkit.discovery.candidates",
    "Thresholds": "toolkit.discovery.calibration",
    "load_fitted_module": "toolkit.discovery.loading",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'toolkit.discovery' has no attribute {name!r}")

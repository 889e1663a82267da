"""Digital twins of fitted runs: export (``projo4d export``), re-simulation (``projo4d simulate``) and a
browser viewer (``projo4d view --browser``).

* :mod:`toolkit.twin.format`: the versioned twin file (:class:`DigitalTwin`);
* :mod:`toolkit.twin.export`: a run folder -> 3DGS PLY, per-frame PLY sequence, twin;
* :mod:`toolkit.twin.simulate`: load -> simulate under new v0/parameters/effects -> render;
* :mod:`toolkit.twin.viewer`: the interactive viewer (viser) with re-simulation sliders.
"""

from toolkit.twin.format import TWIN_FORMAT, TWIN_SCHEMA, TWIN_VERSION, DigitalTwin, TwinFormatError
from toolkit.twin.simulate import (TwinTrajectory, dataset_cameras, orbit_cameras, render_trajectory, simulate_twin,
                                   twin_gaussians, write_video)

__all__ = ["DigitalTwin", "TwinFormatError", "TWIN_FORMAT", "TWIN_SCHEMA", "TWIN_VERSION", "TwinTrajectory",
           "simulate_twin", "twin_gaussians", "dataset_cameras", "orbit_cameras", "render_trajectory", "write_video"]

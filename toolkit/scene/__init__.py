"""The scene model of stage 0: 4D Gaussians and the particle continuum built from them.

* :mod:`toolkit.scene.gaussian_model`: learnable canonical Gaussians, adaptive density control;
* :mod:`toolkit.scene.deformation`: GIC's motion-factorized deformation network;
* :mod:`toolkit.scene.initialization`: random-box and visual-hull initialization;
* :mod:`toolkit.scene.stage0`: :class:`Gaussians4DModule` (LightningModule),
  :class:`Stage0Schedule`, :class:`Stage0DataModule`, :func:`fit_stage0`;
* :mod:`toolkit.scene.export`: per-frame centres, renders, 3DGS PLY;
* :mod:`toolkit.scene.continuum`: :func:`build_continuum` (particles and surface points).

The Lightning parts are imported on first use, so ``import toolkit.scene`` stays light.
"""

from toolkit.scene.continuum import Continuum, ContinuumConfig, build_continuum
from toolkit.scene.deformation import DeformationConfig, DeformationNetwork
from toolkit.scene.export import gaussian_centers, load_ply, ply_property_names, render_views, save_ply
from toolkit.scene.gaussian_model import DensificationConfig, GaussianModel
from toolkit.scene.initialization import mask_bounding_box, random_box_points, visual_hull_points

_LAZY = {
    "Gaussians4DModule",
    "Stage0Schedule",
    "Stage0DataModule",
    "Stage0Checkpoint",
    "TrainingViews",
    "fit_stage0",
}

__all__ = [
    "Continuum",
    "ContinuumConfig",
    "build_continuum",
    "DeformationConfig",
    "DeformationNetwork",
    "DensificationConfig",
    "GaussianModel",
    "gaussian_centers",
    "load_ply",
    "ply_property_names",
    "render_views",
    "save_ply",
    "mask_bounding_box",
    "random_box_points",
    "visual_hull_points",
    *sorted(_LAZY),
]


def __getattr__(name: str):
    if name in _LAZY:
        from toolkit.scene import stage0

        return getattr(stage0, name)
    raise AttributeError(f"module 'toolkit.scene' has no attribute {name!r}")

"""projo4d's core: the differentiable Warp MPM, scene representation, data, losses and metrics,
Lightning modules, command line, discovery and visualization.

Importing ``toolkit`` is light: Warp, open3d and Lightning are imported by the submodules that
need them.
"""

__version__ = "0.1.0"

from toolkit.resources import configs_dir, find_config  # noqa: E402  (light: importlib and pathlib only)

__all__ = ["__version__", "configs_dir", "find_config"]

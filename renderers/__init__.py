"""Renderer registry: differentiable Gaussian-splatting backends, chosen by name.

>>> from renderers import get_renderer
>>> r = get_renderer("torch")          # the exact pure-PyTorch reference
"""

from __future__ import annotations

from toolkit.registry import Registry
from renderers.base import Gaussians, RenderOutput, Renderer

RENDERERS: Registry[type[Renderer]] = Registry(
    "renderer",
    entry_point_group="projo4d.renderers",
    # built-in backends register themselves on import; gsplat_backend registers only when
    # gsplat is importable and CUDA is present
    builtin_modules=("renderers.torch_reference", "renderers.warp_tiles", "renderers.gsplat_backend"),
)
register_renderer = RENDERERS.register

__all__ = ["RENDERERS", "register_renderer", "get_renderer", "Gaussians", "RenderOutput", "Renderer"]


def get_renderer(name: str, **kwargs) -> Renderer:
    """Instantiate the renderer registered as ``name`` with ``kwargs``."""
    return RENDERERS.get(name)(**kwargs)

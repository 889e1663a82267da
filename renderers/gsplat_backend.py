"""gsplat (CUDA) backend, registered as ``"gsplat"`` only when gsplat imports and CUDA is present.

Wraps ``gsplat.rasterization`` (API of gsplat 1.5.3) in classic 3DGS mode with the project's
conventions: quaternions (w, x, y, z) as they are (gsplat normalizes them), ``scales =
exp(log_scales)``, ``opacities = sigmoid(opacity_logits)``, ``viewmats = cameras.w2c``,
``Ks = cameras.K``, ``eps2d = 0.3``, ``render_mode="RGB+D"`` (accumulated depth ``sum w_i z_i``
in the last channel), ``packed=False``, backgrounds per camera. SH colours go through gsplat's
own evaluation (``sh_degree`` from K, ``+0.5`` and clamp at 0, as the reference does).

Known differences from the contribution rule of :mod:`renderers.base` (gsplat's kernels, not
this wrapper), so cross-backend tests should keep opacities below 0.99 and stay away from the
exact cut-off value:

* gsplat clamps per-Gaussian alpha at 0.999 instead of 0.99;
* gsplat stops when ``T (1 - alpha) <= 1e-4`` (the reference: ``< 1e-4``);
* gsplat skips a contribution whose quadratic form is negative by rounding.

Everything runs in float32 on CUDA (gsplat's kernels are float32-only): inputs are cast, the
outputs are float32. There is no far-plane culling, as in the reference (``far_plane=1e10``).
gsplat is imported only when this module is imported (by the renderer registry on first lookup),
so ``import renderers`` stays light.
"""

from __future__ import annotations

import importlib.util

import torch

from renderers import register_renderer
from renderers.base import LOW_PASS, Gaussians, Renderer, RenderOutput
from renderers.torch_reference import covariance_3d, sh_degree_from_coeffs, validate_render_inputs
from toolkit.cameras import Cameras

__all__ = ["gsplat_available", "GsplatRenderer"]


def gsplat_available() -> bool:
    """True when ``import gsplat`` succeeds and CUDA is available."""
    if importlib.util.find_spec("gsplat") is None or not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # a broken or CUDA-less build must not break the other backends
        return False
    return True


class GsplatRenderer(Renderer):
    """gsplat's CUDA tile rasterizer behind the :class:`renderers.base.Renderer` interface.

    Args:
        background: RGB added as ``(1 - alpha) * background``.
        tile_size: gsplat's tile size in pixels.
    """

    def __init__(self, background: tuple[float, float, float] = (0.0, 0.0, 0.0), tile_size: int = 16):
        super().__init__(background)
        self.tile_size = int(tile_size)

    def render(self, gaussians: Gaussians, cameras: Cameras) -> RenderOutput:
        """Render into every camera; returns float32 rgb (B, H, W, 3), alpha and depth (B, H, W)."""
        from gsplat import rasterization

        validate_render_inputs(gaussians, cameras)
        device = gaussians.means.device
        if device.type != "cuda":
            raise ValueError(f"the gsplat renderer needs Gaussians on a CUDA device, got {device}")
        cameras = cameras.to(device)
        B, H, W, N = len(cameras), cameras.height, cameras.width, len(gaussians)
        f32 = torch.float32
        background = torch.tensor(self.background, dtype=f32, device=device)
        if N == 0:
            anchor = (gaussians.means.sum() + gaussians.opacity_logits.sum()).to(f32) * 0.0
            zeros = torch.zeros(B, H, W, dtype=f32, device=device) + anchor
            return RenderOutput(rgb=background.expand(B, H, W, 3) + anchor, alpha=zeros, depth=zeros.clone())

        if gaussians.sh is not None:
            colors = gaussians.sh.to(f32).contiguous()
            sh_degree = sh_degree_from_coeffs(colors.shape[1])
        else:
            colors = gaussians.colors.to(f32).contiguous()
            sh_degree = None
        # deformed Gaussians go in as covariances A R S S^T R^T A^T (gsplat then ignores quats and scales)
        covars = None if gaussians.deformation is None else covariance_3d(
            gaussians.log_scales.to(f32), gaussians.quats.to(f32), gaussians.deformation.to(f32)).contiguous()
        render, alphas, _ = rasterization(
            means=gaussians.means.to(f32).contiguous(),
            quats=gaussians.quats.to(f32).contiguous(),
            scales=torch.exp(gaussians.log_scales.to(f32)).contiguous(),
            opacities=torch.sigmoid(gaussians.opacity_logits.to(f32)).contiguous(),
            colors=colors,
            viewmats=cameras.w2c.to(f32).contiguous(),
            Ks=cameras.K.to(f32).contiguous(),
            width=W,
            height=H,
            near_plane=cameras.near,
            far_plane=1e10,
            eps2d=LOW_PASS,
            sh_degree=sh_degree,
            packed=False,
            tile_size=self.tile_size,
            backgrounds=background.expand(B, 3).contiguous(),
            render_mode="RGB+D",
            rasterize_mode="classic",
            covars=covars,
        )
        return RenderOutput(rgb=render[..., :3], alpha=alphas[..., 0], depth=render[..., 3])


if gsplat_available():
    register_renderer("gsplat")(GsplatRenderer)

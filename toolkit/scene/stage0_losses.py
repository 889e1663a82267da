"""Training helpers of stage 0: the screen-space statistics that drive densification and a cached
SSIM (3DGS's loss term)."""

from __future__ import annotations

import torch

from toolkit.cameras import Cameras

__all__ = ["screen_space_stats"]


@torch.no_grad()
def screen_space_stats(
    means: torch.Tensor, max_scale: torch.Tensor, cameras: Cameras
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-Gaussian visibility, 2D radius and the metres-to-NDC factor for a batch of cameras.

    3DGS densifies on ``|dL/d mean2d|`` in NDC units, ``mean2d`` being the projected centre. The
    renderers here are differentiated with respect to 3D means only; since a lateral move of
    ``dx`` metres at depth ``z`` moves the projection by ``f dx / z`` pixels, i.e.
    ``2 f dx / (z W)`` NDC units, ``|dL/d ndc| ≈ |dL/dx| z W / (2 f)``. With C cameras in one loss
    the 3D gradient is the sum of the per-view ones; the factor is averaged over the cameras
    that see the Gaussian.

    Args:
        means: (N, 3) rendered positions, metres.
        max_scale: (N,) largest standard deviation, metres.
        cameras: C cameras.

    Returns:
        ``(factor (N,), visible (N,) bool, radii (N,))``: metres-to-NDC gradient factor (mean
        over the cameras that see each Gaussian), in view of at least one camera (projected 3-sigma
        disc overlaps the image, centre in front of the near plane), largest 3-sigma radius in
        pixels.
    """
    pc = cameras.world_to_camera(means)  # (C, N, 3)
    z = pc[..., 2]
    valid = z > cameras.near
    zs = torch.where(valid, z, torch.ones_like(z))
    K = cameras.K.to(means)
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    u = fx * pc[..., 0] / zs + K[:, 0, 2, None]
    v = fy * pc[..., 1] / zs + K[:, 1, 2, None]
    r = 3.0 * max_scale[None] * torch.maximum(fx, fy) / zs
    vis = valid & (u + r > 0) & (u - r < cameras.width) & (v + r > 0) & (v - r < cameras.height)
    visf = vis.to(means.dtype)
    factor_c = zs * cameras.width / (2.0 * fx)
    factor = (factor_c * visf).sum(0) / visf.sum(0).clamp_min(1.0)
    radii = (r * visf).amax(0)
    return factor, vis.any(0), radii


class _SSIM:
    """:func:`toolkit.metrics.ssim_torch` (3DGS SSIM: 11 x 11 Gaussian window, sigma 1.5, zero
    padding) with the window cached per device and dtype: building it on the CPU and copying it
    to the GPU every call would synchronize the host with the device each iteration."""

    def __init__(self, window_size: int = 11, sigma: float = 1.5):
        self.window_size, self.sigma = window_size, sigma
        self._cache: dict = {}

    def __call__(self, img: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """img, gt: (B, H, W, C) in [0, 1] -> scalar mean SSIM (differentiable)."""
        x, y = img.permute(0, 3, 1, 2), gt.to(img.dtype).permute(0, 3, 1, 2)
        c = x.shape[1]
        key = (x.device, x.dtype, c)
        w = self._cache.get(key)
        if w is None:
            from toolkit.metrics.image import gaussian_window

            w = gaussian_window(self.window_size, self.sigma, dtype=x.dtype, device=x.device)
            w = self._cache[key] = w.expand(5 * c, 1, self.window_size, self.window_size).contiguous()
        stats = torch.cat([x, y, x * x, y * y, x * y], dim=1)
        blurred = torch.nn.functional.conv2d(stats, w, padding=self.window_size // 2, groups=5 * c)
        mu_x, mu_y, e_xx, e_yy, e_xy = blurred.split(c, dim=1)
        mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
        c1, c2 = 0.01**2, 0.03**2
        ssim_map = ((2 * mu_xy + c1) * (2 * (e_xy - mu_xy) + c2)) / ((mu_xx + mu_yy + c1) * (e_xx - mu_xx + e_yy - mu_yy + c2))
        return ssim_map.mean()

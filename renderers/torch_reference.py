"""The exact pure-PyTorch reference of 3D Gaussian splatting (registered as ``"torch"``).

This backend is the ground truth the fast backends (Warp tiles, gsplat) are tested against. It
evaluates every Gaussian at every pixel centre (dense, pixel-chunked) and follows the
contribution rule of :mod:`renderers.base` literally:

1. ``Sigma = R S S^T R^T`` with ``R`` from the normalized quaternion (w, x, y, z) and
   ``S = diag(exp(log_scales))``; camera-space mean ``m = R_c x + t_c``.
2. Gaussians with ``z <= cameras.near`` contribute nothing (there is no far-plane culling).
3. EWA projection with the Jacobian of the perspective map at the camera-space mean,
   ``J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]``, where ``(tx, ty) = z * clamp(x/z, y/z)``
   (see :data:`CLAMP_MARGIN`: the clamp is gsplat's, which is 3DGS's ``1.3 tan(fov/2)`` for a
   centred principal point). ``Sigma2d = J R_c Sigma R_c^T J^T + 0.3 I``. The projected centre
   uses the unclamped mean: ``(fx x/z + cx, fy y/z + cy)``.
4. At pixel centre ``p = (i + 0.5, j + 0.5)``, ``d = p - mean2d``:
   ``alpha = min(0.99, sigmoid(logit) * exp(-0.5 d^T Sigma2d^-1 d))``; contributions with
   ``alpha < 1/255`` are skipped (they leave the transmittance unchanged).
5. Gaussians are composited front to back by camera ``z`` (stable sort: ties keep input order),
   ``T_i = prod_{j<i} (1 - alpha_j)``. Compositing stops *before* the first Gaussian for which
   ``T_i (1 - alpha_i) < 1e-4``: it and every later one contribute nothing.
6. ``w_i = alpha_i T_i``; ``rgb = sum w_i c_i + (1 - A) bg``, ``A = 1 - T_final`` (transmittance
   after the last contributing Gaussian), ``depth = sum w_i z_i``.

Colours are ``colors`` as given, or ``max(SH(dir) + 0.5, 0)`` with ``dir`` the unit vector from
the camera centre to the Gaussian mean (3DGS real SH basis up to degree 3).

Everything is plain torch (differentiable by autograd, CPU and CUDA, float32 or float64: the
computation runs in the dtype of ``gaussians.means``). Pixels are processed in chunks of at most
``chunk_elements / (B * N)`` pixels; under autograd each chunk is checkpointed, so memory stays
bounded in the backward pass too (it recomputes the chunk).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch.utils.checkpoint import checkpoint

from renderers import register_renderer
from renderers.base import ALPHA_MAX, ALPHA_MIN, LOW_PASS, T_MIN, Gaussians, Renderer, RenderOutput
from toolkit.cameras import Cameras

__all__ = [
    "TorchRenderer",
    "ProjectedGaussians",
    "quat_to_rotmat",
    "covariance_3d",
    "rotmat_to_quat",
    "bake_deformation",
    "project_gaussians",
    "eval_sh",
    "sh_degree_from_coeffs",
    "gaussian_colors",
    "validate_render_inputs",
    "SH_C0",
    "SH_C1",
    "SH_C2",
    "SH_C3",
    "CLAMP_MARGIN",
]

# Real spherical-harmonic constants used by 3DGS (utils/sh_utils.py) and gsplat.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

# Jacobian clamp (gsplat's rule, identical to 3DGS's 1.3 * tan(fov/2) when cx = W/2, cy = H/2):
#   x/z is clamped to [-(cx/fx + m * W/(2 fx)), (W - cx)/fx + m * W/(2 fx)]   with m = CLAMP_MARGIN,
#   y/z is clamped to [-(cy/fy + m * H/(2 fy)), (H - cy)/fy + m * H/(2 fy)],
# i.e. the view frustum through the image edges widened by 30% of the half field of view on each
# side. Only J sees the clamped values; the projected centre does not.
CLAMP_MARGIN = 0.3


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions.

    Args:
        quats: (..., 4) quaternions in (w, x, y, z) order; normalized here (not required to be
            unit; must be non-zero).

    Returns:
        (..., 3, 3) rotation matrices (local -> world), in the dtype of ``quats``.
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def covariance_3d(log_scales: torch.Tensor, quats: torch.Tensor, deformation: Optional[torch.Tensor] = None) -> torch.Tensor:
    """World-space covariances ``Sigma = R S S^T R^T``.

    Args:
        log_scales: (..., 3) natural logs of the standard deviations along the local axes (metres).
        quats: (..., 4) quaternions (w, x, y, z), normalized here.

    Returns:
        (..., 3, 3) symmetric covariances in m^2.
    """
    M = quat_to_rotmat(quats) * torch.exp(log_scales)[..., None, :]
    if deformation is not None:  # (..., 3, 3): Sigma = A R S S^T R^T A^T
        M = deformation @ M
    return M @ M.transpose(-1, -2)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions (w, x, y, z) with ``w >= 0`` of proper rotation matrices (..., 3, 3)
    (scipy's conversion; not differentiable)."""
    from scipy.spatial.transform import Rotation

    m = R.detach().cpu().double().reshape(-1, 3, 3).numpy()
    xyzw = torch.from_numpy(Rotation.from_matrix(m).as_quat())
    q = torch.cat([xyzw[:, 3:], xyzw[:, :3]], dim=1)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(R.shape[:-2] + (4,)).to(dtype=R.dtype, device=R.device)


def bake_deformation(gaussians: Gaussians) -> Gaussians:
    """The same Gaussians with each ``deformation`` folded into its scales and rotation.

    ``A R S = U diag(sigma) V^T`` (SVD) gives the covariance ``U diag(sigma)^2 U^T``: rotation
    ``U`` (a column flipped when ``det U < 0``) and scales ``sigma``. For files and renderers that
    only take scales and rotations (3DGS PLY). Not meant for gradients (singular vectors are not
    differentiable where two scales coincide). Gaussians without a deformation come back as they are.
    """
    if gaussians.deformation is None:
        return gaussians
    with torch.no_grad():
        M = gaussians.deformation.double() @ (quat_to_rotmat(gaussians.quats.double())
                                              * torch.exp(gaussians.log_scales.double())[..., None, :])
        U, sigma, _ = torch.linalg.svd(M)
        flip = torch.linalg.det(U) < 0
        U[flip, :, 2] = -U[flip, :, 2]
        quats = rotmat_to_quat(U).to(gaussians.quats.dtype)
        log_scales = torch.log(sigma.clamp_min(1e-30)).to(gaussians.log_scales.dtype)
    return gaussians.replace(quats=quats, log_scales=log_scales, deformation=None)


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    """SH degree for K = (degree + 1)^2 coefficients (K in 1, 4, 9, 16)."""
    degree = {1: 0, 4: 1, 9: 2, 16: 3}.get(int(num_coeffs))
    if degree is None:
        raise ValueError(f"the number of SH coefficients must be 1, 4, 9 or 16, got {num_coeffs}")
    return degree


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate real spherical harmonics as 3DGS does (no +0.5 offset, no clamp).

    Args:
        degree: SH degree in 0..3; uses the first ``(degree + 1)^2`` coefficients.
        sh: (..., K, 3) coefficients per colour channel, ``K >= (degree + 1)^2``.
        dirs: (..., 3) unit view directions (from the camera centre towards the Gaussian), world
            frame; broadcast against ``sh[..., 0, :]``.

    Returns:
        (..., 3) the SH expansion ``sum_k c_k Y_k(dir)``.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    if sh.shape[-2] < (degree + 1) ** 2:
        raise ValueError(f"degree {degree} needs {(degree + 1) ** 2} SH coefficients, got {sh.shape[-2]}")
    result = SH_C0 * sh[..., 0, :]
    if degree == 0:
        return result
    x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
    result = result - SH_C1 * y * sh[..., 1, :] + SH_C1 * z * sh[..., 2, :] - SH_C1 * x * sh[..., 3, :]
    if degree == 1:
        return result
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    result = (
        result
        + SH_C2[0] * xy * sh[..., 4, :]
        + SH_C2[1] * yz * sh[..., 5, :]
        + SH_C2[2] * (2.0 * zz - xx - yy) * sh[..., 6, :]
        + SH_C2[3] * xz * sh[..., 7, :]
        + SH_C2[4] * (xx - yy) * sh[..., 8, :]
    )
    if degree == 2:
        return result
    return (
        result
        + SH_C3[0] * y * (3.0 * xx - yy) * sh[..., 9, :]
        + SH_C3[1] * xy * z * sh[..., 10, :]
        + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[..., 11, :]
        + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[..., 12, :]
        + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[..., 13, :]
        + SH_C3[5] * z * (xx - yy) * sh[..., 14, :]
        + SH_C3[6] * x * (xx - 3.0 * yy) * sh[..., 15, :]
    )


def gaussian_colors(gaussians: Gaussians, cameras: Cameras) -> torch.Tensor:
    """Per-camera RGB of every Gaussian.

    Returns:
        (B, N, 3): ``colors`` broadcast over cameras, or, when ``sh`` is set,
        ``max(eval_sh(deg, sh, dir) + 0.5, 0)`` with ``dir = normalize(mean - camera_centre)``.
    """
    B, N = len(cameras), len(gaussians)
    if gaussians.sh is None:
        return gaussians.colors[None].expand(B, N, 3)
    dtype = gaussians.means.dtype
    degree = sh_degree_from_coeffs(gaussians.sh.shape[1])
    dirs = gaussians.means[None] - cameras.centers.to(dtype)[:, None, :]  # (B, N, 3)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(dtype).tiny ** 0.5)
    rgb = eval_sh(degree, gaussians.sh[None].expand(B, -1, -1, -1), dirs)
    return (rgb + 0.5).clamp_min(0.0)


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians for a batch of B cameras (entries with ``valid == False`` are finite
    placeholders and must be ignored).

    Attributes:
        means2d: (B, N, 2) projected centres ``(u, v)`` in pixels (pixel ``(i, j)``'s centre is at
            ``(i + 0.5, j + 0.5)``).
        cov2d: (B, N, 2, 2) projected covariances in px^2, low-pass ``0.3 I`` included.
        conic: (B, N, 2, 2) inverses of ``cov2d``.
        depths: (B, N) camera-space ``z`` of the centres (metres).
        valid: (B, N) bool, ``z > near``.
        radius: (B, N) opacity-aware pixel radius, detached: at a distance from ``means2d``
            greater than ``sqrt(2 ln(255 opacity) lambda_max(cov2d))`` the alpha is below 1/255
            (up to floating-point rounding: tile backends should add a small margin). 0 when
            invalid or ``opacity < 1/255``.
    """

    means2d: torch.Tensor
    cov2d: torch.Tensor
    conic: torch.Tensor
    depths: torch.Tensor
    valid: torch.Tensor
    radius: torch.Tensor


def project_gaussians(gaussians: Gaussians, cameras: Cameras) -> ProjectedGaussians:
    """EWA-project the Gaussians into every camera (steps 1-3 of the module docstring).

    Args:
        gaussians: N Gaussians; the result has their dtype and device.
        cameras: B cameras (moved to the Gaussians' device and dtype).

    Returns:
        :class:`ProjectedGaussians` with (B, N, ...) tensors, differentiable with respect to
        ``means``, ``log_scales`` and ``quats`` (``radius`` excepted).
    """
    dtype, device = gaussians.means.dtype, gaussians.means.device
    K = cameras.K.to(device=device, dtype=dtype)
    w2c = cameras.w2c.to(device=device, dtype=dtype)
    Rc, tc = w2c[:, :3, :3], w2c[:, :3, 3]
    W, H = float(cameras.width), float(cameras.height)

    mc = torch.einsum("bij,nj->bni", Rc, gaussians.means) + tc[:, None, :]  # (B, N, 3)
    x, y, z = mc.unbind(-1)
    valid = z > cameras.near
    z_safe = torch.where(valid, z, torch.ones_like(z))  # keeps the discarded branch finite for autograd

    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]  # (B, 1)
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    u = fx * x / z_safe + cx
    v = fy * y / z_safe + cy
    means2d = torch.stack([u, v], -1)

    tan_half_x = 0.5 * W / fx
    tan_half_y = 0.5 * H / fy
    lim_x_pos = (W - cx) / fx + CLAMP_MARGIN * tan_half_x
    lim_x_neg = cx / fx + CLAMP_MARGIN * tan_half_x
    lim_y_pos = (H - cy) / fy + CLAMP_MARGIN * tan_half_y
    lim_y_neg = cy / fy + CLAMP_MARGIN * tan_half_y
    tx = z_safe * torch.minimum(torch.maximum(x / z_safe, -lim_x_neg), lim_x_pos)
    ty = z_safe * torch.minimum(torch.maximum(y / z_safe, -lim_y_neg), lim_y_pos)

    zero = torch.zeros_like(z_safe)
    J = torch.stack(
        [
            torch.stack([fx / z_safe, zero, -fx * tx / (z_safe * z_safe)], -1),
            torch.stack([zero, fy / z_safe, -fy * ty / (z_safe * z_safe)], -1),
        ],
        -2,
    )  # (B, N, 2, 3)
    cov3d = covariance_3d(gaussians.log_scales, gaussians.quats, gaussians.deformation)  # (N, 3, 3)
    cov_cam = torch.einsum("bij,njk,blk->bnil", Rc, cov3d, Rc)  # (B, N, 3, 3)
    cov2d = J @ cov_cam @ J.transpose(-1, -2)
    cov2d = cov2d + LOW_PASS * torch.eye(2, dtype=dtype, device=device)

    a, b, c = cov2d[..., 0, 0], 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0]), cov2d[..., 1, 1]
    det = a * c - b * b
    conic = torch.stack([torch.stack([c, -b], -1), torch.stack([-b, a], -1)], -2) / det[..., None, None]

    with torch.no_grad():
        opacity = torch.sigmoid(gaussians.opacity_logits)[None].expand_as(z)
        lam_max = 0.5 * (a + c) + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
        log_term = torch.log((255.0 * opacity).clamp_min(1.0))  # 0 where opacity < 1/255
        radius = torch.sqrt(2.0 * log_term * lam_max)
        radius = torch.where(valid & (opacity >= ALPHA_MIN), radius, torch.zeros_like(radius))

    return ProjectedGaussians(means2d=means2d, cov2d=cov2d, conic=conic, depths=z, valid=valid, radius=radius)


def _composite_chunk(
    px: torch.Tensor,
    py: torch.Tensor,
    means2d: torch.Tensor,
    conic: torch.Tensor,
    opacity: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    valid: torch.Tensor,
    background: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite depth-sorted Gaussians at P pixel centres for B cameras.

    Shapes: px, py (P,); means2d (B, M, 2); conic (B, M, 2, 2); opacity, depths, valid (B, M);
    colors (B, M, 3); background (3,). Returns rgb (B, P, 3), alpha (B, P), depth (B, P).
    """
    dx = px[None, :, None] - means2d[:, None, :, 0]  # (B, P, M)
    dy = py[None, :, None] - means2d[:, None, :, 1]
    ca, cb, cc = conic[:, None, :, 0, 0], conic[:, None, :, 0, 1], conic[:, None, :, 1, 1]
    power = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    alpha = (opacity[:, None, :] * torch.exp(-power)).clamp_max(ALPHA_MAX)
    contributes = valid[:, None, :] & (alpha >= ALPHA_MIN)
    alpha = torch.where(contributes, alpha, torch.zeros_like(alpha))
    # Cut-off: T only decreases, so "before the first Gaussian that would bring T below T_MIN"
    # is exactly "the inclusive transmittance is still >= T_MIN".
    with torch.no_grad():
        alive = torch.cumprod(1.0 - alpha, dim=-1) >= T_MIN
    alpha = torch.where(alive, alpha, torch.zeros_like(alpha))
    trans_incl = torch.cumprod(1.0 - alpha, dim=-1)
    trans_excl = torch.cat([torch.ones_like(trans_incl[..., :1]), trans_incl[..., :-1]], dim=-1)
    weights = alpha * trans_excl
    acc = 1.0 - trans_incl[..., -1]
    rgb = torch.einsum("bpm,bmc->bpc", weights, colors) + (1.0 - acc)[..., None] * background
    depth = torch.einsum("bpm,bm->bp", weights, depths)
    return rgb, acc, depth


@register_renderer("torch")
class TorchRenderer(Renderer):
    """Dense pure-PyTorch 3DGS reference (exact contribution rule of :mod:`renderers.base`).

    Args:
        background: RGB added as ``(1 - alpha) * background``.
        chunk_elements: at most this many pixel x Gaussian x camera elements per chunk. Peak
            memory is about a dozen tensors of this size (times the dtype's bytes).
        checkpoint: recompute each chunk in the backward pass instead of keeping its
            intermediates (memory O(chunk) instead of O(B H W N)).
    """

    def __init__(
        self,
        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
        chunk_elements: int = 2**22,
        checkpoint: bool = True,
    ):
        super().__init__(background)
        if int(chunk_elements) < 1:
            raise ValueError(f"chunk_elements must be >= 1, got {chunk_elements}")
        self.chunk_elements = int(chunk_elements)
        self.checkpoint = bool(checkpoint)

    def render(self, gaussians: Gaussians, cameras: Cameras) -> RenderOutput:
        """Render ``gaussians`` into every camera of ``cameras``.

        Returns:
            :class:`RenderOutput` with rgb (B, H, W, 3), alpha (B, H, W), depth (B, H, W) in the
            dtype and on the device of ``gaussians.means``.
        """
        validate_render_inputs(gaussians, cameras)
        dtype, device = gaussians.means.dtype, gaussians.means.device
        cameras = cameras.to(device)
        B, H, W, N = len(cameras), cameras.height, cameras.width, len(gaussians)
        background = torch.tensor(self.background, dtype=dtype, device=device)

        if N == 0:
            return _background_only(gaussians, B, H, W, background)

        proj = project_gaussians(gaussians, cameras)
        colors = gaussian_colors(gaussians, cameras)
        opacity = torch.sigmoid(gaussians.opacity_logits)[None].expand(B, N)

        # Front-to-back order per camera; culled Gaussians go last and are then dropped.
        key = torch.where(proj.valid, proj.depths, torch.full_like(proj.depths, math.inf))
        order = torch.sort(key, dim=-1, stable=True).indices
        m = int(proj.valid.sum(-1).max())
        if m == 0:
            return _background_only(gaussians, B, H, W, background)
        order = order[:, :m]

        def take(t: torch.Tensor) -> torch.Tensor:
            idx = order.reshape(order.shape + (1,) * (t.ndim - 2)).expand(order.shape + t.shape[2:])
            return torch.gather(t, 1, idx)

        means2d, conic, depths = take(proj.means2d), take(proj.conic), take(proj.depths)
        valid, opac, cols = take(proj.valid), take(opacity), take(colors)

        n_pix = H * W
        chunk = max(1, min(n_pix, self.chunk_elements // max(1, B * m)))
        use_ckpt = self.checkpoint and torch.is_grad_enabled() and n_pix > chunk
        rgbs, alphas, depth_out = [], [], []
        for start in range(0, n_pix, chunk):
            idx = torch.arange(start, min(start + chunk, n_pix), device=device)
            px = (idx % W).to(dtype) + 0.5
            py = torch.div(idx, W, rounding_mode="floor").to(dtype) + 0.5
            args = (px, py, means2d, conic, opac, cols, depths, valid, background)
            if use_ckpt:
                out = checkpoint(_composite_chunk, *args, use_reentrant=False)
            else:
                out = _composite_chunk(*args)
            rgbs.append(out[0])
            alphas.append(out[1])
            depth_out.append(out[2])
        return RenderOutput(
            rgb=torch.cat(rgbs, 1).reshape(B, H, W, 3),
            alpha=torch.cat(alphas, 1).reshape(B, H, W),
            depth=torch.cat(depth_out, 1).reshape(B, H, W),
        )


def _background_only(gaussians: Gaussians, B: int, H: int, W: int, background: torch.Tensor) -> RenderOutput:
    """Images with nothing rendered, still attached to the inputs' graph so backward() works."""
    anchor = (gaussians.means.sum() + gaussians.opacity_logits.sum()) * 0.0
    zeros = torch.zeros(B, H, W, dtype=background.dtype, device=background.device) + anchor
    return RenderOutput(rgb=background.expand(B, H, W, 3) + anchor, alpha=zeros, depth=zeros.clone())


def validate_render_inputs(gaussians: Gaussians, cameras: Cameras) -> None:
    """Input checks shared by the backends.

    Raises:
        TypeError: ``gaussians`` is not :class:`Gaussians` or ``cameras`` not :class:`Cameras`.
        ValueError: wrong shapes, NaN/inf, mixed dtypes or devices, zero-norm quaternions,
            malformed cameras (messages name the attribute and the first bad rows).
    """
    if not isinstance(gaussians, Gaussians):
        raise TypeError(f"gaussians must be renderers.base.Gaussians, got {type(gaussians).__name__}")
    if not isinstance(cameras, Cameras):
        raise TypeError(f"cameras must be toolkit.cameras.Cameras, got {type(cameras).__name__}")
    gaussians.validate()
    cameras.validate()
    dtype = gaussians.means.dtype
    for name in ("log_scales", "quats", "opacity_logits", "colors", "sh", "deformation"):
        t = getattr(gaussians, name)
        if t is not None and t.dtype != dtype:
            raise ValueError(f"Gaussians.{name} has dtype {t.dtype} but means have {dtype}; use one dtype")
    if len(gaussians):
        qn = gaussians.quats.detach().norm(dim=-1)
        bad = qn <= torch.finfo(dtype).tiny
        if bad.any():
            raise ValueError(f"Gaussians.quats has zero-norm rows (first rows: {bad.nonzero()[:5, 0].tolist()})")

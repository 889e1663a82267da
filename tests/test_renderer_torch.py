"""renderers.torch_reference: the exact 3DGS reference (contribution rule, geometry, gradients)."""

from __future__ import annotations

import math

import pytest
import torch

from renderers import RENDERERS
from renderers.base import ALPHA_MIN, Gaussians
from renderers.torch_reference import (
    SH_C0,
    SH_C1,
    TorchRenderer,
    covariance_3d,
    eval_sh,
    project_gaussians,
    quat_to_rotmat,
)
from toolkit.cameras import Cameras

F64 = torch.float64


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _axis_camera(width: int = 9, height: int = 9, f: float = 10.0, near: float = 0.01) -> Cameras:
    """Camera at the origin looking down +z (w2c = I); the optical axis hits pixel centre ((W-1)/2 + .5, ...)."""
    K = [[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]]
    return Cameras(K, torch.eye(4), width, height, near=near)


def _on_axis(zs, scale: float, opacities, colors, dtype=F64, device="cpu") -> Gaussians:
    """Isotropic Gaussians on the optical axis of :func:`_axis_camera` at depths ``zs``."""
    n = len(zs)
    means = torch.zeros(n, 3, dtype=dtype, device=device)
    means[:, 2] = torch.tensor(zs, dtype=dtype)
    return Gaussians(
        means=means,
        log_scales=torch.full((n, 3), math.log(scale), dtype=dtype, device=device),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype, device=device),
        opacity_logits=torch.tensor([_logit(o) for o in opacities], dtype=dtype, device=device),
        colors=torch.tensor(colors, dtype=dtype, device=device),
    )


def _random_gaussians(n: int, seed: int = 0, dtype=F64, sh_coeffs: int = 0, spread: float = 0.4) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    sh = None
    if sh_coeffs:
        sh = 0.3 * torch.randn(n, sh_coeffs, 3, generator=g, dtype=dtype)
        sh[:, 0] += 0.5
    return Gaussians(
        means=spread * torch.randn(n, 3, generator=g, dtype=dtype),
        log_scales=math.log(0.25) + 0.3 * torch.randn(n, 3, generator=g, dtype=dtype),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        opacity_logits=0.5 * torch.randn(n, generator=g, dtype=dtype),
        colors=torch.rand(n, 3, generator=g, dtype=dtype),
        sh=sh,
    )


def _two_cameras(width: int = 16, height: int = 12) -> Cameras:
    eyes = torch.tensor([[0.0, 0.3, 4.0], [2.5, 1.0, 3.0]])
    return Cameras.look_at(eyes, (0.0, 0.0, 0.0), fov_y_deg=40.0, width=width, height=height)


def test_registered_as_torch():
    assert RENDERERS.get("torch") is TorchRenderer


# ---------------------------------------------------------------- gradients


def _finite_difference_check(g: Gaussians, cams: Cameras, names: list[str], renderer: TorchRenderer) -> None:
    gen = torch.Generator().manual_seed(7)
    B, H, W = len(cams), cams.height, cams.width
    w_rgb = torch.randn(B, H, W, 3, generator=gen, dtype=F64)
    w_alpha = torch.randn(B, H, W, generator=gen, dtype=F64)
    w_depth = torch.randn(B, H, W, generator=gen, dtype=F64)

    def loss(gs: Gaussians) -> torch.Tensor:
        out = renderer(gs, cams)
        return (out.rgb * w_rgb).sum() + (out.alpha * w_alpha).sum() + 0.3 * (out.depth * w_depth).sum()

    params = {n: getattr(g, n).detach().clone().requires_grad_(True) for n in names}
    loss(g.replace(**params)).backward()
    eps = 1e-6
    for name in names:
        analytic = params[name].grad
        base = getattr(g, name).detach()
        numeric = torch.zeros_like(base)
        flat = numeric.view(-1)
        for i in range(base.numel()):
            plus, minus = base.clone(), base.clone()
            plus.view(-1)[i] += eps
            minus.view(-1)[i] -= eps
            with torch.no_grad():
                flat[i] = (loss(g.replace(**{name: plus})) - loss(g.replace(**{name: minus}))) / (2 * eps)
        scale = numeric.abs().max().clamp_min(1e-3)
        err = (analytic - numeric).abs().max() / scale
        assert numeric.abs().max() > 1e-3, f"{name} has no effect on the loss: the test scene is degenerate"
        assert err < 1e-5, f"gradient of {name}: max relative error {err:.2e}\nanalytic {analytic}\nnumeric {numeric}"


def test_gradients_match_finite_differences_colors():
    g = _random_gaussians(4, seed=1)
    cams = _two_cameras()
    _finite_difference_check(g, cams, ["means", "log_scales", "quats", "opacity_logits", "colors"], TorchRenderer())


def test_gradients_match_finite_differences_sh_and_chunks():
    g = _random_gaussians(3, seed=2, sh_coeffs=16)
    cams = _two_cameras(width=12, height=10)
    # tiny chunks: exercises pixel chunking and per-chunk checkpointing in the backward pass
    _finite_difference_check(g, cams, ["means", "sh", "quats"], TorchRenderer(background=(0.2, 0.4, 0.6), chunk_elements=50))


def test_chunking_and_checkpointing_do_not_change_results():
    g = _random_gaussians(20, seed=3, dtype=torch.float32)
    cams = _two_cameras()
    outs, grads = [], []
    for r in (TorchRenderer(), TorchRenderer(chunk_elements=97), TorchRenderer(chunk_elements=97, checkpoint=False)):
        means = g.means.clone().requires_grad_(True)
        out = r(g.replace(means=means), cams)
        (out.rgb.sum() + out.depth.sum()).backward()
        outs.append(out)
        grads.append(means.grad)
    for out, grad in zip(outs[1:], grads[1:]):
        assert torch.allclose(out.rgb, outs[0].rgb, atol=1e-6)
        assert torch.allclose(out.depth, outs[0].depth, atol=1e-6)
        assert torch.allclose(grad, grads[0], rtol=1e-4, atol=1e-5)


def test_batch_equals_individual_cameras(device):
    g = _random_gaussians(30, seed=4, dtype=torch.float32).to(device)
    cams = _two_cameras().to(device)
    r = TorchRenderer(background=(0.1, 0.2, 0.3))
    both = r(g, cams)
    for b in range(len(cams)):
        one = r(g, cams[b])
        assert torch.allclose(both.rgb[b], one.rgb[0], atol=1e-6)
        assert torch.allclose(both.alpha[b], one.alpha[0], atol=1e-6)
        assert torch.allclose(both.depth[b], one.depth[0], atol=1e-5)


# ---------------------------------------------------------------- geometry of a single splat


def _single_splat_scene():
    # camera at (0, 0, 5) looking at the origin, f = 64 px, principal point at the image centre
    K = [[64.0, 0.0, 32.0], [0.0, 64.0, 32.0], [0.0, 0.0, 1.0]]
    cam = Cameras.look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), K=K, width=64, height=64)
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    axis = axis / axis.norm()
    half = 0.6
    quat = torch.cat([torch.tensor([math.cos(half)], dtype=F64), math.sin(half) * axis])[None]
    opacity = 0.9  # peak alpha 0.9 < 0.99: nothing clips
    g = Gaussians(
        means=torch.tensor([[0.1, -0.05, 0.2]], dtype=F64),
        log_scales=torch.log(torch.tensor([[0.3, 0.15, 0.2]], dtype=F64)),
        quats=quat,
        opacity_logits=torch.tensor([_logit(opacity)], dtype=F64),
        colors=torch.ones(1, 3, dtype=F64),
    )
    return g, cam, opacity


def test_projected_covariance_matches_linearized_camera_projection():
    g, cam, _ = _single_splat_scene()
    proj = project_gaussians(g, cam)
    # independent linearization: the Jacobian of Cameras.project at the mean (autograd)
    J = torch.autograd.functional.jacobian(lambda x: cam.project(x[None])[0][0, 0], g.means[0])  # (2, 3)
    cov = covariance_3d(g.log_scales, g.quats)[0]
    expected = J @ cov @ J.T + 0.3 * torch.eye(2, dtype=F64)
    assert torch.allclose(proj.cov2d[0, 0], expected, rtol=1e-5, atol=1e-6)
    assert torch.allclose(proj.means2d[0, 0], cam.project(g.means)[0][0, 0].to(F64), atol=1e-5)
    assert torch.allclose(proj.conic[0, 0] @ proj.cov2d[0, 0], torch.eye(2, dtype=F64), atol=1e-10)
    # on the optical axis by hand: cam coords (0, 0, 5), J = diag(64/5), Sigma2d = (64 s / 5)^2 + 0.3
    on_axis = g.replace(means=torch.zeros(1, 3, dtype=F64), log_scales=torch.full((1, 3), math.log(0.2), dtype=F64))
    c2 = project_gaussians(on_axis, cam).cov2d[0, 0]
    assert torch.allclose(c2, ((64 * 0.2 / 5) ** 2 + 0.3) * torch.eye(2, dtype=F64), atol=1e-4)


def test_single_gaussian_centroid_and_footprint():
    g, cam, opacity = _single_splat_scene()
    out = TorchRenderer()(g, cam)
    proj = project_gaussians(g, cam)
    mu, cov = proj.means2d[0, 0], proj.cov2d[0, 0]
    a = out.alpha[0]
    jj, ii = torch.meshgrid(torch.arange(64, dtype=F64), torch.arange(64, dtype=F64), indexing="ij")
    pix = torch.stack([ii + 0.5, jj + 0.5], -1)  # pixel centres (u, v)
    mass = a.sum()
    centroid = (a[..., None] * pix).sum((0, 1)) / mass
    assert (centroid - mu).abs().max() < 0.05, f"centroid {centroid.tolist()} vs projected mean {mu.tolist()}"
    d = pix - mu
    second = (a[..., None, None] * d[..., :, None] * d[..., None, :]).sum((0, 1)) / mass
    # alpha is cut where it drops below 1/255, i.e. at Mahalanobis radius^2 = 2 c with
    # c = ln(255 * opacity); a 2D Gaussian truncated there has covariance Sigma * f,
    # f = (1 - e^-c (1 + c)) / (1 - e^-c)
    c = math.log(255.0 * opacity)
    f = (1.0 - math.exp(-c) * (1.0 + c)) / (1.0 - math.exp(-c))
    rel = (second - f * cov).abs().max() / cov.abs().max()
    assert rel < 0.02, f"second moments {second.tolist()} vs {(f * cov).tolist()}"
    # the peak value is the opacity (up to the offset of the nearest pixel centre)
    assert 0.8 < float(a.max()) <= opacity + 1e-12


def test_radius_bounds_the_footprint():
    g = _random_gaussians(12, seed=5)
    cams = _two_cameras(width=32, height=24)
    proj = project_gaussians(g, cams)
    r = TorchRenderer()
    jj, ii = torch.meshgrid(torch.arange(24, dtype=F64), torch.arange(32, dtype=F64), indexing="ij")
    pix = torch.stack([ii + 0.5, jj + 0.5], -1)
    for n in range(len(g)):
        one = Gaussians(**{k: v[n : n + 1] for k, v in vars(g).items() if v is not None})
        out = r(one, cams)
        for b in range(len(cams)):
            dist = (pix - proj.means2d[b, n]).norm(dim=-1)
            covered = out.alpha[b] > 0
            if covered.any():
                assert dist[covered].max() <= proj.radius[b, n] + 1e-6
    low = g.replace(opacity_logits=torch.full((12,), _logit(0.5 / 255), dtype=F64))
    assert (project_gaussians(low, cams).radius == 0).all()


# ---------------------------------------------------------------- visibility


def test_no_gaussians_gives_background(device):
    empty = Gaussians(
        means=torch.zeros(0, 3, device=device, requires_grad=True),
        log_scales=torch.zeros(0, 3, device=device),
        quats=torch.zeros(0, 4, device=device),
        opacity_logits=torch.zeros(0, device=device, requires_grad=True),
        colors=torch.zeros(0, 3, device=device),
    )
    out = TorchRenderer(background=(0.25, 0.5, 1.0))(empty, _two_cameras().to(device))
    assert out.rgb.shape == (2, 12, 16, 3) and out.alpha.shape == (2, 12, 16) and out.depth.shape == (2, 12, 16)
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    assert torch.equal(out.rgb[0, 0, 0].cpu(), torch.tensor([0.25, 0.5, 1.0]))
    out.rgb.sum().backward()  # stays attached to the graph
    assert empty.means.grad.shape == (0, 3)


def test_gaussian_behind_camera_or_before_near_contributes_nothing(device):
    cam = _axis_camera(near=0.5).to(device)
    for z in (-2.0, 0.0, 0.3, 0.5):  # behind, at the centre, before and exactly at the near plane
        g = _on_axis([z], scale=1.0, opacities=[0.9], colors=[[1.0, 0.0, 0.0]], dtype=torch.float32, device=device)
        out = TorchRenderer()(g, cam)
        assert (out.alpha == 0).all(), f"Gaussian at z={z} contributed"
    g = _on_axis([0.6], scale=0.05, opacities=[0.9], colors=[[1.0, 0.0, 0.0]], dtype=torch.float32, device=device)
    assert TorchRenderer()(g, cam).alpha.max() > 0.5


def test_opaque_front_gaussian_hides_back_one_independent_of_order(device):
    cam = _axis_camera().to(device)
    red, green = [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    front_first = _on_axis([2.0, 4.0], 0.2, [0.9999, 0.5], [red, green], device=device)
    back_first = _on_axis([4.0, 2.0], 0.2, [0.5, 0.9999], [green, red], device=device)
    r = TorchRenderer()
    a, b = r(front_first, cam), r(back_first, cam)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha) and torch.equal(a.depth, b.depth)
    # centre pixel (4, 4): front alpha clamps at 0.99; the back one (alpha 0.5) sees T = 0.01
    centre = a.rgb[0, 4, 4].cpu()
    assert torch.allclose(centre, torch.tensor([0.99, 0.01 * 0.5, 0.0], dtype=F64), atol=1e-12)
    assert torch.allclose(a.depth[0, 4, 4].cpu(), torch.tensor(0.99 * 2.0 + 0.005 * 4.0, dtype=F64), atol=1e-12)
    assert torch.allclose(a.alpha[0, 4, 4].cpu(), torch.tensor(1 - 0.01 * 0.5, dtype=F64), atol=1e-12)


def test_equal_depths_keep_input_order():
    cam = _axis_camera()
    red, green = [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    out = TorchRenderer()(_on_axis([3.0, 3.0], 0.2, [0.5, 0.5], [red, green]), cam)
    # stable sort: the first input is in front -> 0.5 red + 0.25 green at the centre pixel
    assert torch.allclose(out.rgb[0, 4, 4], torch.tensor([0.5, 0.25, 0.0], dtype=F64), atol=1e-12)


# ---------------------------------------------------------------- thresholds, by hand
#
# _axis_camera: fx = fy = 10, w2c = I, principal point (4.5, 4.5) = centre of pixel (4, 4).
# A Gaussian on the axis at depth z with isotropic scale s has mean2d (4.5, 4.5) and
# Sigma2d = (fx s / z)^2 I + 0.3 I; with s = 0.2, z = 2: Sigma2d = 1.3 I, so
# alpha(pixel at offset d px) = opacity * exp(-0.5 |d|^2 / 1.3).


def test_transmittance_cutoff_by_hand(device):
    cam = _axis_camera().to(device)
    cols = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]]
    zs = [2.0, 3.0, 4.0, 5.0]
    # small scale: at the centre pixel d = 0 so alpha = opacity exactly
    # T: 1 -> 0.01 (0.99) -> 2e-4 (0.98) -> 0.6 would give 8e-5 < 1e-4: stop before it;
    # the 4th (0.1, would give 1.8e-4 from 2e-4) comes after the stop and contributes nothing.
    g = _on_axis(zs, 0.01, [0.99, 0.98, 0.6, 0.1], cols, device=device)
    out = TorchRenderer()(g, cam)
    expect_rgb = 0.99 * torch.tensor(cols[0], dtype=F64) + 0.01 * 0.98 * torch.tensor(cols[1], dtype=F64)
    assert torch.allclose(out.rgb[0, 4, 4].cpu(), expect_rgb, atol=1e-10)
    assert torch.allclose(out.alpha[0, 4, 4].cpu(), torch.tensor(1 - 2e-4, dtype=F64), atol=1e-10)
    assert torch.allclose(out.depth[0, 4, 4].cpu(), torch.tensor(0.99 * 2 + 0.0098 * 3, dtype=F64), atol=1e-10)
    # control: third opacity 0.4 -> T 2e-4 -> 1.2e-4 (contributes) -> 1.08e-4 (4th contributes too)
    g = _on_axis(zs, 0.01, [0.99, 0.98, 0.4, 0.1], cols, device=device)
    out = TorchRenderer()(g, cam)
    w = torch.tensor([0.99, 0.01 * 0.98, 2e-4 * 0.4, 1.2e-4 * 0.1], dtype=F64)
    assert torch.allclose(out.rgb[0, 4, 4].cpu(), (w[:, None] * torch.tensor(cols, dtype=F64)).sum(0), atol=1e-10)
    assert torch.allclose(out.alpha[0, 4, 4].cpu(), torch.tensor(1 - 1.08e-4, dtype=F64), atol=1e-10)
    # float32 still takes the same decisions (the margins are far from rounding)
    g32 = _on_axis(zs, 0.01, [0.99, 0.98, 0.6, 0.1], cols, dtype=torch.float32, device=device)
    out32 = TorchRenderer()(g32, cam)
    assert torch.allclose(out32.rgb[0, 4, 4].cpu(), expect_rgb.float(), atol=1e-5)


def test_alpha_threshold_and_clamp_by_hand(device):
    cam = _axis_camera().to(device)
    o = 0.02
    out = TorchRenderer()(_on_axis([2.0], 0.2, [o], [[1.0, 1.0, 1.0]], device=device), cam)
    jj, ii = torch.meshgrid(torch.arange(9, dtype=F64), torch.arange(9, dtype=F64), indexing="ij")
    d2 = (ii - 4.0) ** 2 + (jj - 4.0) ** 2
    raw = o * torch.exp(-0.5 * d2 / 1.3)
    # centre 0.02; 1 px: 0.0136; sqrt2: 0.0093; 2 px: 0.0043 (>= 1/255 = 0.00392, kept);
    # sqrt5 px: 0.0029 (< 1/255, dropped although the Gaussian is non-zero there)
    expected = torch.where(raw >= ALPHA_MIN, raw, torch.zeros_like(raw))
    assert torch.allclose(out.alpha[0].cpu(), expected, atol=1e-12)
    assert out.alpha[0, 4, 6] > 0 and out.alpha[0, 5, 6] == 0 and raw[5, 6] > 0
    # opacity just below 1/255: nothing anywhere; just above: only the centre pixel
    below = TorchRenderer()(_on_axis([2.0], 0.2, [0.999 / 255], [[1.0, 1.0, 1.0]], device=device), cam)
    assert (below.alpha == 0).all()
    above = TorchRenderer()(_on_axis([2.0], 0.2, [1.01 / 255], [[1.0, 1.0, 1.0]], device=device), cam)
    assert (above.alpha > 0).sum() == 1 and torch.isclose(above.alpha[0, 4, 4].cpu(), torch.tensor(1.01 / 255, dtype=F64))
    # opacity sigmoid(8) = 0.99966 clamps at 0.99 at the centre
    clamped = TorchRenderer()(_on_axis([2.0], 0.2, [1 / (1 + math.exp(-8))], [[1.0, 1.0, 1.0]], device=device), cam)
    assert torch.isclose(clamped.alpha[0, 4, 4].cpu(), torch.tensor(0.99, dtype=F64), atol=1e-12)


def test_jacobian_clamp_outside_frustum():
    # a Gaussian far outside the image: its J uses x/z clamped to (W - cx)/fx + 0.3 W/(2 fx)
    cam = _axis_camera()
    g = _on_axis([2.0], 0.2, [0.5], [[1.0, 1.0, 1.0]])
    g = g.replace(means=torch.tensor([[10.0, 0.0, 2.0]], dtype=F64))
    proj = project_gaussians(g, cam)
    lim = (9 - 4.5) / 10 + 0.3 * 4.5 / 10  # 0.585
    tx = 2.0 * lim
    J = torch.tensor([[10 / 2.0, 0.0, -10 * tx / 4.0], [0.0, 10 / 2.0, 0.0]], dtype=F64)
    expected = J @ (0.04 * torch.eye(3, dtype=F64)) @ J.T + 0.3 * torch.eye(2, dtype=F64)
    assert torch.allclose(proj.cov2d[0, 0], expected, atol=1e-6)
    assert torch.allclose(proj.means2d[0, 0], torch.tensor([10 * 10 / 2.0 + 4.5, 4.5], dtype=F64), atol=1e-6)


# ---------------------------------------------------------------- colours


def test_sh_degree_zero_is_constant_colour(device):
    g = _random_gaussians(10, seed=6, dtype=torch.float32).to(device)
    sh = torch.randn(10, 1, 3, generator=torch.Generator().manual_seed(1)).to(device)
    cams = _two_cameras().to(device)
    r = TorchRenderer(background=(0.3, 0.3, 0.3))
    with_sh = r(g.replace(sh=sh, colors=None), cams)
    with_rgb = r(g.replace(colors=(SH_C0 * sh[:, 0] + 0.5).clamp_min(0.0)), cams)
    assert torch.allclose(with_sh.rgb, with_rgb.rgb, atol=1e-6)
    # degree 3 with zero higher bands equals degree 0
    sh16 = torch.cat([sh, torch.zeros(10, 15, 3, device=device)], 1)
    assert torch.allclose(r(g.replace(sh=sh16), cams).rgb, with_rgb.rgb, atol=1e-6)


def test_sh_view_direction_by_hand():
    # degree 1: SH = C0 c0 - C1 y c1 + C1 z c2 - C1 x c3 with dir = normalize(mean - camera centre)
    sh = torch.zeros(1, 4, 3, dtype=F64)
    sh[0, 0] = 0.4
    sh[0, 2] = torch.tensor([0.5, 0.0, -0.5], dtype=F64)  # the z band
    g = _on_axis([0.0], 0.3, [0.5], [[0.0, 0.0, 0.0]]).replace(colors=None, sh=sh)
    for eye, dz in (((0.0, 0.0, 5.0), -1.0), ((0.0, 0.0, -5.0), 1.0)):
        cam = Cameras.look_at(eye, (0.0, 0.0, 0.0), fov_y_deg=40.0, width=9, height=9)
        out = TorchRenderer()(g, cam)
        colour = SH_C0 * 0.4 + SH_C1 * dz * torch.tensor([0.5, 0.0, -0.5], dtype=F64) + 0.5
        expected = colour.clamp_min(0.0) * out.alpha[0, 4, 4]
        assert torch.allclose(out.rgb[0, 4, 4], expected, atol=1e-6)
    dirs = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    assert torch.allclose(eval_sh(1, sh, dirs), torch.full((1, 3), SH_C0 * 0.4, dtype=F64))


def test_quat_to_rotmat_normalizes():
    q = torch.tensor([[2.0, 0.0, 0.0, 0.0], [math.cos(0.5), 0.0, 0.0, math.sin(0.5)]], dtype=F64)
    R = quat_to_rotmat(q)
    assert torch.allclose(R[0], torch.eye(3, dtype=F64))
    c, s = math.cos(1.0), math.sin(1.0)  # rotation by 1 rad about z
    assert torch.allclose(R[1], torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=F64))


# ---------------------------------------------------------------- bad inputs


def test_bad_inputs_raise_clear_errors():
    g = _random_gaussians(3, dtype=torch.float32)
    cams = _two_cameras()
    r = TorchRenderer()
    nan_means = g.means.clone()
    nan_means[1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"Gaussians.means has NaN or inf values \(first rows: \[1\]\)"):
        r(g.replace(means=nan_means), cams)
    with pytest.raises(ValueError, match=r"Gaussians.quats must have shape \(3, 4\)"):
        r(g.replace(quats=g.quats[:, :3]), cams)
    with pytest.raises(ValueError, match=r"Gaussians.means must have shape \(N, 3\)"):
        r(g.replace(means=g.means[:, :2]), cams)
    with pytest.raises(ValueError, match="either colors"):
        r(g.replace(colors=None), cams)
    with pytest.raises(ValueError, match="K in 1, 4, 9, 16"):
        r(g.replace(sh=torch.zeros(3, 5, 3)), cams)
    with pytest.raises(ValueError, match="zero-norm"):
        r(g.replace(quats=torch.zeros(3, 4)), cams)
    with pytest.raises(ValueError, match="dtype"):
        r(g.replace(colors=g.colors.double()), cams)
    with pytest.raises(TypeError, match="Cameras"):
        r(g, torch.eye(4))
    with pytest.raises(ValueError, match="empty batch"):
        Cameras(torch.zeros(0, 3, 3), torch.zeros(0, 4, 4), 8, 8)
    with pytest.raises(ValueError, match="chunk_elements"):
        TorchRenderer(chunk_elements=0)

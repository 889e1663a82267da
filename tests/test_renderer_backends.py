"""Every fast renderer backend against the exact dense ``"torch"`` reference.

The reference runs in float64 on the same (float32-representable) inputs, so the differences
measured here are the backend's own float32 round-off. Tolerances:

* Images: absolute 1e-4 on rgb and alpha (values in [0, 1]; float32 compositing of a few hundred
  Gaussians accumulates ~1e-6), and 1e-4 times the largest depth on ``depth`` (it is a weighted
  sum of camera depths of a few metres).
* Gradients: relative L2 error of each attribute's whole gradient < 1e-3. The float32 sums over
  thousands of pixel contributions (atomics on CUDA, in any order) land near 1e-6; a wrong or
  missing term gives O(1) errors.
* The contribution rule has two discontinuities: ``alpha >= 1/255`` and the transmittance cut-off
  ``T (1 - alpha) >= 1e-4`` (plus a kink at the 0.99 clamp that only the gradients see). Where the
  float64 value lies within a relative 1e-3 of a threshold, float32 round-off in the backend may
  legitimately decide the other way and change a pixel by up to 1/255 (or every Gaussian behind
  the cut). Those pixels are masked out of the image comparison and their output cotangents are
  zeroed for the gradient comparison; the tests assert the mask removes only a small fraction.
"""

from __future__ import annotations

import math
from contextlib import contextmanager

import pytest
import torch

from renderers import RENDERERS, get_renderer
from renderers.base import ALPHA_MAX, ALPHA_MIN, T_MIN, Gaussians
from renderers.torch_reference import project_gaussians
from toolkit.cameras import Cameras

ATTRS = ("means", "log_scales", "quats", "opacity_logits", "colors", "sh", "deformation")
CUDA_ONLY = {"gsplat"}  # backends that only exist for CUDA tensors
BAND = 1e-3  # relative distance to the 1/255 or 1e-4 threshold below which a pixel is not compared
CLAMP_BAND = 1e-4  # the same for the 0.99 clamp (a kink, not a jump: only gradients see it)
# Backends whose culling is not the exact contribution rule may set looser tolerances here,
# with the reason next to them: {"name": {"atol": ..., "grad_rtol": ...}}.
TOLERANCES: dict[str, dict[str, float]] = {}
DEFAULT_TOL = {"atol": 1e-4, "grad_rtol": 1e-3}

BACKENDS = [name for name in RENDERERS.names() if name != "torch"]


def _skip_unsupported(name: str, device: str) -> None:
    if name in CUDA_ONLY and not device.startswith("cuda"):
        pytest.skip(f"{name} renders CUDA tensors only")


def _tol(name: str) -> dict[str, float]:
    return {**DEFAULT_TOL, **TOLERANCES.get(name, {})}


# ---------------------------------------------------------------------------- scenes


def _ring_cameras(width: int, height: int, n: int = 3, device: str = "cpu", radius: float = 2.6) -> Cameras:
    """``n`` cameras on a ring around the origin, looking at it (OpenCV convention)."""
    eyes = []
    for k in range(n):
        a = 2.0 * math.pi * k / n + 0.3
        eyes.append([radius * math.sin(a), 0.4 * math.cos(3.0 * a), radius * math.cos(a)])
    cams = Cameras.look_at(torch.tensor(eyes), (0.0, 0.0, 0.0), fov_y_deg=45.0, width=width, height=height)
    return cams.to(device)


def _random_gaussians(n: int, seed: int, device: str = "cpu", sh_coeffs: int = 0, cube: float = 1.0) -> Gaussians:
    """``n`` random Gaussians with means in a ``cube``-metre cube at the origin (float32)."""
    g = torch.Generator().manual_seed(seed)
    sh = None
    if sh_coeffs:
        sh = 0.25 * torch.randn(n, sh_coeffs, 3, generator=g)
        sh[:, 0] += 0.4
    gs = Gaussians(
        means=cube * (torch.rand(n, 3, generator=g) - 0.5),
        log_scales=torch.log(0.015 + 0.06 * torch.rand(n, 3, generator=g)),
        quats=torch.randn(n, 4, generator=g),
        # opacities within (0.018, 0.982): no alpha reaches the 0.99 clamp, where gsplat differs
        opacity_logits=(1.5 * torch.randn(n, generator=g)).clamp(-4.0, 4.0),
        colors=torch.rand(n, 3, generator=g),
        sh=sh,
    )
    return gs.to(device)


def _axis_camera(width: int, height: int, f: float, device: str = "cpu") -> Cameras:
    """Camera at the origin looking down +z (w2c = I), principal point at the image centre."""
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return Cameras(K, torch.eye(4), width, height).to(device)


def _at_pixels(u: torch.Tensor, v: torch.Tensor, z: torch.Tensor, cam: Cameras) -> torch.Tensor:
    """World points (w2c = I) that project to pixel coordinates (u, v) at depths z."""
    fx, fy, cx, cy = float(cam.fx[0]), float(cam.fy[0]), float(cam.cx[0]), float(cam.cy[0])
    return torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)


# ---------------------------------------------------------------------------- comparison helpers


def _float64(gs: Gaussians) -> Gaussians:
    return Gaussians(**{k: (None if getattr(gs, k) is None else getattr(gs, k).detach().double()) for k in ATTRS})


def _stable_pixels(gs: Gaussians, cams: Cameras) -> torch.Tensor:
    """(B, H, W) bool: no Gaussian is within ``BAND`` of a discontinuity of the contribution rule.

    Evaluated densely in float64 with the reference's own projection and depth order.
    """
    g64 = _float64(gs)
    with torch.no_grad():
        proj = project_gaussians(g64, cams)
        B, H, W = len(cams), cams.height, cams.width
        key = torch.where(proj.valid, proj.depths, torch.full_like(proj.depths, math.inf))
        order = torch.sort(key, dim=-1, stable=True).indices
        m2d = torch.gather(proj.means2d, 1, order[..., None].expand(-1, -1, 2))
        con = torch.gather(proj.conic.reshape(B, -1, 4), 1, order[..., None].expand(-1, -1, 4))
        valid = torch.gather(proj.valid, 1, order)
        opacity = torch.sigmoid(g64.opacity_logits)[order]
        j, i = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
        px = (i.reshape(-1) + 0.5).to(m2d.device)
        py = (j.reshape(-1) + 0.5).to(m2d.device)
        dx = px[None, :, None] - m2d[:, None, :, 0]
        dy = py[None, :, None] - m2d[:, None, :, 1]
        power = 0.5 * (con[:, None, :, 0] * dx * dx + con[:, None, :, 3] * dy * dy) + con[:, None, :, 1] * dx * dy
        raw = opacity[:, None, :] * torch.exp(-power)
        alpha = torch.where(valid[:, None, :] & (raw >= ALPHA_MIN), raw.clamp_max(ALPHA_MAX), torch.zeros_like(raw))
        trans = torch.cumprod(1.0 - alpha, -1)
        trans_excl = torch.cat([torch.ones_like(trans[..., :1]), trans[..., :-1]], -1)
        # splats behind the cut-off cannot change the image (a borderline cut is caught below)
        reached = valid[:, None, :] & (trans_excl >= T_MIN * (1.0 - BAND))
        near_min = (raw - ALPHA_MIN).abs() <= BAND * ALPHA_MIN
        near_clamp = (raw - ALPHA_MAX).abs() <= CLAMP_BAND * ALPHA_MAX
        near_cut = (alpha > 0) & ((trans - T_MIN).abs() <= BAND * T_MIN)
        unstable = ((near_min | near_clamp) & reached | near_cut).any(-1)
    return ~unstable.reshape(B, H, W)


def _compare(name: str, gs: Gaussians, cams: Cameras, device: str, seed: int = 0, grads: bool = True, **render_kw) -> None:
    """Render with backend ``name`` and with the float64 reference; compare images and gradients."""
    tol = _tol(name)
    stable = _stable_pixels(gs, cams)
    assert stable.float().mean() > 0.9, "the scene sits too close to the contribution rule's discontinuities"

    def leaves(dtype):
        out = {}
        for k in ATTRS:
            t = getattr(gs, k)
            out[k] = None if t is None else t.detach().to(dtype).clone().requires_grad_(True)
        return out

    fast_in, ref_in = leaves(torch.float32), leaves(torch.float64)
    fast = get_renderer(name, **render_kw)(Gaussians(**fast_in), cams)
    ref = get_renderer("torch", **render_kw)(Gaussians(**ref_in), cams)
    B, H, W = len(cams), cams.height, cams.width
    assert fast.rgb.shape == (B, H, W, 3) and fast.alpha.shape == (B, H, W) and fast.depth.shape == (B, H, W)
    assert fast.rgb.device.type == torch.device(device).type

    zmax = float(ref.depth.detach().abs().max().clamp_min(1.0))
    for key, atol in (("rgb", tol["atol"]), ("alpha", tol["atol"]), ("depth", tol["atol"] * zmax)):
        a, b = getattr(fast, key).double(), getattr(ref, key)
        mask = stable[..., None].expand_as(b) if key == "rgb" else stable
        err = (a - b).abs()[mask].max().item()
        assert err <= atol, f"{name}: {key} differs from the reference by {err:.3g} > {atol:.3g}"

    if not grads:
        return
    gen = torch.Generator().manual_seed(seed + 1)
    cot = {
        "rgb": torch.randn(B, H, W, 3, generator=gen, dtype=torch.float64) * stable[..., None].cpu(),
        "alpha": torch.randn(B, H, W, generator=gen, dtype=torch.float64) * stable.cpu(),
        "depth": torch.randn(B, H, W, generator=gen, dtype=torch.float64) * stable.cpu(),
    }
    cot = {k: v.to(ref.rgb.device) for k, v in cot.items()}

    def backprop(out, inputs, dtype):
        loss = sum((getattr(out, k) * v.to(dtype)).sum() for k, v in cot.items())
        names = [k for k, t in inputs.items() if t is not None and (k != "colors" or inputs["sh"] is None)]
        return dict(zip(names, torch.autograd.grad(loss, [inputs[k] for k in names])))

    g_fast = backprop(fast, fast_in, torch.float32)
    g_ref = backprop(ref, ref_in, torch.float64)
    for key, gr in g_ref.items():
        gf = g_fast[key].double()
        assert torch.isfinite(gf).all(), f"{name}: non-finite gradient for {key}"
        rel = ((gf - gr).norm() / gr.norm().clamp_min(1e-30)).item()
        assert rel < tol["grad_rtol"], f"{name}: gradient of {key} has relative L2 error {rel:.3g}"


@contextmanager
def _cpu_blocks():
    """Run Warp's CPU tiled launches with real 256-lane blocks (as on CUDA) inside the block."""
    import warp as wp

    old = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        yield
    finally:
        wp.config.enable_cpu_blocks = old


# ---------------------------------------------------------------------------- tests


def test_warp_backend_is_registered():
    from renderers.warp_tiles import WarpTileRenderer

    assert "warp" in BACKENDS
    assert RENDERERS.get("warp") is WarpTileRenderer


@pytest.mark.parametrize("name", BACKENDS)
@pytest.mark.parametrize(
    "n, width, height, sh_coeffs, seed",
    [
        (250, 48, 40, 0, 0),  # sizes not multiples of the 16 px tile
        (150, 32, 32, 16, 1),  # degree-3 SH colours
        (300, 37, 29, 0, 2),
    ],
)
def test_random_scene_matches_reference(name, device, n, width, height, sh_coeffs, seed):
    _skip_unsupported(name, device)
    gs = _random_gaussians(n, seed, device, sh_coeffs=sh_coeffs)
    cams = _ring_cameras(width, height, 3, device)
    _compare(name, gs, cams, device, seed=seed, background=(0.2, 0.5, 0.9))


@pytest.mark.parametrize("name", BACKENDS)
def test_near_plane_and_huge_footprints(name, device):
    """A camera inside the cloud: Gaussians behind it are culled, the ones next to it cover many tiles."""
    _skip_unsupported(name, device)
    gs = _random_gaussians(120, 5, device, cube=1.0)
    cams = Cameras.look_at(
        torch.tensor([[0.05, 0.02, 0.2], [0.0, 0.3, 2.5]]), (0.0, 0.0, -1.0), fov_y_deg=60.0, width=40, height=36, near=0.05
    ).to(device)
    z = cams.world_to_camera(gs.means)[0, :, 2]
    assert (z <= cams.near).any() and (z > cams.near).any()
    _compare(name, gs, cams, device, seed=5)


@pytest.mark.parametrize("name", BACKENDS)
def test_gaussian_straddling_tile_borders(name, device):
    """One wide Gaussian centred on the corner shared by four 16 px tiles, plus a small one on a border."""
    _skip_unsupported(name, device)
    cam = _axis_camera(40, 40, 40.0, device)
    z = torch.tensor([2.0, 1.5])
    means = _at_pixels(torch.tensor([16.0, 31.7]), torch.tensor([16.0, 9.0]), z, cam)
    gs = Gaussians(
        means=means,
        log_scales=torch.log(torch.tensor([[0.3, 0.2, 0.1], [0.03, 0.05, 0.02]])),
        quats=torch.tensor([[0.9, 0.1, 0.3, 0.2], [1.0, 0.0, 0.0, 0.0]]),
        opacity_logits=torch.tensor([1.0, 2.0]),
        colors=torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3]]),
    ).to(device)
    out = get_renderer(name)(gs, cam)
    a = out.alpha[0]
    assert (a[:16, :16] > ALPHA_MIN).any() and (a[:16, 16:32] > ALPHA_MIN).any()
    assert (a[16:32, :16] > ALPHA_MIN).any() and (a[16:32, 16:32] > ALPHA_MIN).any()
    _compare(name, gs, cam, device, seed=3)


@pytest.mark.parametrize("name", BACKENDS)
def test_many_gaussians_in_one_tile(name, device):
    """2000 tiny Gaussians inside one tile: its list spans several 256-Gaussian batches."""
    _skip_unsupported(name, device)
    cam = _axis_camera(32, 32, 30.0, device)
    g = torch.Generator().manual_seed(11)
    n = 2000
    u = 1.0 + 14.0 * torch.rand(n, generator=g)
    v = 1.0 + 14.0 * torch.rand(n, generator=g)
    z = 1.0 + 2.0 * torch.rand(n, generator=g)
    gs = Gaussians(
        means=_at_pixels(u, v, z, cam),
        log_scales=torch.log(z[:, None] * (0.4 + 0.6 * torch.rand(n, 3, generator=g)) / 30.0),  # 0.4-1 px
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=-2.5 + torch.randn(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
    ).to(device)
    out = get_renderer(name)(gs, cam)
    assert float(out.alpha[0, :16, :16].mean()) > 0.5
    _compare(name, gs, cam, device, seed=11)


def _opaque_layers(device: str, n: int = 400) -> tuple[Gaussians, Cameras]:
    """Nearly opaque, overlapping splats of 2-8 px: alpha reaches the 0.99 clamp, most pixels reach
    the transmittance cut-off, and every tile's list is longer than one 256-splat batch."""
    cam = _axis_camera(36, 28, 30.0, device)
    g = torch.Generator().manual_seed(21)
    z = 1.0 + 3.0 * torch.rand(n, generator=g)
    gs = Gaussians(
        means=_at_pixels(36.0 * torch.rand(n, generator=g), 28.0 * torch.rand(n, generator=g), z, cam),
        log_scales=torch.log(z[:, None] * (2.0 + 6.0 * torch.rand(n, 3, generator=g)) / 30.0),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=3.0 + 4.0 * torch.rand(n, generator=g),  # opacity 0.95..0.999
        colors=torch.rand(n, 3, generator=g),
    ).to(device)
    return gs, cam


@pytest.mark.parametrize("name", BACKENDS)
def test_opaque_layers_clamp_and_cutoff(name, device):
    _skip_unsupported(name, device)
    if name == "gsplat":
        pytest.skip("gsplat clamps alpha at 0.999 and cuts at T(1 - alpha) <= 1e-4 (see renderers.gsplat_backend)")
    gs, cam = _opaque_layers(device)
    _compare(name, gs, cam, device, seed=21, background=(1.0, 1.0, 1.0))


@pytest.mark.parametrize("name", BACKENDS)
def test_outputs_are_differentiable_for_one_output_only(name, device):
    """Backward with only one output used (the other cotangents are None) works and is finite."""
    _skip_unsupported(name, device)
    gs = _random_gaussians(60, 4, device)
    for k in ("means", "log_scales", "quats", "opacity_logits", "colors"):
        getattr(gs, k).requires_grad_(True)
    out = get_renderer(name)(gs, _ring_cameras(24, 20, 2, device))
    out.alpha.sum().backward()
    assert torch.isfinite(gs.means.grad).all() and gs.means.grad.abs().sum() > 0
    assert float(gs.colors.grad.abs().sum()) == 0.0  # alpha does not depend on colour


def test_warp_cpu_blocks_match_reference():
    """The CUDA code path (256-lane blocks, shared-memory batches, block-wide early exit and max)
    emulated on the CPU with Warp's cooperative CPU blocks."""
    with _cpu_blocks():
        gs = _random_gaussians(200, 7, "cpu")
        _compare("warp", gs, _ring_cameras(40, 33, 2, "cpu"), "cpu", seed=7)
        cam = _axis_camera(32, 32, 30.0)
        g = torch.Generator().manual_seed(8)
        n = 700
        z = 1.0 + 2.0 * torch.rand(n, generator=g)
        dense = Gaussians(
            means=_at_pixels(1.0 + 30.0 * torch.rand(n, generator=g), 1.0 + 14.0 * torch.rand(n, generator=g), z, cam),
            log_scales=torch.log(0.01 + 0.03 * torch.rand(n, 3, generator=g)),
            quats=torch.randn(n, 4, generator=g),
            opacity_logits=torch.randn(n, generator=g),
            colors=torch.rand(n, 3, generator=g),
        )
        _compare("warp", dense, cam, "cpu", seed=8)
        gs, cam = _opaque_layers("cpu")  # blocks leave early: every pixel is done before the list ends
        _compare("warp", gs, cam, "cpu", seed=21, background=(1.0, 1.0, 1.0))


# ---------------------------------------------------------------------------- edge cases and errors


@pytest.mark.parametrize("name", BACKENDS)
def test_no_gaussians_gives_background(name, device):
    _skip_unsupported(name, device)
    gs = Gaussians(
        means=torch.zeros(0, 3, device=device, requires_grad=True),
        log_scales=torch.zeros(0, 3, device=device),
        quats=torch.zeros(0, 4, device=device),
        opacity_logits=torch.zeros(0, device=device),
        colors=torch.zeros(0, 3, device=device),
    )
    out = get_renderer(name, background=(0.25, 0.5, 1.0))(gs, _ring_cameras(20, 18, 2, device))
    assert out.rgb.shape == (2, 18, 20, 3) and out.alpha.shape == (2, 18, 20) and out.depth.shape == (2, 18, 20)
    assert torch.equal(out.alpha, torch.zeros_like(out.alpha))
    assert torch.equal(out.depth, torch.zeros_like(out.depth))
    assert torch.allclose(out.rgb, torch.tensor([0.25, 0.5, 1.0], device=out.rgb.device).expand_as(out.rgb))
    (out.rgb.sum() + out.alpha.sum()).backward()  # still attached to the (empty) inputs
    assert gs.means.grad is not None and gs.means.grad.shape == (0, 3)


@pytest.mark.parametrize("name", BACKENDS)
def test_everything_culled_gives_background(name, device):
    _skip_unsupported(name, device)
    gs = _random_gaussians(20, 9, device)
    gs = gs.replace(means=gs.means + torch.tensor([0.0, 0.0, 50.0], device=gs.means.device))
    cam = Cameras.look_at([0.0, 0.0, 40.0], (0.0, 0.0, 0.0), fov_y_deg=40.0, width=20, height=20).to(device)  # all behind
    gs.means.requires_grad_(True)
    out = get_renderer(name, background=(0.1, 0.2, 0.3))(gs, cam)
    assert float(out.alpha.detach().abs().max()) == 0.0
    out.rgb.sum().backward()
    assert float(gs.means.grad.abs().max()) == 0.0


@pytest.mark.parametrize("name", BACKENDS)
def test_bad_inputs_raise_clear_errors(name, device):
    _skip_unsupported(name, device)
    r = get_renderer(name)
    cams = _ring_cameras(16, 16, 1, device)
    good = _random_gaussians(5, 0, device)

    nan_means = good.means.clone()
    nan_means[2, 1] = float("nan")
    with pytest.raises(ValueError, match="means"):
        r(good.replace(means=nan_means), cams)
    inf_logit = good.opacity_logits.clone()
    inf_logit[0] = float("inf")
    with pytest.raises(ValueError, match="opacity_logits"):
        r(good.replace(opacity_logits=inf_logit), cams)
    with pytest.raises(ValueError, match="log_scales"):
        r(good.replace(log_scales=good.log_scales[:, :2]), cams)
    with pytest.raises(ValueError, match="quats"):
        r(good.replace(quats=good.quats[:4]), cams)
    with pytest.raises(ValueError, match="means"):
        r(good.replace(means=good.means[:, :2]), cams)
    with pytest.raises(ValueError, match="sh"):
        r(good.replace(sh=torch.zeros(5, 3, 3, device=good.means.device)), cams)
    with pytest.raises(ValueError, match="zero-norm"):
        r(good.replace(quats=torch.zeros_like(good.quats)), cams)
    with pytest.raises(ValueError, match="dtype"):
        r(good.replace(colors=good.colors.double()), cams)
    with pytest.raises(ValueError, match="no camera"):
        r(good, cams[torch.zeros(0, dtype=torch.long)])
    with pytest.raises(TypeError):
        r(good, "not cameras")


@pytest.mark.parametrize("name", BACKENDS)
def test_deformed_gaussians_match_reference(name, device):
    """Per-Gaussian deformations A (covariance A R S S^T R^T A^T): images and every gradient,
    the deformations' included, match the float64 reference."""
    _skip_unsupported(name, device)
    gs = _random_gaussians(200, 5, device)
    gen = torch.Generator().manual_seed(7)
    A = torch.eye(3) + 0.3 * torch.randn(200, 3, 3, generator=gen)
    _compare(name, gs.replace(deformation=A.to(device)), _ring_cameras(40, 32, 3, device), device, seed=5)


def test_deformation_is_the_covariance_map():
    """The reference's covariance with a deformation is A Sigma A^T; the identity changes nothing."""
    from renderers.torch_reference import covariance_3d

    gs = _float64(_random_gaussians(50, 3))
    A = torch.eye(3, dtype=torch.float64) + 0.4 * torch.randn(50, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    sigma = covariance_3d(gs.log_scales, gs.quats)
    torch.testing.assert_close(covariance_3d(gs.log_scales, gs.quats, A), A @ sigma @ A.transpose(1, 2))
    torch.testing.assert_close(covariance_3d(gs.log_scales, gs.quats, torch.eye(3, dtype=torch.float64).expand(50, 3, 3)), sigma)


def test_deformation_shape_is_checked():
    gs = _random_gaussians(10, 0)
    with pytest.raises(ValueError, match="Gaussians.deformation must have shape"):
        gs.replace(deformation=torch.zeros(10, 3)).validate()


@pytest.mark.parametrize("seed", [0, 1])
def test_baked_deformation_renders_the_same_image(seed):
    """Folding each deformation into scales and a rotation (for PLY files and viewers) keeps the
    covariance A R S S^T R^T A^T, so the baked Gaussians render the deformed image."""
    from renderers.torch_reference import bake_deformation, covariance_3d, rotmat_to_quat, quat_to_rotmat

    gs = _random_gaussians(150, 3, "cpu")
    gen = torch.Generator().manual_seed(seed)
    A = torch.eye(3) + 0.4 * torch.randn(150, 3, 3, generator=gen)
    A[0] = torch.diag(torch.tensor([1.0, 1.0, -1.0]))  # a reflection: the rotation must stay proper
    baked = bake_deformation(gs.replace(deformation=A))
    assert baked.deformation is None and bool((baked.quats[:, 0] >= 0).all())
    torch.testing.assert_close(covariance_3d(baked.log_scales, baked.quats), covariance_3d(gs.log_scales, gs.quats, A),
                               atol=1e-6, rtol=1e-4)
    R = quat_to_rotmat(torch.randn(50, 4, generator=gen, dtype=torch.float64))
    torch.testing.assert_close(quat_to_rotmat(rotmat_to_quat(R)), R)
    r = get_renderer("torch")
    cams = _ring_cameras(40, 32, 2, "cpu")
    torch.testing.assert_close(r(baked, cams).rgb, r(gs.replace(deformation=A), cams).rgb, atol=1e-4, rtol=0)


@pytest.mark.parametrize("edge", [1, 7, 16])
def test_cpu_tile_edge_changes_nothing(edge, monkeypatch):
    """The CPU's tile edge (:data:`renderers.warp_tiles.CPU_TILE_SIZE`, 4 px) only regroups the
    work: images and gradients equal those of any other edge, also one that does not divide the
    image, up to float32 summation order."""
    import renderers.warp_tiles as wt

    gs = _random_gaussians(300, 7, "cpu")
    cams = _ring_cameras(37, 29, 2, "cpu")
    gen = torch.Generator().manual_seed(8)
    cot = torch.randn(2, 29, 37, 3, generator=gen)

    def render():
        leaves = {k: (None if getattr(gs, k) is None else getattr(gs, k).clone().requires_grad_(True)) for k in ATTRS}
        out = get_renderer("warp")(Gaussians(**leaves), cams)
        names = ["means", "log_scales", "opacity_logits", "colors"]
        grads = torch.autograd.grad((out.rgb * cot).sum() + out.depth.sum(), [leaves[k] for k in names])
        return out, dict(zip(names, grads))

    assert wt.tile_size(torch.device("cpu")) == wt.CPU_TILE_SIZE == 4
    base, g_base = render()
    monkeypatch.setattr(wt, "CPU_TILE_SIZE", edge)
    assert wt.tile_size(torch.device("cpu")) == edge
    other, g_other = render()
    assert float(base.alpha.detach().mean()) > 0.2  # the scene covers the images
    for key in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(getattr(other, key), getattr(base, key), rtol=0, atol=1e-5)
    for key, g in g_base.items():
        rel = float((g_other[key] - g).norm() / g.norm())
        assert rel < 1e-5, f"gradient of {key} changed by {rel:.2g} with a {edge} px tile"

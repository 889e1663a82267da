"""renderers.gsplat_backend against the torch reference (needs gsplat and CUDA; skipped otherwise)."""

from __future__ import annotations

import math

import pytest
import torch

from renderers.gsplat_backend import GsplatRenderer, gsplat_available

pytestmark = pytest.mark.skipif(
    not gsplat_available(), reason="gsplat backend needs `import gsplat` to succeed and a CUDA device"
)


def _scene(device: str, sh: bool):
    from renderers.base import Gaussians
    from toolkit.cameras import Cameras

    g = torch.Generator().manual_seed(0)
    n = 60
    opacity = 0.05 + 0.9 * torch.rand(n, generator=g)  # < 0.99: gsplat clamps alpha at 0.999, the reference at 0.99
    gs = Gaussians(
        means=0.5 * torch.randn(n, 3, generator=g),
        log_scales=math.log(0.08) + 0.3 * torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.log(opacity / (1 - opacity)),
        colors=torch.rand(n, 3, generator=g),
        sh=(0.3 * torch.randn(n, 9, 3, generator=g)) if sh else None,
    ).to(device)
    eyes = torch.tensor([[0.0, 0.5, 4.0], [3.0, 1.0, 2.0]])
    cams = Cameras.look_at(eyes, (0.0, 0.0, 0.0), fov_y_deg=45.0, width=48, height=40).to(device)
    return gs, cams


@pytest.mark.cuda
@pytest.mark.parametrize("sh", [False, True])
def test_gsplat_matches_reference(sh):
    from renderers import RENDERERS
    from renderers.torch_reference import TorchRenderer

    assert RENDERERS.get("gsplat") is GsplatRenderer
    gs, cams = _scene("cuda:0", sh)
    names = ["means", "log_scales", "quats", "opacity_logits", "sh" if sh else "colors"]
    outs, grads = [], []
    for r in (TorchRenderer(background=(0.1, 0.2, 0.3)), GsplatRenderer(background=(0.1, 0.2, 0.3))):
        params = {k: getattr(gs, k).detach().clone().requires_grad_(True) for k in names}
        out = r(gs.replace(**params), cams)
        (out.rgb.square().sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        outs.append(out)
        grads.append({k: p.grad for k, p in params.items()})
    ref, fast = outs
    assert (ref.rgb - fast.rgb).abs().max() < 2e-3
    assert (ref.alpha - fast.alpha).abs().max() < 2e-3
    assert (ref.depth - fast.depth).abs().max() < 1e-2
    for k in names:
        a, b = grads[0][k], grads[1][k]
        rel = (a - b).norm() / a.norm().clamp_min(1e-8)
        assert rel < 2e-2, f"gradient of {k} differs: relative error {rel:.3g}"


@pytest.mark.cuda
def test_gsplat_empty_scene():
    from renderers.base import Gaussians

    _, cams = _scene("cuda:0", False)
    empty = Gaussians(*(torch.zeros(0, d, device="cuda:0") for d in (3, 3, 4)), torch.zeros(0, device="cuda:0"), torch.zeros(0, 3, device="cuda:0"))
    out = GsplatRenderer(background=(1.0, 0.0, 0.0))(empty, cams)
    assert (out.alpha == 0).all() and (out.rgb[..., 0] == 1).all()

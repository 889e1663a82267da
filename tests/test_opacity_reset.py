"""The opacity-reset guard of stage 0 (:mod:`toolkit.scene.opacity_reset`): a reset that fades most
of the model is undone exactly (parameters, Adam state, count), one that fades a few floaters is kept."""

from __future__ import annotations

import torch

from toolkit.scene.gaussian_model import PER_GAUSSIAN_PARAMS, DensificationConfig, GaussianModel
from toolkit.scene.opacity_reset import OpacityResetGuard


def _trained_model(n: int = 200, steps: int = 5) -> tuple[GaussianModel, torch.optim.Adam]:
    torch.manual_seed(0)
    g = GaussianModel(sh_degree=0)
    g.init_from_points(torch.rand(n, 3), torch.rand(n, 3), opacity=0.5)
    opt = torch.optim.Adam([getattr(g, name) for name in PER_GAUSSIAN_PARAMS if getattr(g, name).requires_grad], lr=0.05)
    target = torch.rand(n)
    for _ in range(steps):  # some optimizer state to restore
        opt.zero_grad()
        loss = ((g.opacity - target) ** 2).sum() + g.means.pow(2).sum() + g.log_scales.pow(2).sum()
        loss.backward()
        opt.step()
    return g, opt


def _state(g: GaussianModel, opt: torch.optim.Optimizer) -> dict:
    out = {name: getattr(g, name).detach().clone() for name in PER_GAUSSIAN_PARAMS}
    for name in PER_GAUSSIAN_PARAMS:
        st = opt.state.get(getattr(g, name))
        if st:
            out.update({f"{name}.{k}": v.clone() for k, v in st.items()})
    return out


def test_a_reset_that_fades_most_gaussians_is_undone_exactly():
    g, opt = _trained_model()
    before = _state(g, opt)
    n0 = g.n
    cfg = DensificationConfig()
    guard = OpacityResetGuard()
    assert guard.reset(g, opt, cfg.opacity_reset_value, iteration=376)
    assert float(g.opacity.detach().max()) <= cfg.opacity_reset_value + 1e-6
    # what a 4D model that does not follow the motion does next: the rows change (a clone round)
    # and most opacities fall below min_opacity
    g.clone(torch.arange(g.n) < 10, opt)
    with torch.no_grad():
        g.opacity_logits[: int(0.8 * g.n)] = -8.0
    record = guard.check(g, opt, cfg.min_opacity, iteration=384)
    assert record == {"reset_iteration": 376, "iteration": 384, "faded": int(0.8 * (n0 + 10)), "n": n0 + 10, "restored_n": n0}
    after = _state(g, opt)
    assert after.keys() == before.keys()
    for key in before:
        assert torch.equal(after[key], before[key]), key
    assert g.n == n0 and g.grad_accum.shape == (n0,) and float(g.max_radii.abs().sum()) == 0.0
    # the optimizer still steps the restored parameters
    opt.zero_grad()
    g.opacity.sum().backward()
    opt.step()
    assert not torch.equal(g.opacity_logits.detach(), before["opacity_logits"])
    # no further resets in the run
    assert guard.disabled and not guard.reset(g, opt, cfg.opacity_reset_value, iteration=564)
    assert float(g.opacity.detach().max()) > cfg.opacity_reset_value


def test_a_reset_that_fades_a_few_floaters_is_kept():
    g, _ = _trained_model()
    opt = torch.optim.Adam([g.opacity_logits], lr=0.05)
    cfg = DensificationConfig()
    guard = OpacityResetGuard()
    guard.reset(g, opt, cfg.opacity_reset_value, iteration=376)
    with torch.no_grad():
        g.opacity_logits[:20] = -8.0  # 10 % of the Gaussians: floaters the reset is meant to remove
    assert guard.check(g, opt, cfg.min_opacity, iteration=384) is None
    assert float(g.opacity.detach().max()) <= cfg.opacity_reset_value + 1e-6 and not guard.disabled
    # the threshold is the guard's max_fade: a stricter guard undoes the same reset
    strict = OpacityResetGuard(max_fade=0.05)
    strict.reset(g, opt, cfg.opacity_reset_value, iteration=376)
    with torch.no_grad():
        g.opacity_logits[:20] = -8.0
    assert strict.check(g, opt, cfg.min_opacity, iteration=384)["faded"] == 20


def test_check_without_a_reset_does_nothing():
    g, opt = _trained_model()
    with torch.no_grad():
        g.opacity_logits[:] = -8.0
    assert OpacityResetGuard().check(g, opt, DensificationConfig().min_opacity, iteration=10) is None


def test_release_drops_the_copy():
    g, opt = _trained_model()
    guard = OpacityResetGuard()
    guard.reset(g, opt, 0.01, iteration=376)
    guard.release()
    with torch.no_grad():
        g.opacity_logits[:] = -8.0
    assert guard.check(g, opt, 0.005, iteration=1000) is None and not guard.disabled

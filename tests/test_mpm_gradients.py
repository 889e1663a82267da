"""Gradients of the simulator against central finite differences, and chunking invariance.

Tolerance: the simulator runs in float32, so a finite difference of a loss of magnitude ~10 has
round-off noise ~1e-6/h; the steps below keep that under 1e-3 relative. The larger error budget
(6% of the component, or 2% of the gradient's overall scale) covers the non-differentiable
branches the finite-difference stencil may straddle: grid-node contact with the sticky ground,
the yield surfaces of the plastic models and sand's tension cut-off. A wrong adjoint (missing
term, wrong sign, lost shear stiffness at F = I) gives errors of order 100%.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from tests.mpm_scenes import block
from toolkit.mpm import MPMSimulator, SimConfig

CASES = {
    "neo_hookean": {"E": 2e4, "nu": 0.3},
    "neo_hookean_simplicits": {"E": 2e4, "nu": 0.3},
    "newtonian": {"mu": 1.0, "kappa": 1e4},
    "non_newtonian": {"mu": 1e3, "kappa": 1e4, "yield_stress": 50.0, "plastic_viscosity": 1.0},
    "plasticine": {"E": 2e4, "nu": 0.3, "yield_stress": 300.0},
    "sand": {"friction_angle": 30.0, "E": 1e5, "nu": 0.3},
    "kelvin_voigt": {"E": 2e4, "nu": 0.3, "damping": 30.0},
}


@pytest.fixture(autouse=True)
def _verify_array_access():
    previous = wp.config.verify_autograd_array_access
    wp.config.verify_autograd_array_access = True
    yield
    wp.config.verify_autograd_array_access = previous


def _scene(material: str, device: str, checkpoint_every: int = 7, effects=(), graphs="auto", deterministic=False,
           keep_tapes="auto"):
    cfg = SimConfig(dx=0.05, substeps=20, checkpoint_every=checkpoint_every, boundary="sticky", graphs=graphs,
                    deterministic=deterministic, keep_tapes=keep_tapes)
    sim = MPMSimulator(material, cfg, effects=effects, device=device)
    x0 = block((5, 5, 5), 0.025, (0.5, 0.08, 0.5))
    gen = torch.Generator().manual_seed(0)
    weights = torch.randn(4, x0.shape[0], 3, generator=gen)
    direction = torch.randn(x0.shape, generator=gen)
    return sim, x0, weights, direction


def _loss(sim, weights, x0, v0, raw, gravity, effect_params=None, n_frames=3):
    params = sim.material.to_physical(raw)
    out = sim.simulate(x0, v0, params, gravity=gravity, effect_params=effect_params, n_frames=n_frames)
    w = weights.to(out.positions.device)
    return (out.positions[1:] * w[1:]).sum() + 0.3 * (out.velocities[1:] * w[1:]).sum()


def _check(ad: torch.Tensor, fd: torch.Tensor, what: str) -> None:
    scale = fd.abs().max().item()
    err = (ad - fd).abs()
    bound = 0.06 * fd.abs() + 0.02 * scale
    assert bool((err <= bound).all()), f"{what}: autodiff {ad.tolist()} vs finite differences {fd.tolist()}"


@pytest.mark.parametrize("material", list(CASES))
def test_gradients_match_finite_differences(material, device):
    sim, x0, w, direction = _scene(material, device)
    raw = sim.material.to_raw(CASES[material])
    v0 = torch.tensor([0.3, -0.5, 0.1])
    gravity = torch.tensor([0.0, -9.8, 0.0])

    leaves = [t.clone().requires_grad_() for t in (x0, v0, raw, gravity)]
    _loss(sim, w, *leaves).backward()
    g_x0, g_v0, g_raw, g_gravity = (t.grad.cpu() for t in leaves)

    def loss_at(x=x0, v=v0, r=raw, g=gravity):
        with torch.no_grad():
            return _loss(sim, w, x, v, r, g).item()

    def central(fn, h):
        return (fn(h) - fn(-h)) / (2 * h)

    steps = {"log10": 1e-2, "tanh": 1e-2, "linear": 0.5}
    fd_raw = torch.tensor([
        central(lambda h, i=i: loss_at(r=raw + h * torch.nn.functional.one_hot(torch.tensor(i), len(raw)).float()),
                steps[p.transform])
        for i, p in enumerate(sim.material.params)
    ])
    _check(g_raw, fd_raw, f"{material} material parameters {sim.material.param_names}")
    fd_v0 = torch.tensor([central(lambda h, i=i: loss_at(v=v0 + h * torch.eye(3)[i]), 1e-2) for i in range(3)])
    _check(g_v0, fd_v0, f"{material} v0")
    fd_g = torch.tensor([central(lambda h, i=i: loss_at(g=gravity + h * torch.eye(3)[i]), 0.1) for i in range(3)])
    _check(g_gravity, fd_g, f"{material} gravity")
    # positions sit close to branch switches (contact, yield, tension): a small step keeps the stencil on one branch
    fd_x = torch.tensor([central(lambda h: loss_at(x=x0 + h * direction), 1e-4)])
    _check((g_x0 * direction).sum().reshape(1), fd_x, f"{material} x0 (directional)")


@pytest.mark.parametrize("material", ["neo_hookean", "plasticine"])
def test_chunked_gradients_equal_unchunked(material, device):
    grads = []
    # graphs: each chunk's recompute + adjoint (or kept forward and adjoint) replayed as captured Warp graphs
    for every, graphs, keep in ((1, False, False), (7, False, False), (1000, False, False), (7, True, False),
                                (7, False, True), (7, True, True)):
        # deterministic atomics: on CUDA the order of float atomics would otherwise differ between runs
        sim, x0, w, _ = _scene(material, device, checkpoint_every=every, graphs=graphs, deterministic=True, keep_tapes=keep)
        leaves = [t.clone().requires_grad_() for t in (x0, torch.tensor([0.3, -0.5, 0.1]), sim.material.to_raw(CASES[material]),
                                                       torch.tensor([0.0, -9.8, 0.0]))]
        _loss(sim, w, *leaves).backward()
        grads.append([t.grad.cpu() for t in leaves])
        assert len(sim.chunks(3, 20)) == 3 * -(-20 // every)
    for other in grads[1:]:
        for a, b in zip(grads[0], other):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6 * a.abs().max().item())


@pytest.mark.parametrize("effect,values,step", [
    ("air_drag", {"linear": 0.5, "quadratic": 0.3}, 1e-2),
    ("extra_acceleration", {"ax": 0.5, "ay": -0.2, "az": 0.1}, 1e-2),
    ("ground_friction", {"mu": 0.3}, 1e-2),
])
def test_effect_parameter_gradients(effect, values, step, device):
    sim, x0, w, _ = _scene("neo_hookean", device, effects=[effect])
    sim.config.boundary = "slip"  # friction needs a non-sticky ground
    sim_slip = MPMSimulator("neo_hookean", SimConfig(dx=0.05, substeps=20, checkpoint_every=7, boundary="slip"),
                            effects=[effect], device=device)
    raw = sim_slip.material.to_raw(CASES["neo_hookean"])
    v0 = torch.tensor([1.0, -0.5, 0.2])
    gravity = torch.tensor([0.0, -9.8, 0.0])
    ep = sim_slip.pack_effects({effect: values}).cpu()
    ep_leaf = ep.clone().requires_grad_()
    _loss(sim_slip, w, x0, v0, raw, gravity, ep_leaf).backward()
    fd = []
    for i in range(len(ep)):
        e = torch.eye(len(ep))[i] * step
        with torch.no_grad():
            fd.append((_loss(sim_slip, w, x0, v0, raw, gravity, ep + e).item()
                       - _loss(sim_slip, w, x0, v0, raw, gravity, ep - e).item()) / (2 * step))
    fd = torch.tensor(fd)
    assert fd.abs().max() > 1e-3, "the effect must matter in this scene"
    _check(ep_leaf.grad.cpu(), fd, f"{effect} parameters {sim_slip.effect_param_names}")


def test_memory_does_not_grow_with_substeps(device):
    """Without kept tapes, checkpoint buffers depend on the chunk length, not on the number of substeps."""
    sim, x0, w, _ = _scene("neo_hookean", device, checkpoint_every=5, keep_tapes=False)
    for substeps in (10, 40):
        sim.config.substeps = substeps
        leaves = [t.clone().requires_grad_() for t in (x0, torch.tensor([0.3, -0.5, 0.1]), sim.material.to_raw(CASES["neo_hookean"]),
                                                       torch.tensor([0.0, -9.8, 0.0]))]
        _loss(sim, w, *leaves).backward()
        pools = [k for k in sim._buffers if k[0] == "pool"]
        assert pools == [("pool", x0.shape[0], 5)]


def test_cached_graphs_see_new_inputs(device):
    """Graphs are captured once per simulator and replayed; each call's inputs must still be used.
    Deterministic atomics, so that graph and launch-by-launch runs can be compared tightly on CUDA
    (with ordinary float atomics gradients differed by up to 1.6e-4 relative between two runs)."""
    results = {}
    for graphs in (False, True):
        sim, x0, w, _ = _scene("plasticine", device, graphs=graphs, deterministic=True)
        runs = []
        for E, v in ((2e4, 0.3), (5e4, -0.2), (2e4, 0.3)):
            raw = sim.material.to_raw({"E": E, "nu": 0.3, "yield_stress": 300.0}).requires_grad_()
            v0 = torch.tensor([v, -0.5, 0.1], requires_grad=True)
            loss = _loss(sim, w, x0, v0, raw, torch.tensor([0.0, -9.8, 0.0]))
            loss.backward()
            runs.append((loss.item(), raw.grad.clone(), v0.grad.clone()))
        results[graphs] = runs
    for (la, ra, va), (lb, rb, vb) in zip(results[False], results[True]):
        assert la == pytest.approx(lb, rel=1e-5)
        torch.testing.assert_close(ra, rb, rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(va, vb, rtol=1e-4, atol=1e-6)
    # the second call differs from the first (the inputs really changed)
    assert abs(results[True][0][0] - results[True][1][0]) > 1e-3


def test_gradients_do_not_depend_on_which_inputs_require_them(device):
    """Inputs that need no gradient get no gradient buffer (their adjoint adds nothing), and a
    shared parameter row is expanded to one row per particle for the adjoint, then summed. The
    gradients that are asked for must not change with that bookkeeping."""
    sim, x0, w, _ = _scene("plasticine", device)
    values = {"E": 2e4, "nu": 0.3, "yield_stress": 300.0}

    def grads(which: set[str]):
        raw = sim.material.to_raw(values).requires_grad_("raw" in which)
        v0 = torch.tensor([0.3, -0.5, 0.1], requires_grad="v0" in which)
        gravity = torch.tensor([0.0, -9.8, 0.0], requires_grad="gravity" in which)
        loss = _loss(sim, w, x0, v0, raw, gravity)
        loss.backward()
        return {name: t.grad for name, t in (("raw", raw), ("v0", v0), ("gravity", gravity)) if name in which}

    every = grads({"raw", "v0", "gravity"})
    assert all(g is not None and g.abs().max() > 0 for g in every.values())
    for subset in ({"raw"}, {"v0"}, {"gravity"}, {"raw", "v0"}):
        part = grads(subset)
        for name, g in part.items():
            torch.testing.assert_close(g, every[name], rtol=2e-4, atol=1e-6)
    # per-particle parameters: each particle's row gets its own gradient; they sum to the shared row's
    def physical_grad(params: torch.Tensor) -> torch.Tensor:
        params = params.detach().clone().requires_grad_()
        out = sim.simulate(x0, torch.tensor([0.3, -0.5, 0.1]), params, gravity=torch.tensor([0.0, -9.8, 0.0]), n_frames=3)
        wt = w.to(out.positions.device)
        ((out.positions[1:] * wt[1:]).sum() + 0.3 * (out.velocities[1:] * wt[1:]).sum()).backward()
        return params.grad

    shared = sim.material.to_physical(sim.material.to_raw(values))
    g_rows = physical_grad(shared.expand(x0.shape[0], -1))
    assert g_rows.shape == (x0.shape[0], shared.shape[0]) and g_rows[:, 0].abs().max() > 0
    torch.testing.assert_close(g_rows.sum(0), physical_grad(shared), rtol=2e-4, atol=1e-9)


@pytest.mark.parametrize("material", ["neo_hookean", "sand"])
def test_cpu_grid_update_box_equals_the_whole_grid(material, monkeypatch):
    """On the CPU the grid update visits only the box of nodes the particles' stencils reach
    (:meth:`MPMSimulator._update_box`). States and gradients equal those of the slow, obvious
    whole-grid update exactly, through a bounce on the ground, and the box is a small part of the
    grid. Launched one by one: a captured graph (``graphs="auto"`` captures this small grid on the
    CPU) visits the whole grid."""
    sim, x0, w, _ = _scene(material, "cpu", graphs=False)
    args = (x0, torch.tensor([0.3, -0.5, 0.1]), sim.material.to_raw(CASES[material]), torch.tensor([0.0, -9.8, 0.0]))
    visited = []
    box = MPMSimulator._update_box

    def spy(self, s_in, tracers):
        offset, dims = box(self, s_in, tracers)
        visited.append(dims[0] * dims[1] * dims[2] / float(self._grid.dims[0] * self._grid.dims[1] * self._grid.dims[2]))
        return offset, dims

    def run():
        leaves = [t.clone().requires_grad_() for t in args]
        params = sim.material.to_physical(leaves[2])
        out = sim.simulate(leaves[0], leaves[1], params, gravity=leaves[3], n_frames=4)
        loss = (out.positions[1:] * w[:4]).sum() + 0.3 * (out.velocities[1:] * w[:4]).sum()
        loss.backward()
        return out.positions.detach(), [t.grad for t in leaves]

    monkeypatch.setattr(MPMSimulator, "_update_box", spy)
    pos_box, grads_box = run()
    monkeypatch.setattr(MPMSimulator, "_update_box", lambda self, s_in, tracers: (wp.vec3i(0, 0, 0), self._grid.dims))
    pos_full, grads_full = run()
    assert torch.equal(pos_box, pos_full)
    for a, b in zip(grads_box, grads_full):
        assert torch.equal(a, b) and a.abs().max() > 0
    assert float(pos_box[:, :, 1].min()) < 0.06  # the body reached the ground layers
    assert visited and max(visited) < 0.5


def _grads_and_states(sim, x0, w, material, n_frames=4):
    leaves = [t.clone().requires_grad_() for t in (x0, torch.tensor([0.3, -0.5, 0.1]), sim.material.to_raw(CASES[material]),
                                                   torch.tensor([0.0, -9.8, 0.0]))]
    params = sim.material.to_physical(leaves[2])
    out = sim.simulate(leaves[0], leaves[1], params, gravity=leaves[3], n_frames=n_frames)
    loss = (out.positions[1:] * w[:n_frames].to(out.positions.device)).sum() + 0.3 * (out.velocities[1:] * w[:n_frames].to(out.positions.device)).sum()
    loss.backward()
    return out.positions.detach().cpu(), [t.grad.cpu() for t in leaves]


@pytest.mark.parametrize("material", ["neo_hookean", "plasticine", "sand"])
def test_kept_tapes_equal_the_recompute(material, device):
    """Kept tapes (toolkit.mpm.tapes: the forward pass records every chunk, the backward pass runs
    adjoints only) give the states and gradients of the slow, obvious recompute from checkpoints,
    bit for bit (deterministic atomics on CUDA), through a bounce; the forward really kept its
    tapes (one buffer set per chunk) and the recompute pool was never allocated."""
    results = {}
    for keep in (False, True):
        sim, x0, w, _ = _scene(material, device, keep_tapes=keep, deterministic=True)
        results[keep] = _grads_and_states(sim, x0, w, material)
        pools = [k for k in sim._buffers if k[0] == "pool"]
        kept = [v for k, v in sim._buffers.items() if k[0] == "tapes"]
        if keep:
            assert not pools and len(kept) == 1 and len(kept[0].pools) == len(sim.chunks(4, sim.last_plan.substeps))
        else:
            assert pools and not kept
    (pos_a, grads_a), (pos_b, grads_b) = results[False], results[True]
    assert torch.equal(pos_a, pos_b)
    assert float(pos_a[:, :, 1].min()) < 0.06  # the body reached the ground layers
    for a, b in zip(grads_a, grads_b):
        assert torch.equal(a, b) and a.abs().max() > 0


def test_kept_tapes_overwritten_by_a_later_forward_fall_back_to_the_recompute(device):
    """Two differentiable rollouts before one backward pass: the first one's tapes were reused by
    the second, so its backward pass recomputes from its checkpoints (and the second's then does
    too, as the recompute rewrote the inputs its tapes read); every gradient still equals the one
    computed alone. A forward-only rollout in between invalidates the tapes the same way."""
    sim, x0, w, _ = _scene("plasticine", device, keep_tapes=True, deterministic=True)
    values = [{"E": 2e4, "nu": 0.3, "yield_stress": 300.0}, {"E": 5e4, "nu": 0.2, "yield_stress": 500.0}]

    def loss_of(raw, v0):
        return _loss(sim, w, x0, v0, raw, torch.tensor([0.0, -9.8, 0.0]))

    alone = []
    for vals in values:
        raw = sim.material.to_raw(vals).requires_grad_()
        v0 = torch.tensor([0.3, -0.5, 0.1], requires_grad=True)
        loss_of(raw, v0).backward()
        alone.append((raw.grad.clone(), v0.grad.clone()))
    leaves = [(sim.material.to_raw(vals).requires_grad_(), torch.tensor([0.3, -0.5, 0.1], requires_grad=True)) for vals in values]
    losses = [loss_of(*pair) for pair in leaves]
    losses[0].backward()
    losses[1].backward()
    for (raw, v0), (g_raw, g_v0) in zip(leaves, alone):
        assert torch.equal(raw.grad, g_raw) and torch.equal(v0.grad, g_v0)
    raw, v0 = sim.material.to_raw(values[0]).requires_grad_(), torch.tensor([0.3, -0.5, 0.1], requires_grad=True)
    loss = loss_of(raw, v0)
    sim.rollout(x0, torch.tensor([1.0, 0.0, 0.0]), sim.material.to_physical(sim.material.to_raw(values[1])), n_frames=2)
    loss.backward()
    assert torch.equal(raw.grad, alone[0][0]) and torch.equal(v0.grad, alone[0][1])


def test_kept_tapes_follow_the_memory_limit():
    """keep_tapes="auto" keeps the tapes only when every chunk's buffers take at most half the
    memory limit; the estimate counts (length + 1) states and length grids per chunk, with gradients."""
    from toolkit.mpm.tapes import KeptTapes, tape_bytes

    sim, x0, w, _ = _scene("neo_hookean", "cpu")
    _grads_and_states(sim, x0, w, "neo_hookean", n_frames=2)
    chunks = sim.chunks(2, sim.last_plan.substeps)
    need = tape_bytes(sim.grid.dims, x0.shape[0], [length for _, _, length in chunks])
    kept = next(v for k, v in sim._buffers.items() if k[0] == "tapes")
    allocated = sum(p.grads.base.capacity + p.grid_values.base.capacity for p in kept.pools.values())
    allocated += sum(len(p.grids) * int(np.prod(sim.grid.dims)) * 12 + sum(a.capacity for st in p.states for a in st.arrays())
                     for p in kept.pools.values())
    assert 0.9 * need <= allocated <= 1.1 * need
    sim.config.memory_limit = 2 * need
    assert KeptTapes.fit(sim, x0.shape[0], chunks)
    sim.config.memory_limit = 2 * need - 1
    assert not KeptTapes.fit(sim, x0.shape[0], chunks)
    sim.config.keep_tapes = True
    assert KeptTapes.fit(sim, x0.shape[0], chunks)
    sim.config.keep_tapes = False
    assert not KeptTapes.fit(sim, x0.shape[0], chunks)

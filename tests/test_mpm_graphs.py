"""When substep chains are captured as Warp graphs, and what a deterministic capture costs.

A captured deterministic CUDA launch keeps its sort-reduce scratch for the graph's lifetime, so
``graphs="auto"`` launches deterministic CUDA rollouts one by one (the truth generator's 45 GB, see
:func:`toolkit.mpm.config.captures_graphs`). The CUDA test measures that memory directly. On the
CPU ``auto`` captures small grids, deterministic or not.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from tests.mpm_scenes import block
from toolkit.mpm import MPMSimulator, SimConfig
from toolkit.mpm.config import CPU_GRAPH_MAX_NODES, captures_graphs


@pytest.mark.parametrize("mode,device,deterministic,nodes,expected", [
    ("auto", "cuda:0", False, None, True),
    ("auto", "cuda:0", False, 10**7, True),
    ("auto", "cuda:0", True, 1000, False),
    ("auto", "cpu", False, None, False),  # no grid yet
    ("auto", "cpu", False, CPU_GRAPH_MAX_NODES, True),
    ("auto", "cpu", False, CPU_GRAPH_MAX_NODES + 1, False),
    ("auto", "cpu", True, 1000, True),  # a CPU kernel is deterministic anyway and allocates no scratch
    (True, "cuda:0", True, None, True),
    (True, "cpu", False, 10**7, True),
    (False, "cuda:0", False, 1000, False),
    (False, "cpu", False, 1000, False),
])
def test_which_rollouts_capture_graphs(mode, device, deterministic, nodes, expected):
    assert captures_graphs(mode, device, deterministic, nodes) is expected


def test_simulator_follows_the_rule():
    """``auto`` on the CPU: captured on a small grid, launched one by one on a large one. A CPU
    chain is captured on its second use (:class:`~toolkit.mpm.graph_cache.GraphCache`), so the
    third call replays graphs. Every call gives rollouts and gradients bit-identical to launching
    one by one (whose grid update visits only the box the particles reach; the nodes outside it
    carry no mass)."""
    sim = MPMSimulator("neo_hookean", SimConfig(dx=0.05, substeps=10, deterministic=True), device="cpu")
    assert sim.use_graphs() is False
    sim = MPMSimulator("neo_hookean", SimConfig(dx=0.05, substeps=10, graphs=True), device="cpu")
    assert sim.use_graphs() is True

    def runs(graphs, dx, calls=3):
        s = MPMSimulator("neo_hookean", SimConfig(dx=dx, substeps=10, boundary="sticky", graphs=graphs), device="cpu")
        assert s.use_graphs() is (graphs is True)  # no grid before the first rollout
        out = []
        for _ in range(calls):
            raw = s.material.to_raw({"E": 2e4, "nu": 0.3}).requires_grad_()
            v0 = torch.tensor([0.3, -0.5, 0.1], requires_grad=True)
            res = s.simulate(block((6, 6, 6), 0.0125, (0.5, 0.2, 0.5)), v0, s.material.to_physical(raw),
                             gravity=torch.tensor([0.0, -9.8, 0.0]), n_frames=3)
            (res.positions[1:] ** 2).sum().backward()
            out.append((res.positions.detach().numpy(), raw.grad.numpy(), v0.grad.numpy()))
            captured = len(s._graphs)
            if len(out) == 1:
                assert captured == 0  # first use: launched one by one
        return s, out

    small, auto_small = runs("auto", 0.05)
    assert np.prod(small.grid.dims) <= CPU_GRAPH_MAX_NODES and small.use_graphs() and len(small._graphs) > 0
    _, launched = runs(False, 0.05, calls=1)
    for call in auto_small:
        for a, b in zip(call, launched[0]):
            np.testing.assert_array_equal(a, b)
    large, _ = runs("auto", 0.01, calls=2)
    assert np.prod(large.grid.dims) > CPU_GRAPH_MAX_NODES and not large.use_graphs() and not large._graphs


def test_kept_tapes_capture_a_backward_only_for_a_captured_forward():
    """With kept tapes on the CPU, a pass that records its tapes launch by launch (a fresh tape per
    pass, whose id can be a dead tape's) never captures their backward. The forward chunks are
    captured first (on a key's second use; the first backward allocates gradient buffers, which
    starts a new cache), and their backward one pass later, keeping the tape in the entry. The
    gradients are the same on every pass."""
    sim = MPMSimulator("neo_hookean", SimConfig(dx=0.05, substeps=10, boundary="sticky", keep_tapes=True,
                                                checkpoint_every=5), device="cpu")
    x0 = block((6, 6, 6), 0.0125, (0.5, 0.2, 0.5))
    kinds, grads = [], []
    for _ in range(5):
        raw = sim.material.to_raw({"E": 2e4, "nu": 0.3}).requires_grad_()
        out = sim.simulate(x0, torch.tensor([0.3, -0.5, 0.1]), sim.material.to_physical(raw),
                           gravity=torch.tensor([0.0, -9.8, 0.0]), n_frames=2)
        (out.positions[1:] ** 2).sum().backward()
        grads.append(raw.grad.numpy())
        kinds.append(sorted({k[0] for k in sim._graphs}))
    first_taped = next(i for i, k in enumerate(kinds) if "taped" in k)
    first_backward = next(i for i, k in enumerate(kinds) if "tape_backward" in k)
    assert first_backward == first_taped + 1 and kinds[-1] == ["tape_backward", "taped"]
    taped = {id(v[1]) for k, v in sim._graphs.items() if k[0] == "taped"}
    assert all(id(v[1]) in taped for k, v in sim._graphs.items() if k[0] == "tape_backward")
    for g in grads[1:]:
        np.testing.assert_array_equal(g, grads[0])


def test_graph_cache_captures_a_key_on_its_min_uses_th_use():
    from toolkit.mpm.graph_cache import GraphCache

    cache = GraphCache(2)
    assert [cache.should_capture("a") for _ in range(2)] == [False, True]
    cache["a"] = "graph"
    assert cache.should_capture("a") and not cache.should_capture("b")
    assert GraphCache(1).should_capture("c")
    with pytest.raises(ValueError, match="min_uses"):
        GraphCache(0)


def _rollout(graphs, substeps: int, device: str) -> tuple[MPMSimulator, np.ndarray]:
    """A deterministic two-frame rollout of a 1728-particle block: the simulator (which owns its
    captured graphs) and the final positions (N, 3)."""
    cfg = SimConfig(dx=0.05, substeps=substeps, auto_substeps=False, checkpoint_every=25, graphs=graphs,
                    deterministic=True)
    sim = MPMSimulator("neo_hookean", cfg, device=device)
    x0 = block((12, 12, 12), 0.0125, (0.5, 0.2, 0.5))
    out = sim.rollout(x0, v0=np.array([0.3, -0.5, 0.1], np.float32), params=sim.material.pack({"E": 2e4, "nu": 0.3}),
                      n_frames=2)
    return sim, out.positions[-1].cpu().numpy()


def test_deterministic_cpu_rollout_is_captured_and_equals_launching_one_by_one():
    """On the CPU ``deterministic`` allocates no scratch, so ``auto`` captures a small grid's
    deterministic rollout too, with the same positions as launched. Both frames run the same
    chain of 20 substeps on the same buffers: the first is launched one by one, the second is
    captured and replayed, and a second rollout replays both."""
    _, launched = _rollout(False, 20, "cpu")
    assert launched.shape == (1728, 3) and np.isfinite(launched).all()
    assert launched[:, 1].mean() < 0.2  # it fell
    sim, first = _rollout("auto", 20, "cpu")
    assert sim.use_graphs() and len(sim._graphs) == 1
    x0 = block((12, 12, 12), 0.0125, (0.5, 0.2, 0.5))
    again = sim.rollout(x0, v0=np.array([0.3, -0.5, 0.1], np.float32), params=sim.material.pack({"E": 2e4, "nu": 0.3}),
                        n_frames=2).positions[-1].cpu().numpy()
    assert len(sim._graphs) == 1
    np.testing.assert_array_equal(first, launched)
    np.testing.assert_array_equal(again, launched)


def _memory_taken(graphs, substeps: int) -> tuple[int, np.ndarray]:
    """Bytes of device memory a deterministic rollout took (free memory before minus after: a
    graph's allocations are not in the pool's counters), and its final positions."""
    wp.synchronize_device("cuda:0")
    before = wp.get_device("cuda:0").free_memory
    sim, x = _rollout(graphs, substeps, "cuda:0")
    wp.synchronize_device("cuda:0")
    taken = before - wp.get_device("cuda:0").free_memory
    del sim
    return taken, x


@pytest.mark.skipif(not wp.is_cuda_available(), reason="measures CUDA device memory")
def test_deterministic_rollout_memory_does_not_grow_with_captured_substeps():
    """Captured: scratch for every substep of the frame stays allocated. Launched one by one: the
    scratch is reused, so far less is taken. Both give bit-identical positions. Measured on an H100
    at 200 substeps: 533 MB captured, 33.5 MB (one pool block) launched one by one; at 400 the
    captured graphs should hold about twice that. Free memory is the measure, so the card must not
    be shared with other processes while this runs."""
    captured, x_captured = _memory_taken(True, 400)
    launched, x_launched = _memory_taken("auto", 400)
    np.testing.assert_array_equal(x_captured, x_launched)
    assert captured > 10 * max(launched, 1 << 20), (captured, launched)

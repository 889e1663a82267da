"""Gaussians carried by the particles (toolkit.physics.embedding): exactness under affine motion,
a slow per-Gaussian least-squares twin, and the soft bias of the inverse-distance average."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from toolkit.physics.embedding import AFFINE_MIN_NEIGHBOURS, carry, embed


def _box_particles(spacing: float = 0.01, size=(0.12, 0.06, 0.08)) -> np.ndarray:
    axes = [np.arange(spacing / 2, s, spacing) for s in size]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _gaussians(particles: np.ndarray, rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """Means inside the body and up to 1.5 particle spacings outside its surface."""
    lo, hi = particles.min(0) - 0.015, particles.max(0) + 0.015
    return rng.uniform(lo, hi, size=(n, 3))


def _slow_affine_coefficients(P: np.ndarray, v: np.ndarray, idx: np.ndarray, ridge: float = 1e-6) -> np.ndarray:
    """Twin of the fast weights: solve the weighted least-squares affine fit for each basis motion
    (particle j moved by a unit vector, all others fixed) and read off the fit's value at v."""
    d = np.linalg.norm(P[idx] - v, axis=1)
    R = 1.05 * d[-1] + 1e-12
    w = (1.0 - (d / R) ** 2) ** 3 + 1e-9
    X = np.concatenate([P[idx] - v, np.ones((len(idx), 1))], axis=1)  # (k, 4)
    reg = ridge * R**2 * w.sum()
    A = X.T @ (w[:, None] * X) + np.diag([reg, reg, reg, 0.0])
    coeffs = np.empty(len(idx))
    for j in range(len(idx)):
        y = np.zeros(len(idx))
        y[j] = 1.0
        beta = np.linalg.solve(A, X.T @ (w * y))  # affine fit of the indicator field
        coeffs[j] = beta[3]  # its value at v (the offset term: X's rows are relative to v)
    return coeffs / coeffs.sum()


def test_affine_weights_match_their_slow_twin():
    rng = np.random.default_rng(0)
    P = _box_particles()
    V = _gaussians(P, rng, n=40)
    idx, w = embed(torch.tensor(V), torch.tensor(P), k=8, mode="affine")
    assert idx.shape == (40, AFFINE_MIN_NEIGHBOURS)
    for g in range(40):
        slow = _slow_affine_coefficients(P, V[g], idx[g].numpy())
        np.testing.assert_allclose(w[g].numpy(), slow, atol=2e-5)
    np.testing.assert_allclose(w.sum(1).numpy(), 1.0, atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_affine_embedding_follows_any_affine_motion_exactly(seed):
    """A stretch, shear and rotation of the particles moves every Gaussian, inside the body or
    outside its surface, exactly as it moves the material there: x_g(t) = A x_g(0) + b."""
    rng = np.random.default_rng(seed)
    P = _box_particles()
    V = _gaussians(P, rng)
    A = np.eye(3) + rng.normal(0.0, 0.25, size=(3, 3))
    b = rng.normal(0.0, 0.1, size=3)
    moved = P @ A.T + b
    idx, w = embed(torch.tensor(V, dtype=torch.float32), torch.tensor(P, dtype=torch.float32), mode="affine")
    means = carry(torch.tensor(V, dtype=torch.float32), torch.tensor(moved[None], dtype=torch.float32),
                  torch.tensor(P, dtype=torch.float32), idx, w)[0].numpy()
    np.testing.assert_allclose(means, V @ A.T + b, atol=1e-4)  # 1 % of the spacing, at 1.5 spacings outside a corner (the ridge)


def test_inverse_distance_average_understates_a_stretch():
    """The default: under a 30 % horizontal stretch, a Gaussian 1 cm outside the end face of a 12 cm
    bar moves with the mean of its neighbours, short of where the material's end goes; the affine
    embedding puts it there."""
    P = _box_particles()
    end = np.array([[0.12 + 0.01, 0.03, 0.04]])  # 1 cm beyond the end face x = 0.12
    A = np.diag([1.3, 1.0, 1.0])
    moved = P @ A.T
    target = (end @ A.T)[0, 0]
    out = {}
    for mode in ("idw", "affine"):
        idx, w = embed(torch.tensor(end), torch.tensor(P), k=8, mode=mode)
        out[mode] = carry(torch.tensor(end), torch.tensor(moved[None]), torch.tensor(P), idx, w)[0, 0, 0].item()
    assert abs(out["affine"] - target) < 1e-5  # float32 weights
    # the inverse-distance Gaussian lags the end by about 0.3 x (its distance to its neighbours' mean)
    assert target - out["idw"] > 0.004


def test_embedding_rejects_an_unknown_mode():
    with pytest.raises(ValueError, match="embedding mode must be one of"):
        embed(torch.zeros(1, 3), torch.rand(10, 3), mode="nearest")


def test_few_particles_fall_back_to_inverse_distance():
    P = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    idx, w = embed(torch.tensor([[0.005, 0.005, 0.0]]), P, mode="affine")
    assert idx.shape == (1, 3) and bool((w > 0).all()) and abs(float(w.sum()) - 1.0) < 1e-6


def test_a_run_saved_with_another_embedding_keeps_it(tmp_path):
    """A fit saved with 8 inverse-distance weights per Gaussian loads into a module built with the
    affine embedding (24 per Gaussian): the buffers take the saved shape and values, so the run
    replays as it was fitted."""
    from tests.physics_fixtures import fit_sim, tiny_scene
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.oracle import oracle_input

    inp = oracle_input(tiny_scene(tmp_path / "scene"), particle_spacing=0.02)
    old = InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", material_init="given")
    new = InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", embedding="affine", material_init="given")
    assert old.embed_index.shape[1] == 8 and new.embed_index.shape[1] == AFFINE_MIN_NEIGHBOURS
    new.load_state_dict(old.state_dict())
    assert torch.equal(new.embed_index, old.embed_index) and torch.equal(new.embed_weight, old.embed_weight)


@pytest.mark.parametrize("seed", [0, 3])
def test_local_deformation_is_the_affine_map_of_the_neighbourhood(seed):
    """Under x -> A x + b every Gaussian's local deformation gradient is A (inside the body and
    1.5 spacings outside it), and the identity at frame 0."""
    from toolkit.physics.embedding import local_deformation

    rng = np.random.default_rng(seed)
    P = _box_particles()
    V = _gaussians(P, rng, n=100)
    A = np.eye(3) + rng.normal(0.0, 0.3, size=(3, 3))
    idx, grad = local_deformation(torch.tensor(V), torch.tensor(P))
    for positions, expected in ((P, np.eye(3)), (P @ A.T + rng.normal(size=3), A)):
        got = torch.einsum("gki,gkj->gij", torch.tensor(positions, dtype=torch.float32)[idx], grad).numpy()
        np.testing.assert_allclose(got, np.broadcast_to(expected, got.shape), atol=1e-3)  # measured 3e-4 (ridge)


@pytest.mark.parametrize("seed", [0, 5])
def test_carried_deformation_is_relative_to_the_fits_frame_zero(seed):
    """carry_deformation gives the identity at frame 0 even when frame 0 is itself an affine image
    of the positions the coefficients were fitted on (a fit's position offsets), and exactly A B^-1
    when frame 0 is B x and frame t is A x (plus translations far from the origin, in float32)."""
    from toolkit.physics.embedding import carry_deformation, local_deformation

    rng = np.random.default_rng(seed)
    P = _box_particles()
    V = _gaussians(P, rng, n=60)
    idx, grad = local_deformation(torch.tensor(V), torch.tensor(P))
    B = np.eye(3) + rng.normal(0.0, 0.05, size=(3, 3))
    A = np.eye(3) + rng.normal(0.0, 0.3, size=(3, 3))
    far = np.array([40.0, -25.0, 3.0])  # metres from the origin: the map must not lose the cm scale
    x0 = torch.tensor(P @ B.T + far, dtype=torch.float32)
    frames = torch.tensor(np.stack([P @ B.T + far, P @ A.T + far + 1.0]), dtype=torch.float32)
    got = carry_deformation(frames, x0, idx, grad).numpy()
    assert got.shape == (2, 60, 3, 3)
    np.testing.assert_allclose(got[0], np.broadcast_to(np.eye(3), got[0].shape), atol=2e-3)
    np.testing.assert_allclose(got[1], np.broadcast_to(A @ np.linalg.inv(B), got[1].shape), atol=3e-3)


def test_deformed_gaussians_in_the_fit_follow_a_stretch_and_carry_gradients(tmp_path):
    """A module with gaussian_shape='deformed' renders each Gaussian with its neighbourhood's
    deformation (the identity at the fit's own frame 0, a stretch's A after it), gradients reach
    the particle positions through the covariances, and a rigid module renders none."""
    from tests.physics_fixtures import fit_sim, tiny_scene
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.oracle import oracle_input

    inp = oracle_input(tiny_scene(tmp_path / "scene"), particle_spacing=0.02)
    rigid = InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", material_init="given", gaussian_shape="rigid")
    deformed = InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", material_init="given", gaussian_shape="deformed")
    x0 = deformed.particles0.clone()
    A = torch.tensor([[1.4, 0.0, 0.0], [0.0, 0.7, 0.0], [0.0, 0.0, 1.0]])
    stretched = (x0 - x0.mean(0)) @ A.T + x0.mean(0)
    positions = torch.stack([x0, stretched]).requires_grad_(True)
    g0, g1 = deformed.gaussians_at(positions, x0)
    assert rigid.gaussians_at(positions.detach(), x0)[1].deformation is None
    torch.testing.assert_close(g0.deformation, torch.eye(3).expand_as(g0.deformation), atol=2e-3, rtol=0)
    torch.testing.assert_close(g1.deformation, A.expand_as(g1.deformation), atol=5e-3, rtol=0)
    cams = deformed.input.cameras[list(deformed.input.train_cameras)]
    # means detached: whatever reaches the positions comes through the covariances
    alpha = deformed.renderer(g1.replace(means=g1.means.detach()), cams).alpha.sum()
    (grad,) = torch.autograd.grad(alpha, positions)
    assert float(grad[1].abs().sum()) > 0
    with pytest.raises(ValueError, match="gaussian_shape must be one of"):
        InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", material_init="given", gaussian_shape="soft")


def test_a_run_saved_before_deformed_shapes_replays_rigid(tmp_path):
    """A checkpoint without the deformation buffers (saved before Gaussians could deform) loads
    into a module built with the default deformed shapes as rigid: it renders as it was fitted."""
    from tests.physics_fixtures import fit_sim, tiny_scene
    from toolkit.physics import InversePhysicsModule
    from toolkit.physics.oracle import oracle_input

    inp = oracle_input(tiny_scene(tmp_path / "scene"), particle_spacing=0.02)
    old = InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", material_init="given", gaussian_shape="rigid")
    state = {k: v for k, v in old.state_dict().items() if not k.startswith("deform_")}
    new = InversePhysicsModule(inp, sim=fit_sim(), renderer="torch", material_init="given")
    assert new.gaussian_shape == "deformed" and new.deform_index.numel() > 0
    new.load_state_dict(state)
    x0 = new.particles0
    assert new.deform_index.numel() == 0 and new.gaussian_shape == "rigid"
    assert new.gaussians_at(torch.stack([x0, x0 * 1.1]), x0)[1].deformation is None

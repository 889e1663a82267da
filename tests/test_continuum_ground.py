"""The ground bounds stage 0's continuum (toolkit.scene.continuum_ground) and its Gaussians."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from toolkit.scene.continuum import ContinuumConfig, build_continuum
from toolkit.scene.continuum_ground import carve_through_time, height_above
from toolkit.scene.stage0 import Gaussians4DModule

from tests.test_stage0 import _ring_cameras, _sphere_gaussians, _sphere_masks

GROUND = ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))


def _block(spacing: float = 0.01) -> torch.Tensor:
    """11 x 11 x 11 lattice points, x, z in [0, 0.1], y in [0.2, 0.3] (metres)."""
    r = torch.arange(11, dtype=torch.float64) * spacing
    x, y, z = torch.meshgrid(r, r + 0.2, r, indexing="ij")
    return torch.stack([x, y, z], -1).reshape(-1, 3).float()


@pytest.mark.parametrize("drop, floor", [(0.25, 0.0), (0.27, -0.02)])
def test_carve_through_time_removes_what_a_frame_carries_below_its_floor(drop, floor):
    """A block whose upper half carries the motion (the Gaussians the cameras saw) is translated
    down by ``drop``: its carriers reach y = 0.25 - drop. With drop 0.25 they touch the ground
    and the particles carried more than the tolerance (1.5 spacings) below it (y < 0.235 at the
    first frame: 4 of the 11 layers) go. With drop 0.27 the model itself sinks its carriers 2 cm into the ground:
    that frame's floor is their lowest point, and the same 4 layers go, not 6."""
    spacing = 0.01
    pts = _block(spacing)
    carriers = pts[pts[:, 1] >= 0.25 - 1e-6]
    later = carriers - torch.tensor([0.0, drop, 0.0])
    keep, removed, floors = carve_through_time(pts, carriers, [later], GROUND, tolerance=1.5 * spacing)
    layer = 11 * 11
    assert floors == [pytest.approx(floor, abs=1e-6)]
    assert removed == [4 * layer] and int((~keep).sum()) == 4 * layer
    assert float(pts[~keep][:, 1].max()) < 0.235 < float(pts[keep][:, 1].min())
    # a frame that carries nothing below the floor removes nothing
    keep2, removed2, _ = carve_through_time(pts, carriers, [carriers], GROUND, tolerance=1.5 * spacing)
    assert bool(keep2.all()) and removed2 == [0]


def test_height_above_a_tilted_plane():
    n = torch.tensor([1.0, 2.0, 2.0])  # |n| = 3
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0], [-0.5, -1.0, -1.0]])
    h = height_above(pts, ((0.0, 0.0, 0.0), n.tolist()))
    torch.testing.assert_close(h, torch.tensor([0.0, 3.0, -1.5]))


def test_nothing_below_the_ground_becomes_object():
    """A sphere of radius 0.1 m centred 5 cm above the ground, seen with exact silhouettes by 12
    cameras: with the ground given, no particle or surface point lies more than half a voxel below
    it and the volume is the cap above the ground's (pi h^2 (3r - h) / 3, h = 0.15 m) within the
    15 % of the sphere test; without it, the whole sphere's."""
    centre, radius = (0.0, 0.05, 0.0), 0.1
    cams = _ring_cameras(centre)
    masks = _sphere_masks(cams, centre, radius)
    cfg = ContinuumConfig(grid_size=0.05, final_level=3, candidate_level=3)
    g = _sphere_gaussians(3000, radius, centre)
    clipped = build_continuum(g, cams, masks, frames=[0], config=cfg, renderer="warp", ground=GROUND)
    whole = build_continuum(g, cams, masks, frames=[0], config=dataclasses.replace(cfg, ground_clip=False), renderer="warp",
                            ground=GROUND)
    h = clipped.spacing
    assert float(clipped.particles[:, 1].min()) >= -h / 2 and float(clipped.surfaces[0][:, 1].min()) >= -h / 2
    cap = math.pi * 0.15**2 * (3 * radius - 0.15) / 3
    assert abs(clipped.volume / cap - 1.0) < 0.15, (clipped.volume, cap)
    assert float(whole.particles[:, 1].min()) < -0.04  # the sphere reaches y = -0.05
    assert abs(whole.volume / (4 / 3 * math.pi * radius**3) - 1.0) < 0.15


def test_a_body_that_lands_keeps_its_particles():
    """Frame 0: the sphere at 0.3 m; frame 1: the same Gaussians resting on the ground (lowest
    centre 1 mm above it). Carried to frame 1 no real particle goes below the ground, so the
    carve through time removes (almost) nothing, and says which frames it used."""
    radius = 0.1
    up = (0.0, 0.3, 0.0)
    down = (0.0, radius + 0.001, 0.0)
    cams = _ring_cameras((0.0, 0.2, 0.0), distance=1.0)
    masks = torch.stack([_sphere_masks(cams, up, radius), _sphere_masks(cams, down, radius)])
    g0 = _sphere_gaussians(3000, radius, up)
    g1 = g0.replace(means=g0.means - torch.tensor([0.0, 0.3 - down[1], 0.0]))
    cfg = ContinuumConfig(grid_size=0.05, final_level=3, candidate_level=3)
    res = build_continuum([g0, g1], cams, masks, times=[0.0, 0.1], config=cfg, renderer="warp", ground=GROUND)
    carve = res.stats["frames"][0]["ground_carve"]
    assert carve["frames"] == [1] and carve["floor_per_frame"] == [0.0]
    assert carve["removed"] <= 0.01 * (res.particles.shape[0] + carve["removed"]), carve
    assert float(res.surfaces[1][:, 1].min()) >= -res.spacing / 2
    # a lost frame is not used
    res2 = build_continuum([g0, g1], cams, masks, times=[0.0, 0.1], config=cfg, renderer="warp", ground=GROUND,
                           lost_frames=[1])
    assert res2.stats["frames"][0]["ground_carve"]["frames"] == []


def test_a_body_below_the_ground_is_reported_as_such():
    """Every Gaussian below the ground (a wrong world): the empty continuum names the ground."""
    centre, radius = (0.0, -0.3, 0.0), 0.1
    cams = _ring_cameras(centre)
    res = build_continuum(_sphere_gaussians(500, radius, centre), cams, _sphere_masks(cams, centre, radius), frames=[0],
                          config=ContinuumConfig(grid_size=0.05, final_level=3, candidate_level=3), renderer="warp",
                          ground=GROUND)
    assert res.particles.shape[0] == 0 and "below the dataset's ground plane" in res.empty_reason()


def test_ground_settings_are_checked():
    from toolkit.scene.stage0 import Stage0Schedule

    with pytest.raises(ValueError, match="ground_clip must be true or false"):
        ContinuumConfig(ground_clip="yes")
    with pytest.raises(ValueError, match="stage 0 ground must be true or false, got 'yes'"):
        Stage0Schedule(ground="yes")


def test_stage0_renders_positions_below_the_ground_on_it():
    """``Gaussians4DModule.on_ground``: positions below the plane move onto it along its normal,
    those above stay, and the gradient passes straight through (so the images can lift them);
    without a plane (old checkpoints) nothing changes, and such a checkpoint still loads."""
    m = Gaussians4DModule()
    x = torch.tensor([[0.0, -0.05, 0.1], [0.2, 0.3, 0.0]], requires_grad=True)
    assert torch.equal(m.on_ground(x), x)
    m = Gaussians4DModule()
    m.ground_plane.copy_(torch.tensor([0.0, 0.0, 0.0, 0.0, 1.0, 0.0]))
    y = m.on_ground(x)
    torch.testing.assert_close(y.detach(), torch.tensor([[0.0, 0.0, 0.1], [0.2, 0.3, 0.0]]))
    (grad,) = torch.autograd.grad((y * torch.tensor([1.0, 2.0, 3.0])).sum(), x)
    torch.testing.assert_close(grad, torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]))
    ckpt = {"state_dict": {"gaussians.means": torch.zeros(4, 3)}, "stage0": {}}
    m.on_load_checkpoint(ckpt)  # a checkpoint from before the plane: the module forgets its own
    assert torch.isnan(ckpt["state_dict"]["ground_plane"]).all() and torch.equal(m.on_ground(x), x)



def test_stage0_with_the_ground_keeps_its_plane_through_a_checkpoint(tmp_path):
    """A short stage 0 with ``ground: true`` on a generated torus that lands in its last training
    frame: the plane is the scene's world, every deformed centre of every frame is above it, and
    a model loaded from the checkpoint has the same plane (a default stage 0 has none)."""
    from tests.test_stage0 import _tiny_scene
    from toolkit.data import load_scene
    from toolkit.scene.stage0 import Stage0DataModule, Stage0Schedule, fit_stage0

    scene = load_scene(_tiny_scene(tmp_path))
    dm = Stage0DataModule(scene, cameras="sparse", n_train=7)
    schedule = {**Stage0Schedule.tiny().to_dict(), "iterations": 120, "warmup": 40, "ground": True}
    model = fit_stage0(dm, Gaussians4DModule.from_preset("tiny", schedule=schedule), out_dir=tmp_path / "ck",
                       checkpoint_every=1000, accelerator="cpu")
    torch.testing.assert_close(model.ground_plane, torch.tensor([0.0, 0.0, 0.0, 0.0, 1.0, 0.0]))
    centres = model.centers_at(dm.training_views().times)
    assert float(height_above(centres.reshape(-1, 3), GROUND).min()) >= -1e-6
    loaded = Gaussians4DModule.load_from_checkpoint(tmp_path / "ck" / "last.ckpt", map_location="cpu")
    torch.testing.assert_close(loaded.ground_plane, model.ground_plane)
    below = torch.tensor([[0.0, -0.2, 0.0]])
    assert float(loaded.on_ground(below)[0, 1]) == 0.0
    assert torch.isnan(Gaussians4DModule.from_preset("tiny").ground_plane).all()

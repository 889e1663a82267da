"""toolkit.cameras: conventions, constructors, round trips and validation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from toolkit.cameras import Cameras, rodrigues, rotmat_to_rodrigues


def _random_rotations(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _random_cameras(n: int = 3, seed: int = 0) -> Cameras:
    g = torch.Generator().manual_seed(seed)
    w2c = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    w2c[:, :3, :3] = _random_rotations(n, seed)
    w2c[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[50.0, 0, 31.3], [0, 55.0, 22.7], [0, 0, 1]]).repeat(n, 1, 1)
    K[:, 0, 0] += torch.arange(n)
    return Cameras(K, w2c.float(), width=64, height=48)


# ---------------------------------------------------------------- hand-computed projections


def test_opengl_c2w_projects_by_hand():
    # OpenGL camera at (0, 0, 5) with identity rotation looks along world -z at the origin.
    c2w = torch.eye(4)
    c2w[2, 3] = 5.0
    cam = Cameras.from_opengl_c2w(c2w, fx=100.0, fy=100.0, cx=32.0, cy=24.0, width=64, height=48)
    # world (1, 0.5, 0) -> OpenCV camera (x, y, z) = (1, -0.5, 5)   (y flips to point down, z = 5 - 0)
    # u = 100 * 1 / 5 + 32 = 52 ; v = 100 * (-0.5) / 5 + 24 = 14
    pix, depth = cam.project(torch.tensor([[1.0, 0.5, 0.0]]))
    assert torch.allclose(pix[0, 0], torch.tensor([52.0, 14.0]), atol=1e-5)
    assert torch.allclose(depth[0, 0], torch.tensor(5.0))
    assert torch.allclose(cam.centers[0], torch.tensor([0.0, 0.0, 5.0]))


def test_blender_projects_by_hand():
    # camera_angle_x = 2 atan(0.5): fx = 0.5 * 64 / tan(atan(0.5)) = 64; cx = 64 / 2 = 32, cy = 48 / 2 = 24.
    # transform_matrix: rotation of +90 deg about y, camera at (5, 0, 0): its -z axis (view
    # direction) is world -x, its x axis (image right) is world -z, its y axis (image up) world +y.
    c2w = [[0.0, 0.0, 1.0, 5.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    cam = Cameras.from_blender(2 * math.atan(0.5), c2w, width=64, height=48)
    assert torch.allclose(cam.fx, torch.tensor([64.0])) and torch.allclose(cam.fy, torch.tensor([64.0]))
    assert torch.allclose(cam.cx, torch.tensor([32.0])) and torch.allclose(cam.cy, torch.tensor([24.0]))
    # world (0, 1, 0.5): offset from the camera (-5, 1, 0.5); OpenGL camera coords
    # (x, y, z) = (-0.5, 1, -5) -> OpenCV (-0.5, -1, 5); u = 64 * -0.5 / 5 + 32 = 25.6, v = 64 * -1 / 5 + 24 = 11.2
    pix, depth = cam.project(torch.tensor([[0.0, 1.0, 0.5]]))
    assert torch.allclose(pix[0, 0], torch.tensor([25.6, 11.2]), atol=1e-5)
    assert torch.allclose(depth[0, 0], torch.tensor(5.0))


def test_opencv_projects_by_hand():
    # rvec = (0, pi, 0): R = rotation by 180 deg about y = diag(-1, 1, -1); t = (0, 0, 5)
    K = [[100.0, 0.0, 30.0], [0.0, 110.0, 20.0], [0.0, 0.0, 1.0]]
    cam = Cameras.from_opencv([0.0, math.pi, 0.0], [0.0, 0.0, 5.0], K, width=64, height=48)
    assert torch.allclose(cam.R[0], torch.diag(torch.tensor([-1.0, 1.0, -1.0])), atol=1e-6)
    # world (1, 0.5, 0) -> camera R x + t = (-1, 0.5, 5); u = 100 * -1 / 5 + 30 = 10, v = 110 * 0.5 / 5 + 20 = 31
    pix, depth = cam.project(torch.tensor([[1.0, 0.5, 0.0]]))
    assert torch.allclose(pix[0, 0], torch.tensor([10.0, 31.0]), atol=1e-5)
    assert torch.allclose(depth[0, 0], torch.tensor(5.0))
    assert torch.allclose(cam.centers[0], torch.tensor([0.0, 0.0, 5.0]), atol=1e-6)


def test_look_at_projects_by_hand():
    # fov_y = 90 deg: fy = fx = 0.5 * 48 / tan(45 deg) = 24; cx = 32, cy = 24
    cam = Cameras.look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), fov_y_deg=90.0, width=64, height=48)
    assert torch.allclose(cam.K[0], torch.tensor([[24.0, 0, 32], [0, 24, 24], [0, 0, 1]]))
    # world (1, 0.5, 0) -> camera (1, -0.5, 5): u = 24 * 1 / 5 + 32 = 36.8, v = 24 * -0.5 / 5 + 24 = 21.6
    pix, depth = cam.project(torch.tensor([[1.0, 0.5, 0.0]]))
    assert torch.allclose(pix[0, 0], torch.tensor([36.8, 21.6]), atol=1e-5)
    assert torch.allclose(depth[0, 0], torch.tensor(5.0))


def test_pixel_centre_convention():
    # principal point at the image centre (W/2, H/2) lies on the corner of the four central pixels;
    # the centre of pixel (0, 0) is at (0.5, 0.5) and unprojects to the corner ray offset by 0.5 px.
    cam = Cameras.look_at((0.0, 0.0, 5.0), fov_y_deg=60.0, width=8, height=8)
    world = cam.unproject(torch.tensor([[[0.5, 0.5]]]), torch.tensor([[5.0]]))
    pix, _ = cam.project(world[0])
    assert torch.allclose(pix, torch.tensor([[[0.5, 0.5]]]), atol=1e-5)
    assert torch.allclose(cam.cx, torch.tensor([4.0])) and torch.allclose(cam.cy, torch.tensor([4.0]))


# ---------------------------------------------------------------- round trips


def test_opengl_round_trip():
    c2w = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    c2w[:, :3, :3] = _random_rotations(4, seed=1)
    c2w[:, :3, 3] = torch.randn(4, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 3
    cam = Cameras.from_opengl_c2w(c2w, fx=80.0, width=64, height=48)
    assert torch.allclose(cam.c2w_opengl().double(), c2w, atol=1e-5)
    assert torch.allclose(cam.centers.double(), c2w[:, :3, 3], atol=1e-5)
    # (3, 4) c2w as stored by some datasets
    cam34 = Cameras.from_opengl_c2w(c2w[:, :3, :], cam.K, width=64, height=48)
    assert torch.allclose(cam34.w2c, cam.w2c)
    # the OpenGL camera looks along its -z axis: c2w_opencv's z column is minus the OpenGL one
    assert torch.allclose(cam.c2w_opencv()[:, :3, 2].double(), -c2w[:, :3, 2], atol=1e-5)


def test_opencv_round_trip_and_rodrigues():
    g = torch.Generator().manual_seed(3)
    rvec = torch.randn(5, 3, generator=g, dtype=torch.float64)
    tvec = torch.randn(5, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[70.0, 0, 30], [0, 70, 25], [0, 0, 1]])
    cam = Cameras.from_opencv(rvec[:, :, None], tvec[:, :, None], K, width=64, height=48)
    assert torch.allclose(cam.R.double(), rodrigues(rvec), atol=1e-6)
    assert torch.allclose(cam.t.double(), tvec, atol=1e-6)
    assert torch.allclose(rotmat_to_rodrigues(cam.R), rvec, atol=1e-5)
    # rodrigues agrees with scipy and with a hand-written rotation
    from scipy.spatial.transform import Rotation

    assert np.allclose(rodrigues(rvec).numpy(), Rotation.from_rotvec(rvec.numpy()).as_matrix(), atol=1e-12)
    Rz = rodrigues(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))[0]
    assert torch.allclose(Rz, torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(rodrigues(torch.zeros(3, dtype=torch.float64))[0], torch.eye(3, dtype=torch.float64))
    # differentiable at zero
    r = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rodrigues, (r,))
    # angles near pi
    for v in ([math.pi, 0, 0], [0, 3.14159, 0], [1e-9, 0, 0]):
        rv = torch.tensor([v], dtype=torch.float64)
        assert torch.allclose(rodrigues(rotmat_to_rodrigues(rodrigues(rv))), rodrigues(rv), atol=1e-6)


def test_blender_matches_opengl_constructor():
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[:, :3, :3] = _random_rotations(2, seed=4).float()
    c2w[:, :3, 3] = torch.tensor([[0.0, 1.0, 4.0], [3.0, 1.0, -2.0]])
    angle = 0.69
    cam = Cameras.from_blender(angle, c2w, width=80, height=60)
    f = 0.5 * 80 / math.tan(0.5 * angle)
    ref = Cameras.from_opengl_c2w(c2w, fx=f, width=80, height=60)
    assert torch.allclose(cam.K, ref.K) and torch.allclose(cam.w2c, ref.w2c)
    assert torch.allclose(cam.c2w_opengl(), c2w, atol=1e-5)


def test_project_unproject_round_trip():
    cam = _random_cameras(3)
    pts = torch.randn(10, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    pix, depth = cam.project(pts)
    assert pix.shape == (3, 10, 2) and depth.shape == (3, 10) and pix.dtype == torch.float64
    back = cam.unproject(pix, depth)
    assert torch.allclose(back, pts.expand(3, -1, -1), atol=1e-5)
    # world_to_camera agrees with the 4x4 matrix
    homog = torch.cat([pts, torch.ones(10, 1, dtype=torch.float64)], -1)
    ref = (cam.w2c.double() @ homog.T).transpose(-1, -2)[..., :3]
    assert torch.allclose(cam.world_to_camera(pts), ref, atol=1e-6)
    # batched points (B, N, 3)
    pix_b, _ = cam.project(pts.expand(3, -1, -1))
    assert torch.allclose(pix_b, pix)


def test_project_is_differentiable():
    cam = _random_cameras(2)
    # points in front of camera 0 (pixels lifted to depths 4 and 6)
    pix = torch.tensor([[[20.0, 20.0], [40.0, 30.0]]], dtype=torch.float64)
    world = cam[0].unproject(pix, torch.tensor([[4.0, 6.0]], dtype=torch.float64))[0]
    pts = world.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: cam.project(p)[0], (pts,))


def test_look_at_points_axis_at_target():
    eyes = torch.tensor([[3.0, 2.0, 4.0], [-2.0, 0.5, 1.0], [0.0, 5.0, 0.1]])
    targets = torch.tensor([[0.0, 0.5, 0.0], [1.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    cam = Cameras.look_at(eyes, targets, fov_y_deg=50.0, width=40, height=30)
    fwd = (targets - eyes) / (targets - eyes).norm(dim=-1, keepdim=True)
    assert torch.allclose(cam.R[:, 2], fwd, atol=1e-6)  # camera z axis (third row of R) = view direction
    pix, depth = cam.project(targets[:, None, :].clone())
    assert torch.allclose(pix[:, 0], torch.tensor([[20.0, 15.0]]).expand(3, 2), atol=1e-4)
    assert torch.allclose(depth[:, 0], (targets - eyes).norm(dim=-1), atol=1e-5)
    assert torch.allclose(cam.centers, eyes, atol=1e-5)
    # world up (+y) appears upward (smaller v) in the image
    above = targets + torch.tensor([0.0, 0.1, 0.0])
    pix_up, _ = cam.project(above[:, None, :].clone())
    assert (pix_up[:, 0, 1] < pix[:, 0, 1]).all()
    with pytest.raises(ValueError, match="parallel to up"):
        Cameras.look_at((0.0, 5.0, 0.0), (0.0, 0.0, 0.0), fov_y_deg=50.0, width=4, height=4)
    with pytest.raises(ValueError, match="exactly one of fov_y_deg or K"):
        Cameras.look_at((0.0, 0.0, 5.0), width=4, height=4)


# ---------------------------------------------------------------- container behaviour


def test_indexing_cat_to_and_dict():
    cam = _random_cameras(4)
    assert len(cam) == 4
    assert len(cam[1]) == 1 and torch.equal(cam[1].w2c[0], cam.w2c[1])
    assert torch.equal(cam[-1].K[0], cam.K[3])
    assert len(cam[1:3]) == 2 and len(cam[[0, 2, 3]]) == 3
    assert torch.equal(cam[torch.tensor([3, 0])].w2c, cam.w2c[[3, 0]])
    both = Cameras.cat([cam[0], cam[1:]])
    assert torch.equal(both.w2c, cam.w2c) and torch.equal(both.K, cam.K)
    assert cam.to("cpu").device == torch.device("cpu")
    with pytest.raises(IndexError):
        cam[4]
    with pytest.raises(ValueError, match="image size"):
        Cameras.cat([cam, cam.scaled(0.5)])
    d = json.loads(json.dumps(cam.to_dict()))
    back = Cameras.from_dict(d)
    assert torch.equal(back.K, cam.K) and torch.equal(back.w2c, cam.w2c)
    assert (back.width, back.height, back.near, back.far) == (cam.width, cam.height, cam.near, cam.far)
    # one K shared by a batch of extrinsics
    shared = Cameras(cam.K[0], cam.w2c, 64, 48)
    assert shared.K.shape == (4, 3, 3)


def test_scaled_maps_pixels_consistently():
    cam = _random_cameras(2)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (32, 24)
    pts = cam[0].unproject(torch.tensor([[[10.0, 7.0], [63.0, 47.0]]]), torch.tensor([[3.0, 4.0]]))[0]
    pix, _ = cam.project(pts)
    pix_half, _ = half.project(pts)
    assert torch.allclose(pix_half, pix * 0.5, atol=1e-4)
    with pytest.raises(ValueError, match="positive number"):
        cam.scaled(0.0)


def test_device(device):
    cam = _random_cameras(2).to(device)
    pts = torch.randn(5, 3, device=device)
    pix, depth = cam.project(pts)
    assert pix.device.type == torch.device(device).type
    assert torch.allclose(cam.unproject(pix, depth), pts.expand(2, -1, -1), atol=1e-3)


# ---------------------------------------------------------------- validation


def _w2c_with(R) -> torch.Tensor:
    m = torch.eye(4)
    m[:3, :3] = torch.as_tensor(R, dtype=torch.float32)
    m[2, 3] = 5.0
    return m


K0 = [[50.0, 0.0, 16.0], [0.0, 50.0, 16.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize(
    "w2c, match",
    [
        (_w2c_with([[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "camera index 0 is not orthonormal"),  # shear
        (_w2c_with(2.0 * torch.eye(3)), r"not orthonormal: max \|R R\^T - I\| = 3"),  # scaled
        (_w2c_with(torch.diag(torch.tensor([1.0, 1.0, -1.0]))), "det = -1"),  # reflection
        (torch.eye(3), r"w2c must have shape \(4, 4\) or \(B, 4, 4\), got \(3, 3\)"),
        (torch.full((4, 4), float("nan")), "w2c has NaN or inf values for camera index 0"),
        (torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 1, 1]]), "last row must be"),
    ],
)
def test_bad_extrinsics(w2c, match):
    with pytest.raises(ValueError, match=match):
        Cameras(K0, w2c, 32, 32)


def test_bad_camera_index_is_named():
    w2c = torch.eye(4).repeat(3, 1, 1)
    w2c[2, :3, :3] *= 1.01
    with pytest.raises(ValueError, match="camera index 2"):
        Cameras(K0, w2c, 32, 32)


def test_a_checked_camera_is_checked_again_after_any_change(monkeypatch):
    """Renderers validate on every call; unchanged cameras are checked once, and an in-place edit,
    new tensors or new planes are checked again."""
    cam = Cameras(K0, torch.eye(4).repeat(2, 1, 1), 32, 32)
    calls = []
    check = Cameras._check
    monkeypatch.setattr(Cameras, "_check", lambda self: (calls.append(1), check(self)))
    cam.validate()
    cam[1].validate()  # a slice holds new tensors: checked
    assert len(calls) == 1
    cam.validate()
    assert len(calls) == 1  # unchanged: not checked again
    cam.w2c[1, :3, :3] *= 2.0  # in place: the version counter moved
    with pytest.raises(ValueError, match="camera index 1 is not orthonormal"):
        cam.validate()
    cam.w2c = torch.eye(4).repeat(2, 1, 1)
    cam.validate()
    cam.K[0, 0, 0] = -1.0  # K of one camera was expanded to the batch: a write through the view is seen
    with pytest.raises(ValueError, match="must be positive"):
        cam.validate()
    cam.K = torch.tensor(K0).repeat(2, 1, 1)
    cam.near, cam.far = 5.0, 1.0
    with pytest.raises(ValueError, match="near must be < far"):
        cam.validate()


@pytest.mark.parametrize(
    "K, match",
    [
        ([[0.0, 0, 16], [0, 50, 16], [0, 0, 1]], r"fx \(K\[0, 0\]\) must be positive, got 0.0 for camera index 0"),
        ([[50.0, 0, 16], [0, -5, 16], [0, 0, 1]], r"fy \(K\[1, 1\]\) must be positive, got -5.0"),
        ([[50.0, 1, 16], [0, 50, 16], [0, 0, 1]], "no skew"),
        ([[50.0, 0, 16], [0, 50, 16]], r"K must have shape \(3, 3\) or \(B, 3, 3\)"),
        ([[50.0, 0, float("nan")], [0, 50, 16], [0, 0, 1]], "K has NaN or inf"),
    ],
)
def test_bad_intrinsics(K, match):
    with pytest.raises(ValueError, match=match):
        Cameras(K, torch.eye(4), 32, 32)


def test_bad_sizes_and_planes():
    with pytest.raises(ValueError, match="width must be a positive integer"):
        Cameras(K0, torch.eye(4), 0, 32)
    with pytest.raises(ValueError, match="height must be a positive integer"):
        Cameras(K0, torch.eye(4), 32, 31.5)
    with pytest.raises(ValueError, match="near must be < far"):
        Cameras(K0, torch.eye(4), 32, 32, near=2.0, far=1.0)
    with pytest.raises(ValueError, match="batch sizes must match"):
        Cameras(torch.tensor(K0).repeat(2, 1, 1), torch.eye(4).repeat(3, 1, 1), 32, 32)
    with pytest.raises(ValueError, match="empty batch"):
        Cameras(torch.zeros(0, 3, 3), torch.zeros(0, 4, 4), 32, 32)
    with pytest.raises(ValueError, match="c2w must have shape"):
        Cameras.from_opengl_c2w(torch.eye(3), fx=10.0, width=4, height=4)
    with pytest.raises(ValueError, match="not orthonormal"):
        Cameras.from_opengl_c2w(torch.diag(torch.tensor([1.0, 1.0, 1.5, 1.0])), fx=10.0, width=4, height=4)


def test_with_centre_moved_moves_one_centre_and_keeps_every_orientation():
    cams = Cameras.look_at(eye=[[1.0, 0.5, 0.0], [0.0, 0.5, 1.0]], target=(0.0, 0.0, 0.0), fov_y_deg=40, width=32, height=32)
    moved = cams.with_centre_moved(1, [0.02, -0.01, 0.03])
    torch.testing.assert_close(moved.centers[1] - cams.centers[1], torch.tensor([0.02, -0.01, 0.03], dtype=cams.centers.dtype),
                               atol=1e-6, rtol=0)
    torch.testing.assert_close(moved.centers[0], cams.centers[0])
    torch.testing.assert_close(moved.R, cams.R)
    torch.testing.assert_close(moved.K, cams.K)

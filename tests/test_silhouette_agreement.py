"""The silhouette check: cameras whose masks agree, and one whose claimed pose the masks contradict."""

import json
import math

import numpy as np
import pytest
import torch

from toolkit.cameras import Cameras
from toolkit.scene.silhouette_agreement import DISAGREE, check_scene, pair_uncovered, silhouette_agreement

RADIUS = 0.05
SIZE = 64
VOXELS = 300_000  # the hull's voxel grows from half a pixel (1.7 mm here) to about 2.4 mm


def ring_cameras(shift0=(0.0, 0.0, 0.0)) -> Cameras:
    """Three cameras 1 m from the origin, 120 degrees apart, 25 degrees up; camera 0's centre
    optionally moved by ``shift0`` (m) with its orientation kept."""
    eyes = []
    for k in range(3):
        a, e = 2 * math.pi * k / 3, math.radians(25)
        eyes.append([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])
    cams = Cameras.cat([Cameras.look_at(eye, (0, 0, 0), fov_y_deg=12.0, width=SIZE, height=SIZE) for eye in eyes])
    return cams.with_centre_moved(0, shift0) if any(shift0) else cams


def sphere_masks(cams: Cameras, centre=(0.0, 0.0, 0.0)) -> dict[int, list[torch.Tensor]]:
    """Exact masks of a sphere: a pixel is object when the ray through its centre passes within
    RADIUS of the sphere's centre (one frame per camera)."""
    j, i = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64) + 0.5, torch.arange(SIZE, dtype=torch.float64) + 0.5,
                          indexing="ij")
    pix = torch.stack([i.reshape(-1), j.reshape(-1)], -1)
    out = {}
    c = torch.tensor(centre, dtype=torch.float64)
    for k in range(len(cams)):
        far = cams[[k]].unproject(pix.to(cams.K.dtype), torch.ones(pix.shape[0], dtype=cams.K.dtype))[0].double()
        o = cams.centers[k].double()
        d = (far - o) / (far - o).norm(dim=1, keepdim=True)
        t = ((c - o) * d).sum(1)
        dist = ((o + t[:, None] * d) - c).norm(dim=1)
        out[k] = [(dist < RADIUS).reshape(SIZE, SIZE)]
    return out


def test_true_cameras_agree():
    cams = ring_cameras()
    check = silhouette_agreement(cams, sphere_masks(cams), [0, 1, 2], [0], max_voxels=VOXELS)
    assert max(check.pairs.values()) < 0.002  # a sphere's exact masks: only pixel quantization remains
    assert check.suspect is None and not check.disagree
    assert "agree" in check.message()


def test_a_moved_camera_is_named():
    """The masks are made by the true cameras; camera 0's pose is claimed 3 cm off (across its
    view): the pairs with it leave part of the masks uncovered, the pair without it does not."""
    true = ring_cameras()
    masks = sphere_masks(true)
    claimed = ring_cameras(shift0=(0.0, 0.03, 0.0))
    check = silhouette_agreement(claimed, masks, [0, 1, 2], [0], max_voxels=VOXELS)
    assert check.pairs[(0, 1)] > DISAGREE and check.pairs[(0, 2)] > DISAGREE
    assert check.pairs[(1, 2)] < 0.002
    assert check.suspect == 0 and check.disagree
    with_, without = check.per_camera[0]
    assert with_ > 3 * without
    assert "camera 0's silhouettes disagree" in check.message()
    d = check.to_dict()
    assert d["suspect"] == 0 and set(d["pairs"]) == {"0-1", "0-2", "1-2"}


def test_uncovered_share_grows_with_the_shift():
    true = ring_cameras()
    masks = {k: v[0] for k, v in sphere_masks(true).items()}
    lo, hi = np.full(3, -0.08), np.full(3, 0.08)
    shares = [pair_uncovered(ring_cameras(shift0=(0.0, s, 0.0)), masks, (0, 1), lo, hi, 0.0025)[0] for s in (0.0, 0.01, 0.02, 0.04)]
    assert shares[0] < 0.002
    assert all(b > a for a, b in zip(shares, shares[1:]))
    # beyond the sphere's diameter the cones no longer meet: nothing is covered
    assert pair_uncovered(ring_cameras(shift0=(0.0, 0.3, 0.0)), masks, (0, 1), lo, hi, 0.0025)[0] == pytest.approx(1.0)


def test_two_cameras_cannot_name_one():
    true = ring_cameras()
    masks = sphere_masks(true)
    check = silhouette_agreement(ring_cameras(shift0=(0.0, 0.03, 0.0)), masks, [0, 1], [0], max_voxels=VOXELS)
    assert check.disagree and check.suspect is None
    assert "no single camera" in check.message()


def test_bad_input_is_named():
    cams = ring_cameras()
    masks = sphere_masks(cams)
    with pytest.raises(ValueError, match="at least 2 cameras"):
        silhouette_agreement(cams, masks, [0], [0])
    empty = {k: [torch.zeros(SIZE, SIZE, dtype=torch.bool)] for k in masks}
    with pytest.raises(ValueError, match="no frame"):
        silhouette_agreement(cams, empty, [0, 1, 2], [0])


class _Scene:
    """The part of a scene that :func:`check_scene` reads."""

    def __init__(self, cams, masks):
        self.cameras, self._masks = cams, masks
        self.n_cameras = len(cams)

    def check_camera(self, cam):
        return int(cam)

    def load_mask(self, cam, frame):
        return self._masks[cam][frame].numpy().astype(np.float32)


def test_check_scene_writes_the_record_and_warns(tmp_path, caplog):
    masks = sphere_masks(ring_cameras())
    scene = _Scene(ring_cameras(shift0=(0.0, 0.03, 0.0)), masks)
    with caplog.at_level("WARNING"):
        check = check_scene(scene, [0, 1, 2], [0], tmp_path / "silhouettes.json", max_voxels=VOXELS)
    assert check.suspect == 0
    record = json.loads((tmp_path / "silhouettes.json").read_text())
    assert record["suspect"] == 0 and "camera 0" in record["message"]
    assert any("camera 0's silhouettes disagree" in r.message for r in caplog.records)


def test_check_scene_reads_at_most_max_frames_evenly_spaced(tmp_path):
    masks = sphere_masks(ring_cameras())
    long = {k: v * 40 for k, v in masks.items()}  # the same instant 40 times
    scene = _Scene(ring_cameras(), long)
    check = check_scene(scene, [0, 1, 2], range(40), max_frames=5, max_voxels=VOXELS)
    assert check.frames == [0, 10, 20, 29, 39] and check.suspect is None


def test_discovery_reads_the_physics_input_masks():
    """:func:`toolkit.discovery.camera.silhouette_check` on a physics input's claimed cameras and
    its (C, T, H, W) uint8 masks: it names the moved camera, or says nothing is wrong."""
    from types import SimpleNamespace

    from toolkit.discovery.camera import silhouette_check

    masks = sphere_masks(ring_cameras())
    stack = torch.stack([torch.stack(masks[k]) for k in range(3)]).to(torch.uint8) * 255  # (C, T, H, W)
    good = silhouette_check(SimpleNamespace(cameras=ring_cameras(), masks=stack, train_cameras=[0, 1, 2], n_train=1))
    assert good["suspect"] is None and "agree" in good["message"]
    moved = SimpleNamespace(cameras=ring_cameras(shift0=(0.0, 0.03, 0.0)), masks=stack, train_cameras=[0, 1, 2], n_train=1)
    bad = silhouette_check(moved)
    assert bad["suspect"] == 0 and bad["pairs"]["1-2"] < 0.002
    assert silhouette_check(SimpleNamespace(cameras=ring_cameras(), masks=None, train_cameras=[0, 1, 2], n_train=1)) is None


def test_shared_projections_give_the_pairwise_numbers():
    """silhouette_agreement projects each camera once per frame for all pairs; the slow, obvious
    pair_uncovered (one pair, its own projections) gives the same shares."""
    from toolkit.scene.silhouette_agreement import _all_pairs_uncovered

    masks = {k: v[0] for k, v in sphere_masks(ring_cameras()).items()}
    cams = ring_cameras(shift0=(0.0, 0.02, 0.01))
    lo, hi = np.full(3, -0.08), np.full(3, 0.08)
    foot = {c: 0.003 for c in range(3)}
    fast = _all_pairs_uncovered(cams, masks, [(0, 1), (0, 2), (1, 2)], lo, hi, 0.0025, foot)
    for pair, shares in fast.items():
        slow = pair_uncovered(cams, masks, pair, lo, hi, 0.0025, {c: 0.0025 / 0.003 for c in pair})
        assert shares == pytest.approx(slow, abs=1e-12)
    assert fast[(0, 1)][0] > 0.01 and fast[(1, 2)] == pytest.approx((0.0, 0.0), abs=0.002)


def test_the_camera_that_carves_most_is_ranked_first():
    """benchmarks/visual_hull.py --rank-cameras: with two ring cameras 120 degrees apart fitting a
    sphere, the third ring camera (another 120 degrees round) carves more of their hull than a camera
    10 degrees from one of them, and every added camera carves something; the hulls stay above the
    sphere's own volume."""
    from tests.bench_helpers import load_benchmark_script

    hull = load_benchmark_script("visual_hull")
    e = math.radians(25)
    near = [math.cos(e) * math.cos(math.radians(10)), math.sin(e), math.cos(e) * math.sin(math.radians(10))]
    cams = Cameras.cat([ring_cameras(), Cameras.look_at(near, (0, 0, 0), fov_y_deg=12.0, width=SIZE, height=SIZE)])
    scene = _Scene(cams, sphere_masks(cams))
    lo, hi = np.full(3, -2 * RADIUS), np.full(3, 2 * RADIUS)
    ranking = hull.rank_cameras(scene, [0, 1], [0], lambda f: (lo, hi), voxel=0.003)
    order = [r["camera"] for r in ranking]
    assert order == [2, 3, None]
    sphere_l = 4 / 3 * math.pi * RADIUS ** 3 * 1e3
    volumes = {r["camera"]: r["volume_L"] for r in ranking}
    assert sphere_l < volumes[2] < volumes[3] < volumes[None]
    assert volumes[None] - volumes[2] > 2 * (volumes[None] - volumes[3])  # 0.100 L against 0.033 L

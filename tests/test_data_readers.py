"""Dataset readers and the DataModule on tiny fixtures written in each public layout."""

from __future__ import annotations

import json
import struct
from itertools import product
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from toolkit.cameras import rotmat_to_rodrigues
from toolkit.data import (
    DatasetError,
    GroundTruth,
    detect_layout,
    load_scene,
    read_ground_truth,
    read_pac_nerf,
    read_ply_points,
    read_spring_gaus,
    read_spring_gaus_real,
    read_vid2sim_gso,
    write_ground_truth,
    write_ply_points,
)
from toolkit.data.datamodule import CameraFrameBatchSampler, MultiViewDataModule, MultiViewDataset
from toolkit.metrics import parameter_errors

W = H = 8
TARGET = np.array([0.0, 0.5, 0.0])
BG, FG = 51, 230  # background plate and object grey levels
SQUARE = (slice(2, 5), slice(3, 6))  # object pixels (rows, cols)


def eye_of(c: int, n: int) -> np.ndarray:
    a = 2 * np.pi * c / n
    return np.array([2.0 * np.cos(a), 1.0 + 0.1 * c, 2.0 * np.sin(a)])


def basis(eye: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, forward) unit vectors of a camera at ``eye`` looking at TARGET, world up +y."""
    f = TARGET - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    return r, np.cross(r, f), f


def opengl_c2w(eye: np.ndarray) -> np.ndarray:
    r, u, f = basis(eye)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u, -f, eye
    return m


def save_png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(arr).astype(np.uint8)).save(path)


def frame_rgb(shape=(H, W)) -> np.ndarray:
    img = np.full((*shape, 3), BG, np.uint8)
    img[SQUARE] = FG
    return img


def frame_rgba() -> np.ndarray:
    img = np.zeros((H, W, 4), np.uint8)
    img[..., :3] = 90
    img[SQUARE] = (FG, FG, FG, 255)
    return img


def check_cameras(scene, eyes: list[np.ndarray], fx: float) -> None:
    """Centres match; TARGET projects to the image centre; a point above it projects up by fx*d/z.

    Compared in the dataset's frame (the reader moved the cameras into the canonical world)."""
    cameras = scene.to_canonical.inverse().apply_cameras(scene.cameras)
    np.testing.assert_allclose(cameras.centers.numpy(), np.stack(eyes), atol=1e-5)
    for c, eye in enumerate(eyes):
        _, up, _ = basis(eye)
        pts = torch.tensor(np.stack([TARGET, TARGET + 0.1 * up]))
        pix, depth = cameras[c].project(pts)
        dist = np.linalg.norm(TARGET - eye)
        np.testing.assert_allclose(depth[0].numpy(), [dist, dist], rtol=1e-5)
        np.testing.assert_allclose(pix[0, 0].numpy(), [W / 2, H / 2], atol=1e-4)
        np.testing.assert_allclose(pix[0, 1].numpy(), [W / 2, H / 2 - fx * 0.1 / dist], atol=1e-4)


# ------------------------------------------------------------------------------ PAC-NeRF

N_PAC_CAMS, N_PAC_FRAMES, PAC_FX = 10, 3, 10.0


def write_pac_nerf(root: Path, *, gt: bool = True) -> list[np.ndarray]:
    K = [[PAC_FX, 0, W / 2], [0, PAC_FX, H / 2], [0, 0, 1]]
    entries, eyes = [], []
    for c in range(N_PAC_CAMS):
        eye = eye_of(c, N_PAC_CAMS)
        eyes.append(eye)
        c2w = opengl_c2w(eye)[:3].tolist()  # 3x4, as in PAC-NeRF
        for f in range(-1, N_PAC_FRAMES):
            entries.append({"file_path": f"./data/r_{c}_{f}.png", "time": f / 24.0, "c2w": c2w, "intrinsic": K})
            save_png(root / "data" / f"r_{c}_{f}.png", np.full((H, W, 3), BG) if f == -1 else frame_rgb())
    exclusion = np.zeros((H, W, 4), np.uint8)
    exclusion[0, :, 3] = 255
    save_png(root / "data" / "r_0_-2.png", exclusion)
    entries.append({"file_path": "./data/r_0_-2.png", "time": 0.0, "c2w": entries[0]["c2w"], "intrinsic": K})
    (root / "all_data.json").write_text(json.dumps(entries))
    if gt:
        clouds = [write_ply_points(root / "gt_points" / f"frame_{f:03d}.ply", np.full((4, 3), f)) for f in range(N_PAC_FRAMES)]
        write_ground_truth(root / "ground_truth.json", GroundTruth(
            material="neo_hookean", params={"E": 1e5, "nu": 0.3}, v0=[0.0, -1.0, 0.5],
            gravity=[0.0, -9.8, 0.0], effects={"ground_friction": {"mu": 0.3}},
            point_clouds=clouds, extra={"density": 1000, "simulation": {"dx": 0.01}},
        ))
    return eyes


def test_pac_nerf_reader(tmp_path):
    eyes = write_pac_nerf(tmp_path)
    scene = read_pac_nerf(tmp_path)
    assert (scene.n_cameras, scene.n_frames, scene.width, scene.height) == (10, 3, W, H)
    assert scene.layout == "pac_nerf" and scene.camera_names[3] == "3"
    check_cameras(scene, eyes, PAC_FX)
    np.testing.assert_allclose(scene.times, np.arange(3) / 24.0)
    assert scene.fps == pytest.approx(24.0)
    image = scene.load_image(4, 2)
    assert image.shape == (H, W, 3) and image.dtype == np.float32
    assert image[3, 4, 0] == pytest.approx(FG / 255) and image[0, 0, 0] == pytest.approx(BG / 255)
    assert scene.mask_source == "background"
    expected = np.zeros((H, W), np.float32)
    expected[SQUARE] = 1
    np.testing.assert_array_equal(scene.load_mask(4, 2), expected)
    np.testing.assert_allclose(scene.load_background(4), BG / 255)
    excl = scene.load_exclusion_mask(0)
    assert excl[0].all() and not excl[1:].any() and not scene.load_exclusion_mask(1).any()
    gt = scene.ground_truth
    assert gt.material == "neo_hookean" and gt.params == {"E": 1e5, "nu": 0.3}
    assert gt.v0 == [0.0, -1.0, 0.5] and gt.gravity == [0.0, -9.8, 0.0]
    assert gt.effects == {"ground_friction": {"mu": 0.3}}
    assert gt.extra == {"density": 1000, "simulation": {"dx": 0.01}}
    np.testing.assert_allclose(gt.load_point_cloud(2), np.full((4, 3), 2.0))
    assert parameter_errors({"E": 1e6, "nu": 0.3, "v0": [0, -1, 0.5]}, gt.all_params())["E"] == pytest.approx(1.0)
    assert detect_layout(tmp_path) == "pac_nerf" and load_scene(tmp_path).n_cameras == 10


def test_pac_nerf_alpha_files_and_public_ground_truth(tmp_path):
    root = tmp_path / "pacnerf" / "elastic" / "0"
    write_pac_nerf(root, gt=False)
    for c, f in product(range(N_PAC_CAMS), range(N_PAC_FRAMES)):
        save_png(root / "data" / f"a_{c}_{f}.png", frame_rgba())  # GIC's matting output
    (tmp_path / "pacnerf" / "elastic.json").write_text(json.dumps(
        {"0": {"E": 316228, "nu": 0.25, "v": [0.0, -1.0, 0.0], "rho": 1000}}
    ))
    sim = tmp_path / "simulation_data" / "elastic" / "0"
    for f in (1, 0, 10):
        write_ply_points(sim / f"{f:03d}.ply", np.zeros((2, 3)))
    scene = read_pac_nerf(root)
    assert scene.mask_source == "file"
    assert scene.load_mask(2, 1)[SQUARE].all() and scene.load_mask(2, 1).sum() == 9
    gt = scene.ground_truth
    assert gt.material == "neo_hookean" and gt.params == {"E": 316228.0, "nu": 0.25}
    assert gt.v0 == [0.0, -1.0, 0.0] and gt.extra == {"rho": 1000}
    assert [p.name for p in gt.point_clouds] == ["000.ply", "001.ply", "010.ply"]


def test_pac_nerf_errors(tmp_path):
    write_pac_nerf(tmp_path, gt=False)
    index = tmp_path / "all_data.json"
    entries = json.loads(index.read_text())

    (tmp_path / "data" / "r_3_1.png").unlink()
    with pytest.raises(DatasetError, match=r"r_3_1\.png"):
        read_pac_nerf(tmp_path)
    save_png(tmp_path / "data" / "r_3_1.png", frame_rgb())

    index.write_text(json.dumps([e for e in entries if not e["file_path"].endswith("r_2_1.png")]))
    with pytest.raises(DatasetError, match=r"all_data\.json.*camera 2 has no frame 1"):
        read_pac_nerf(tmp_path)

    bad = [dict(e) for e in entries]
    del bad[5]["c2w"]
    index.write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match=r"all_data\.json: entry 5.*'c2w'"):
        read_pac_nerf(tmp_path)
    lines = json.dumps(entries, indent=1).splitlines()
    lines[3] += " oops"
    index.write_text("\n".join(lines))
    with pytest.raises(DatasetError, match=r"malformed JSON in .*all_data\.json at line 4"):
        read_pac_nerf(tmp_path)
    index.write_text(json.dumps(entries))

    save_png(tmp_path / "data" / "r_4_2.png", frame_rgb((H, 10)))
    with pytest.raises(DatasetError, match=r"r_4_2\.png is 10x8 but .*r_0_0\.png is 8x8"):
        read_pac_nerf(tmp_path)
    scene = read_pac_nerf(tmp_path, verify_sizes=False)
    with pytest.raises(DatasetError, match=r"r_4_2\.png is 10x8"):
        scene.load_image(4, 2)
    with pytest.raises(DatasetError, match=r"camera index 42 does not exist.*0\.\.9"):
        scene.load_image(42, 0)
    with pytest.raises(DatasetError, match=r"frame index 3 does not exist.*0\.\.2"):
        scene.load_mask(0, 3)

    index.unlink()
    with pytest.raises(DatasetError, match=r"all_data\.json: expected the PAC-NeRF frame list"):
        read_pac_nerf(tmp_path)


# ------------------------------------------------------------------------------ ground truth


def test_ground_truth_round_trip_and_errors(tmp_path):
    pts = np.random.default_rng(0).normal(size=(5, 3))
    ply = write_ply_points(tmp_path / "gt_points" / "frame_000.ply", pts, double=True)
    np.testing.assert_array_equal(read_ply_points(ply), pts)
    (tmp_path / "ascii.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nelement face 0\nproperty list uchar int vertex_indices\n"
        "end_header\n0 1 2 255\n3 4 5 0\n"
    )
    np.testing.assert_array_equal(read_ply_points(tmp_path / "ascii.ply"), [[0, 1, 2], [3, 4, 5]])
    gt = GroundTruth(material="sand", params={"friction_angle": np.float64(35.0)}, v0=None,
                     gravity=[0, -9.8, 0], point_clouds=[ply], extra={"density": 1500})
    path = write_ground_truth(tmp_path / "ground_truth.json", gt)
    doc = json.loads(path.read_text())
    assert doc["format"] == "projo4d-ground-truth" and doc["version"] == 1
    assert doc["point_clouds"] == ["gt_points/frame_000.ply"] and doc["density"] == 1500
    back = read_ground_truth(path)
    assert back.params == {"friction_angle": 35.0} and back.v0 is None and back.point_clouds == [ply]
    doc["version"] = 2
    path.write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=r"ground_truth\.json: field 'version'"):
        read_ground_truth(path)
    doc["version"], doc["v0"] = 1, [1, 2]
    path.write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=r"ground_truth\.json: field 'v0' must have 3"):
        read_ground_truth(path)
    with pytest.raises(DatasetError, match=r"missing file .*nowhere\.json"):
        read_ground_truth(tmp_path / "nowhere.json")


# ------------------------------------------------------------------------------ Spring-Gaus synthetic

SG_FX = 12.0


def write_spring_gaus(base: Path, n_cams: int = 3, n_frames: int = 3) -> tuple[Path, list[np.ndarray]]:
    root = base / "render" / "apple"
    eyes = [eye_of(c, n_cams) for c in range(n_cams)]
    K = [[SG_FX, 0, W / 2], [0, SG_FX, H / 2], [0, 0, 1]]
    cams = [{"camera": f"camera_{c}", "K": K, "c2w": opengl_c2w(eyes[c]).tolist()} for c in range(n_cams)]
    root.mkdir(parents=True)
    (root / "camera.json").write_text(json.dumps(cams[::-1]))  # listed out of order on purpose
    (root / "frame.json").write_text(json.dumps([{"time": f * 0.03} for f in range(n_frames)]))
    (root / "physical.json").write_text(json.dumps([{"E": 2e5, "NU": 0.3}, {"INIT_VELOCITY": [0, -1, 0]}]))
    for c, f in product(range(n_cams), range(n_frames)):
        save_png(root / f"camera_{c}" / f"{f:03d}.png", frame_rgba())
    for f in range(n_frames):
        write_ply_points(base / "simulation" / "apple" / f"{f:03d}.ply", np.zeros((3, 3)))
    return root, eyes


def test_spring_gaus_reader(tmp_path):
    root, eyes = write_spring_gaus(tmp_path)
    scene = read_spring_gaus(root)
    assert scene.camera_names == ["camera_0", "camera_1", "camera_2"]
    check_cameras(scene, eyes, SG_FX)
    np.testing.assert_allclose(scene.times, np.arange(3) * 0.03)
    assert scene.load_mask(1, 2)[SQUARE].all() and scene.load_mask(1, 2).sum() == 9
    assert scene.load_image(1, 2)[0, 0, 0] == pytest.approx(90 / 255)
    gt = scene.ground_truth
    assert gt.params == {"E": 2e5, "nu": 0.3} and gt.v0 == [0.0, -1.0, 0.0]
    assert len(gt.point_clouds) == 3 and detect_layout(root) == "spring_gaus"

    (root / "camera_1" / "001.png").unlink()
    with pytest.raises(DatasetError, match=r"camera camera_1 has no frame 1.*camera_1/001\.png"):
        read_spring_gaus(root)
    save_png(root / "camera_1" / "001.png", frame_rgba())
    (root / "frame.json").write_text('[{"time": 0.0},\n {"time": }]')
    with pytest.raises(DatasetError, match=r"malformed JSON in .*frame\.json at line 2"):
        read_spring_gaus(root)
    (root / "frame.json").unlink()
    (root / "camera.json").write_text(json.dumps([{"camera": "camera_0", "K": [[1, 0], [0, 1]], "c2w": np.eye(4).tolist()}]))
    with pytest.raises(DatasetError, match=r"camera\.json: entry 0 \(camera_0\) field 'K' must be 3x3"):
        read_spring_gaus(root)


# ------------------------------------------------------------------------------ Spring-Gaus real

REAL_CAMS = ["C0733", "C0787", "C0801"]


def write_colmap_cameras(path: Path, fx: float, fy: float, width: int, height: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, width, height)  # PINHOLE
    path.write_bytes(data + struct.pack("<4d", fx, fy, width / 2, height / 2))


def write_real_capture(base: Path, n_frames: int = 3) -> list[np.ndarray]:
    dyn = base / "dynamic"
    eyes, calib = [], {}
    for c, name in enumerate(REAL_CAMS):
        eye = eye_of(c, 3)
        eyes.append(eye)
        r, u, f = basis(eye)
        R = np.stack([r, -u, f])  # OpenCV rows: right, down, forward
        calib[name] = {"rvecs": rotmat_to_rodrigues(R)[0].tolist(), "tvecs": (-R @ eye).tolist()}
        for t in range(n_frames):
            save_png(dyn / "videos_images" / name / f"{name}_{t:04d}.jpg", frame_rgb())
            mask = np.zeros((H, W), np.uint8)
            mask[SQUARE] = 255
            save_png(dyn / "videos_masks" / name / f"{name}_{t:04d}.png", mask)
    (dyn / "cameras_calib.json").write_text(json.dumps(calib))
    seq = {"hit_frame": 1, **{n: [f"{n}_{t:04d}.jpg" for t in range(n_frames)] for n in REAL_CAMS}}
    (dyn / "sequences" / "bun").mkdir(parents=True)
    (dyn / "sequences" / "bun" / "0.json").write_text(json.dumps(seq))
    write_colmap_cameras(base / "static" / "colmap" / "bun" / "cameras.bin", 40.0, 40.0, 2 * W, 2 * H)
    return eyes


def test_spring_gaus_real_reader(tmp_path):
    eyes = write_real_capture(tmp_path)
    for scene in (read_spring_gaus_real(tmp_path), load_scene(tmp_path / "bun")):
        assert scene.name == "bun" and scene.camera_names == REAL_CAMS and scene.layout == "spring_gaus_real"
        check_cameras(scene, eyes, 20.0)  # 40 px at twice the size
        np.testing.assert_allclose(scene.times, np.arange(3) / 120)
        assert scene.metadata["hit_frame"] == 1 and scene.ground_truth is None
        assert scene.load_mask(2, 1)[SQUARE].all() and scene.load_mask(2, 1).sum() == 9

    seq_path = tmp_path / "dynamic" / "sequences" / "bun" / "0.json"
    seq = json.loads(seq_path.read_text())
    seq["C0787"] = seq["C0787"][:2]
    seq_path.write_text(json.dumps(seq))
    with pytest.raises(DatasetError, match=r"0\.json: camera C0787 has no frame 2"):
        read_spring_gaus_real(tmp_path)
    seq["C0787"].append("C0787_0002.jpg")
    seq_path.write_text(json.dumps(seq))
    (tmp_path / "dynamic" / "videos_masks" / "C0801" / "C0801_0001.png").unlink()
    with pytest.raises(DatasetError, match=r"C0801_0001\.png: expected the mask of frame 1 of camera C0801"):
        read_spring_gaus_real(tmp_path)
    with pytest.raises(DatasetError, match=r"missing folder .*dynamic"):
        read_spring_gaus_real(tmp_path / "elsewhere" / "bun")


# ------------------------------------------------------------------------------ Vid2Sim GSO


def write_vid2sim(root: Path, n_cams: int = 3, n_frames: int = 3, angle: float = 0.9) -> list[np.ndarray]:
    eyes = [eye_of(c, n_cams) for c in range(n_cams)]
    frames = [{"file_path": f"./data/m_{c}_0", "time": 0.0, "rotation": 0.0,
               "transform_matrix": opengl_c2w(eyes[c]).tolist()} for c in range(n_cams)]
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    for c, f in product(range(n_cams), range(n_frames)):
        save_png(root / "data" / f"a_{c}_{f}.png", frame_rgba())
    (root / "gt_phys_params.yaml").write_text("yms: 123456.0\nprs: 0.3\n")
    write_ply_points(root / "simulation" / "000.ply", np.zeros((2, 3)))
    return eyes


def test_vid2sim_reader(tmp_path):
    eyes = write_vid2sim(tmp_path)
    scene = read_vid2sim_gso(tmp_path)
    check_cameras(scene, eyes, 0.5 * W / np.tan(0.45))
    np.testing.assert_allclose(scene.times, [0.0, 0.05, 0.1])
    assert scene.load_mask(0, 2)[SQUARE].all() and scene.load_mask(0, 2).sum() == 9
    gt = scene.ground_truth
    assert gt.material == "neo_hookean_simplicits" and gt.params == {"E": 123456.0, "nu": 0.3}
    assert gt.v0 == [0.0, 0.0, 0.0] and len(gt.point_clouds) == 1
    assert detect_layout(tmp_path) == "vid2sim_gso"

    (tmp_path / "data" / "a_1_2.png").unlink()
    with pytest.raises(DatasetError, match=r"camera 1 has no frame 2.*a_1_2\.png"):
        read_vid2sim_gso(tmp_path)
    save_png(tmp_path / "data" / "a_1_2.png", frame_rgba())
    (tmp_path / "gt_phys_params.yaml").write_text("yms: [1,\nprs: 0.3\n")
    with pytest.raises(DatasetError, match=r"malformed YAML in .*gt_phys_params\.yaml at line"):
        read_vid2sim_gso(tmp_path)
    with pytest.raises(DatasetError, match=r"transforms_train_nvs\.json"):
        read_vid2sim_gso(tmp_path, include_nvs=True)


def test_unknown_layout_lists_what_was_looked_for(tmp_path):
    with pytest.raises(DatasetError) as info:
        load_scene(tmp_path)
    for marker in ("all_data.json", "camera.json", "transforms_train.json", "cameras_calib.json"):
        assert marker in str(info.value)
    with pytest.raises(DatasetError, match="unknown layout 'bogus'.*pac_nerf"):
        load_scene(tmp_path, layout="bogus")


# ------------------------------------------------------------------------------ DataModule


def pairs_of(loader) -> list[tuple[int, int]]:
    out = []
    for batch in loader:
        out += list(zip(batch["cam_indices"].tolist(), batch["frame_indices"].tolist()))
    return out


def test_datamodule_splits_and_batches(tmp_path):
    write_pac_nerf(tmp_path, gt=False)
    dm = MultiViewDataModule(tmp_path, n_train=2)  # default: sparse views, 1-based 2, 6, 10
    assert dm.train_cameras == [1, 5, 9]
    assert dm.held_out_cameras == [0, 2, 3, 4, 6, 7, 8]
    assert (dm.train_frames, dm.future_frames) == ([0, 1], [2])
    batches = list(dm.train_dataloader())
    assert len(batches) == 2  # one frame x the three fitting cameras per batch
    b = batches[0]
    assert b["images"].shape == (3, H, W, 3) and b["masks"].shape == (3, H, W)
    assert len(set(b["frame_indices"].tolist())) == 1
    assert b["times"].dtype == torch.float32
    assert sorted(pairs_of(dm.train_dataloader())) == sorted(product([1, 5, 9], [0, 1]))
    assert sorted(pairs_of(dm.val_dataloader())) == sorted(product(dm.held_out_cameras, range(3)))
    assert sorted(pairs_of(dm.test_dataloader())) == sorted(product(range(10), range(3)))
    image = read_pac_nerf(tmp_path).load_image(5, 1)
    index = [i for i, p in enumerate(pairs_of([b for b in batches])) if p == (5, 1)]
    flat = torch.cat([bb["images"] for bb in batches])
    np.testing.assert_array_equal(flat[index[0]].numpy(), image)

    dm = MultiViewDataModule(tmp_path, cameras=[0, 1, 2, 3], n_train=3, frames_per_batch=2, cameras_per_batch=3, seed=1)
    sizes = sorted(len(b["cam_indices"]) for b in dm.train_dataloader())
    assert sizes == [1, 2, 3, 6]  # frames {2, 1} x cameras {3, 1}
    assert sorted(pairs_of(dm.train_dataloader())) == sorted(product(range(4), range(3)))
    assert sorted(pairs_of(dm.val_dataloader())) == sorted(product(range(4, 10), range(3)))


def test_datamodule_downscale_and_errors(tmp_path):
    write_pac_nerf(tmp_path, gt=False)
    scene = read_pac_nerf(tmp_path)
    dm = MultiViewDataModule(scene, cameras="all", downscale=2)
    assert (dm.cameras.width, dm.cameras.height) == (W // 2, H // 2)
    np.testing.assert_allclose(dm.cameras.K[:, 0, 0].numpy(), PAC_FX / 2)
    np.testing.assert_allclose(dm.cameras.K[:, :2, 2].numpy(), 2.0)
    batch = next(iter(dm.train_dataloader()))
    assert batch["images"].shape[1:] == (H // 2, W // 2, 3)
    cam, frame = batch["cam_indices"][0].item(), batch["frame_indices"][0].item()
    full = scene.load_image(cam, frame)
    np.testing.assert_allclose(batch["images"][0].numpy(), full.reshape(4, 2, 4, 2, 3).mean(axis=(1, 3)), atol=1e-6)

    with pytest.raises(DatasetError, match=r"camera index 42 does not exist.*0\.\.9"):
        MultiViewDataModule(scene, cameras=[1, 42])
    with pytest.raises(DatasetError, match=r"n_train must be in 1\.\.3"):
        MultiViewDataModule(scene, n_train=5)
    small = read_pac_nerf(tmp_path)
    small.cameras, small.image_paths = small.cameras[:3], small.image_paths[:3]
    small.background_paths = small.background_paths[:3]
    with pytest.raises(DatasetError, match=r"sparse-view protocol .* has 3 cameras"):
        MultiViewDataModule(small)

    ds = MultiViewDataset(scene, [0, 1], [0, 1, 2], cache_mb=3 * (H * W * 4 * 4) / 2**20)
    for i in range(len(ds)):
        ds[i]
    assert len(ds._cache) == 3  # LRU bound: three decoded views fit the budget


def test_batch_sampler_reshuffles_every_epoch():
    sampler = CameraFrameBatchSampler(3, 4, cameras_per_batch=2, frames_per_batch=3, shuffle=True, seed=0)
    first, second = list(sampler), list(sampler)
    assert len(first) == len(sampler) == 4
    for epoch in (first, second):
        assert sorted(i for batch in epoch for i in batch) == list(range(12))
    assert first != second
    sampler.set_epoch(0)
    assert list(sampler) == first


def test_camera_and_frame_reads_the_pac_nerf_file_name():
    """The reader's own file-name pattern: camera and frame of ``data/r_<camera>_<frame>[.png]``
    (negative frames are the background plates), ``None`` for any other name."""
    from toolkit.data.pac_nerf import camera_and_frame

    assert camera_and_frame("./data/r_3_12.png") == (3, 12)
    assert camera_and_frame("data/r_10_-1") == (10, -1)
    assert camera_and_frame("data/r_3_12.jpg") is None
    assert camera_and_frame("data/img_3_12.png") is None

"""The synthetic scene generator: shapes, filling, truth renderer, scene files, suite, CLI.

Sizes are tiny (32x32 images, 3 cameras, 3 frames, truth dx 0.04 m, ~4k particles) so the file
runs in well under a minute on 2 CPU cores once Warp's kernels are cached.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from materials import get_material
from toolkit.cameras import Cameras
from toolkit.data import load_scene, read_pac_nerf
from toolkit.mpm import SimConfig
from toolkit.synthetic import (
    SHAPES,
    ConstantTexture,
    FramingError,
    Lighting,
    MeshFileError,
    MeshRenderer,
    ProceduralTexture,
    SceneSpec,
    SpecError,
    build_shape,
    fill_mesh,
    generate_scene,
    generate_suite,
    load_mesh_file,
    sample_scene_spec,
    scene_is_complete,
    validate_spec,
)
from toolkit.synthetic.embedding import SurfaceEmbedding
from toolkit.synthetic.rig import check_in_view, orbit_cameras
from toolkit.synthetic.suite import FAMILY_RANGES
from toolkit.synthetic.truth import build_object, simulate_truth

TINY = dict(
    shape="sphere", shape_size={"radius": 0.1}, position=(0.0, 0.2, 0.0), v0=(0.5, 0.0, 0.2),
    params={"E": 2e4, "nu": 0.3}, width=32, height=32, n_cameras=3, n_frames=3, n_train_frames=2,
    dx=0.04, particle_spacing=0.01, substeps=100, mesh_edge=0.04, supersample=1,
)


def tiny_spec(**changes) -> SceneSpec:
    return SceneSpec.preset("small", **{**TINY, **changes})


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> tuple[SceneSpec, Path]:
    spec = tiny_spec(seed=3)
    return spec, generate_scene(spec, tmp_path_factory.mktemp("tiny") / "scene", progress=False)


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------ shapes and filling


@pytest.mark.parametrize("name", list(SHAPES))
def test_every_shape_is_watertight_with_the_requested_size(name):
    builder = SHAPES[name]
    sizes = {k: (v if k.endswith("_deg") else 0.7 * v) for k, v in builder.defaults.items()}
    mesh = build_shape(name, **sizes)
    assert mesh.is_watertight and mesh.volume > 0
    np.testing.assert_allclose(mesh.extents, builder.extents(**builder.complete(sizes)), rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)


def test_shape_sizes_are_what_was_asked():
    np.testing.assert_allclose(build_shape("sphere", radius=0.07).extents, [0.14] * 3, rtol=2e-3)
    np.testing.assert_allclose(build_shape("box", size_x=0.1, size_y=0.2, size_z=0.3).extents, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(build_shape("torus", major_radius=0.1, minor_radius=0.03).extents, [0.26, 0.06, 0.26], rtol=1e-3)
    np.testing.assert_allclose(build_shape("letter_l", height=0.3, width=0.2, stroke=0.05, thickness=0.04).volume,
                               (0.3 * 0.05 + 0.15 * 0.05) * 0.04)
    # the bend preserves volume: a banana holds what the straight capsule holds
    capsule = build_shape("capsule", radius=0.04, length=0.3)
    assert build_shape("banana", radius=0.04, length=0.3, bend_deg=120).volume == pytest.approx(capsule.volume, rel=0.01)


def test_mesh_files_are_validated(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.apply_translation([5, 5, 5])
    box.export(tmp_path / "box.obj")
    mesh = load_mesh_file(tmp_path / "box.obj", scale=0.1)
    np.testing.assert_allclose(mesh.extents, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(mesh.bounds.mean(0), 0.0, atol=1e-12)
    with pytest.raises(MeshFileError, match="nowhere.obj does not exist"):
        load_mesh_file(tmp_path / "nowhere.obj")
    (tmp_path / "junk.ply").write_text("ply\nthis is not a mesh\n")
    with pytest.raises(MeshFileError, match="junk.ply"):
        load_mesh_file(tmp_path / "junk.ply")
    holed = trimesh.creation.box()
    holed.update_faces(np.arange(len(holed.faces)) >= 2)  # one side missing: a small hole is filled
    holed.export(tmp_path / "holed.stl")
    assert load_mesh_file(tmp_path / "holed.stl").is_watertight
    open_box = trimesh.creation.box()
    open_box.update_faces(np.arange(len(open_box.faces)) >= 6)  # three sides missing: refused
    open_box.export(tmp_path / "open.stl")
    with pytest.raises(MeshFileError, match=r"open.stl: the mesh is not closed \(\d+ boundary edges"):
        load_mesh_file(tmp_path / "open.stl")


def test_filling_matches_the_mesh_volume():
    # Lattice counting: particles are the voxel centres inside the mesh, so count x spacing^3 is
    # an unbiased volume estimate; its error comes from the voxels the surface cuts (each in or
    # out), about sqrt(area / h^2) h^3 / volume = 0.85 % for a sphere of radius 10 spacings h.
    # We allow 3 % (3.5 sigma). Uncarved, voxelized().fill() overestimates by ~+20 % here.
    sphere = build_shape("sphere", radius=0.1)
    sphere.apply_translation([0.013, 0.4, -0.007])
    points, volume = fill_mesh(sphere, 0.01)
    assert volume == pytest.approx(0.01**3)
    assert len(points) * volume == pytest.approx(sphere.volume, rel=0.03)
    assert len(fill_mesh(sphere, 0.01, carve=False)[0]) * volume > 1.1 * sphere.volume
    # a box with faces on multiples of the spacing is filled exactly
    box = build_shape("box", size_x=0.2, size_y=0.12, size_z=0.16)
    points, volume = fill_mesh(box, 0.02)
    assert len(points) == 10 * 6 * 8
    assert len(fill_mesh(box, 0.02, carve=False)[0]) > len(points)
    again, _ = fill_mesh(box, 0.02)
    np.testing.assert_array_equal(points, again)


def test_ground_truth_cloud_at_frame_0_matches_the_mesh_volume(tiny_scene):
    spec, root = tiny_scene
    gt = read_pac_nerf(root).ground_truth
    sim = gt.extra["simulation"]
    cloud = gt.load_point_cloud(0)
    mesh = build_object(spec)
    assert len(cloud) == sim["n_particles"]
    assert sim["particle_volume"] == pytest.approx(spec.spacing**3)
    # sphere of radius 10 particle spacings: lattice counting error ~0.85 % (see above); allow 3 %
    assert len(cloud) * sim["particle_volume"] == pytest.approx(mesh.volume, rel=0.03)
    assert sim["mesh_volume"] == pytest.approx(mesh.volume)
    assert np.all(cloud[:, 1] > 0.0)


def test_rendered_surface_stays_on_the_simulated_body(tiny_scene):
    spec, root = tiny_scene
    gt = read_pac_nerf(root).ground_truth
    truth = simulate_truth(spec)
    gaps = []
    for t in range(spec.n_frames):
        np.testing.assert_allclose(truth.particles[t], gt.load_point_cloud(t), atol=1e-6)
        gaps.append(np.linalg.norm(truth.surface_vertices[t][:, None] - truth.particles[t][None], axis=2).min(axis=1).max())
    # at rest a vertex is within ~one lattice diagonal of a particle; it never drifts further away
    assert gaps[0] < spec.spacing * math.sqrt(3) and max(gaps) < gaps[0] + 0.25 * spec.spacing


def test_surface_embedding_follows_affine_motion_exactly():
    sphere = build_shape("sphere", radius=0.1)
    particles, _ = fill_mesh(sphere, 0.02)
    embed = SurfaceEmbedding(particles, sphere.vertices)
    np.testing.assert_allclose(embed.coefficients.sum(axis=1), 1.0, atol=1e-9)
    A = trimesh.transformations.rotation_matrix(0.7, (1, 2, 3))[:3, :3] @ np.diag([1.3, 0.8, 1.1])
    b = np.array([0.5, -0.2, 0.1])
    moved = embed(np.stack([particles, particles @ A.T + b]))
    np.testing.assert_allclose(moved[0], sphere.vertices, atol=1e-5)
    np.testing.assert_allclose(moved[1], sphere.vertices @ A.T + b, atol=1e-5)


def test_surface_carriers_agree_in_free_flight():
    # before any impact, the simulator's grid-velocity tracers and the particle embedding agree
    tracers = simulate_truth(tiny_spec(surface_motion="tracers"))
    embedded = SurfaceEmbedding(tracers.particles[0], tracers.surface_vertices[0])(tracers.particles)
    assert np.abs(tracers.surface_vertices - embedded).max() < 0.25 * TINY["dx"]


# ------------------------------------------------------------------------------ truth renderer


def sphere_view(device: str, size: int = 64, **renderer_kw):
    radius, dist = 0.2, 1.5
    sphere = build_shape("sphere", radius=radius)
    sphere.apply_translation([0.0, 0.5, 0.0])
    cam = Cameras.look_at(eye=[0.0, 0.5, dist], target=[0.0, 0.5, 0.0], fov_y_deg=40.0, width=size, height=size)
    renderer = MeshRenderer(sphere.faces, sphere.vertices, renderer_kw.pop("texture", ConstantTexture((0.8, 0.8, 0.8))),
                            device=device, **renderer_kw)
    f = float(cam.K[0, 0, 0])
    rho = f * radius / math.sqrt(dist**2 - radius**2)  # silhouette radius in pixels
    return sphere, cam, renderer, rho


def test_truth_renderer_draws_a_sphere_as_the_predicted_disc(device):
    _, cam, renderer, rho = sphere_view(device, supersample=2, ground=False)
    out = renderer.render(cam)
    assert out.rgb.shape == (64, 64, 3) and out.alpha.shape == (64, 64)
    assert out.alpha.sum() == pytest.approx(math.pi * rho**2, rel=0.02)
    jj, ii = np.mgrid[0:64, 0:64] + 0.5
    r = np.hypot(ii - 32, jj - 32)
    assert np.all(out.alpha[r < rho - 1.5] == 1.0)
    assert np.all(out.alpha[r > rho + 1.5] == 0.0)
    assert np.all((out.alpha >= 0) & (out.alpha <= 1))
    np.testing.assert_allclose(out.composite()[r > rho + 1.5], 0.0)  # black sky, no ground


def test_truth_renderer_shading_follows_the_normal(device):
    _, cam, renderer, rho = sphere_view(device, supersample=1, ground=False, lighting=Lighting((0.0, 1.0, 0.0), ambient=0.2))
    out = renderer.render(cam)
    c = 32
    top, centre, bottom = out.rgb[int(c - 0.8 * rho), c, 0], out.rgb[c, c, 0], out.rgb[int(c + 0.8 * rho), c, 0]
    assert top > centre + 0.2 and centre > bottom - 1e-6
    assert bottom == pytest.approx(0.8 * 0.2, abs=0.01)  # facing away from the light: ambient only
    assert top < 0.8 + 1e-6


def test_truth_renderer_texture_sticks_to_the_material(device):
    sphere, cam, renderer, _ = sphere_view(device, texture=ProceduralTexture.from_seed(0, 0.4, (0, 0.5, 0)), ground=True)
    before = renderer.render(cam)
    shift = np.array([0.1, 0.0, 0.0])
    renderer.set_vertices(sphere.vertices + shift)  # move the body, not its material coordinates
    moved_cam = Cameras(cam.K, cam.w2c @ torch.tensor(np.linalg.inv(trimesh.transformations.translation_matrix(shift)),
                                                      dtype=torch.float32), cam.width, cam.height)
    after = renderer.render(moved_cam)
    np.testing.assert_allclose(after.alpha, before.alpha, atol=1e-6)
    inside = before.alpha == 1.0
    np.testing.assert_allclose(after.rgb[inside], before.rgb[inside], atol=2e-3)
    plate = renderer.render_background(cam)
    np.testing.assert_allclose(plate, before.background, atol=1e-6)
    assert plate[-1].std() > 0.01  # the checkered ground shows in the lower rows


# ------------------------------------------------------------------------------ scenes


def test_scene_reads_back_through_the_pac_nerf_reader(tiny_scene):
    spec, root = tiny_scene
    scene = read_pac_nerf(root)
    assert load_scene(root).n_cameras == spec.n_cameras
    assert (scene.n_cameras, scene.n_frames, scene.width, scene.height) == (3, 3, 32, 32)
    entries = json.loads((root / "all_data.json").read_text())
    written = {}
    for e in entries:
        assert np.asarray(e["c2w"]).shape == (4, 4) and np.asarray(e["intrinsic"]).shape == (3, 3)
        written[int(Path(e["file_path"]).stem.split("_")[1])] = np.asarray(e["c2w"])
    np.testing.assert_allclose(scene.cameras.c2w_opengl().numpy(), np.stack([written[c] for c in range(3)]), atol=1e-5)
    np.testing.assert_allclose(scene.times, np.arange(3) / 24.0)
    assert scene.mask_source == "alpha" and scene.background_paths is not None
    mask = scene.load_mask(0, 0)
    assert mask.max() == 1.0 and mask.min() == 0.0
    # every frame is in view: the object's mask never touches the border
    for c in range(3):
        for t in range(3):
            m = scene.load_mask(c, t)
            assert m.sum() > 4 and not (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())
    gt = scene.ground_truth
    assert gt.material == "neo_hookean"
    assert gt.params == get_material("neo_hookean").complete(spec.params)
    assert gt.v0 == list(spec.v0) and gt.gravity == list(spec.gravity) and gt.effects == {}
    assert len(gt.point_clouds) == 3 and gt.extra["density"] == 1000.0
    clouds = [gt.load_point_cloud(t) for t in range(3)]
    assert clouds[2][:, 0].mean() > clouds[0][:, 0].mean() + 0.02  # thrown toward +x
    assert gt.extra["generator"]["spec"]["seed"] == 3 and gt.extra["cameras"]["n_cameras"] == 3
    assert scene_is_complete(root, spec) and not scene_is_complete(root, spec.replace(seed=4))


def test_truth_is_finer_than_the_fitting_defaults(tiny_scene):
    fit = SimConfig()
    default = SceneSpec()
    assert default.dx < fit.dx and default.spacing < fit.dx / 2 and default.substeps > fit.substeps
    assert SceneSpec.preset("full").dx == default.dx
    # no fit refined by halving (0.02 -> 0.01 -> 0.005 m) lands on the truth's own lattice
    ratio = math.log2(fit.dx / default.dx)
    assert abs(ratio - round(ratio)) > 0.1, f"truth dx {default.dx} is a power-of-two refinement of the fit's {fit.dx}"
    spec, root = tiny_scene
    sim = read_pac_nerf(root).ground_truth.extra["simulation"]
    assert sim["fit_defaults"] == {"dx": fit.dx, "substeps": fit.substeps}
    assert sim["dx"] == spec.dx and sim["substeps"] >= spec.substeps and sim["particle_spacing"] == spec.spacing
    assert sim["finer_than_fit_defaults"] == {"dx": spec.dx < fit.dx, "substeps": sim["substeps"] > fit.substeps}
    assert sim["config"]["substeps"] == sim["substeps"]


def test_generation_is_deterministic_from_its_seed(tiny_scene, tmp_path):
    spec, root = tiny_scene
    same = files_of(generate_scene(spec, tmp_path / "same", progress=False))
    assert same == files_of(root)
    other = files_of(generate_scene(spec.replace(seed=4), tmp_path / "other", progress=False))
    assert other.keys() == same.keys()
    assert other["ground_truth.json"] != same["ground_truth.json"]
    assert other["data/r_0_0.png"] != same["data/r_0_0.png"]
    assert other["gt_points/frame_002.ply"] == same["gt_points/frame_002.ply"]  # the seed only draws the texture


def test_bad_specs_raise_clear_errors():
    with pytest.raises(SpecError, match=r"unknown shape 'tours'.*did you mean 'torus'"):
        validate_spec(tiny_spec(shape="tours"))
    with pytest.raises(SpecError, match=r"shape 'sphere' has no size parameter\(s\) \['radious'\]"):
        validate_spec(tiny_spec(shape_size={"radious": 0.1}))
    with pytest.raises(SpecError, match=r"unknown material 'jelly'.*neo_hookean"):
        validate_spec(tiny_spec(material="jelly"))
    with pytest.raises(SpecError, match=r"nu = 0.7 is out of range"):
        validate_spec(tiny_spec(params={"nu": 0.7}))
    with pytest.raises(SpecError, match=r"no parameter\(s\) \['youngs'\]"):
        validate_spec(tiny_spec(params={"youngs": 1e5}))
    with pytest.raises(SpecError, match=r"unknown effect 'drag'.*air_drag"):
        validate_spec(tiny_spec(effects={"drag": {"linear": 1.0}}))
    with pytest.raises(SpecError, match=r"air_drag.linear = -1 is out of range"):
        validate_spec(tiny_spec(effects={"air_drag": {"linear": -1.0}}))
    with pytest.raises(SpecError, match=r"n_train_frames \(5\) must not exceed n_frames \(3\)"):
        validate_spec(tiny_spec(n_train_frames=5))
    with pytest.raises(SpecError, match=r"v0 must be 3"):
        validate_spec(tiny_spec(v0=(1.0, 0.0)))
    with pytest.raises(SpecError, match=r"below the ground.*raise position\[1\] to at least 0.14"):
        build_object(tiny_spec(position=(0.0, 0.05, 0.0)))


def test_trajectories_that_leave_the_frame_are_refused(tmp_path):
    with pytest.raises(FramingError, match=r"leaves the image of camera 0 at frame 0.*increase camera_distance"):
        generate_scene(tiny_spec(fov_y_deg=20.0, camera_distance=0.3), tmp_path / "cramped", progress=False)
    assert not (tmp_path / "cramped").exists()
    cams, distance, fov = orbit_cameras((0, 0.3, 0), 0.2, 4, width=32, height=32, fov_y_deg=40.0)
    assert distance > 0.2 and fov == 40.0
    inside = np.zeros((2, 1, 3)) + [0, 0.3, 0]
    check_in_view(cams, inside)
    away = inside.copy()
    away[1, 0, 0] = 3.0
    with pytest.raises(FramingError, match=r"leaves the image of camera \d at frame 1"):
        check_in_view(cams, away)
    with pytest.raises(SpecError, match="inside the trajectory's bounding sphere"):
        orbit_cameras((0, 0.3, 0), 0.5, 4, width=32, height=32, fov_y_deg=None, distance=0.3)
    with pytest.raises(SpecError, match="below the ground"):
        orbit_cameras((0, 0.3, 0), 0.2, 4, width=32, height=32, elevations_deg=(-60.0,))


# ------------------------------------------------------------------------------ suite and CLI


def test_suite_draws_are_deterministic_and_in_range():
    for family, ranges in FAMILY_RANGES.items():
        spec = sample_scene_spec(family, 1, seed=7)
        assert spec == sample_scene_spec(family, 1, seed=7) and spec != sample_scene_spec(family, 2, seed=7)
        validate_spec(spec)
        build_object(spec)  # above the ground
        for name, (scale, lo, hi) in ranges.items():
            x = math.log10(spec.params[name]) if scale == "log10" else spec.params[name]
            assert lo - 1e-4 <= x <= hi + 1e-4


def test_spring_gaus_shape_set_takes_the_seven_objects_in_turn_with_the_same_draws():
    from toolkit.synthetic.suite import SPRING_GAUS_SHAPES

    specs = [sample_scene_spec("neo_hookean", i, seed=3, size="full", shape_set="spring_gaus") for i in range(8)]
    assert [s.shape for s in specs] == ["apple", "banana", "chess", "cream", "cross", "paste", "torus", "apple"]
    assert tuple(s.shape for s in specs[:7]) == SPRING_GAUS_SHAPES
    for i, spec in enumerate(specs):
        validate_spec(spec)
        build_object(spec)  # above the ground, whatever the shape
        default = sample_scene_spec("neo_hookean", i, seed=3, size="full")
        # only the shape (and what it implies: sizes, release height) differs from the default set
        assert (spec.params, spec.v0, spec.rotation_deg, spec.seed) == (default.params, default.v0, default.rotation_deg, default.seed)
        lowest = spec.position[1] - build_shape(spec.shape, **spec.shape_size).apply_transform(
            trimesh.transformations.euler_matrix(*np.radians(spec.rotation_deg), axes="sxyz")).extents[1] / 2
        assert 0.12 - 1e-3 <= lowest <= 0.35 + 1e-3  # released as high above the ground as any suite scene
    with pytest.raises(SpecError, match="unknown shape set 'spring'; choose from pac_nerf, spring_gaus"):
        sample_scene_spec("neo_hookean", 0, shape_set="spring")


def test_a_generated_benchmark_suite_keeps_its_shape_set(tmp_path, monkeypatch):
    """scenes_to_generate draws the shape set's shapes, and the suite index written after the
    generate jobs is asked for the same set (else it would generate other shapes again)."""
    from toolkit.benchmark import runner
    from toolkit.benchmark.scenes import scenes_to_generate

    scenes = scenes_to_generate(tmp_path, ["neo_hookean"], 3, seed=0, size="small", shape_set="spring_gaus")
    assert [sc.generate["spec"]["shape"] for sc in scenes] == ["apple", "banana", "chess"]
    calls = []
    monkeypatch.setattr("toolkit.synthetic.suite.generate_suite", lambda *a, **k: calls.append(k))
    runner._write_suite_index(type("Spec", (), {"scenes": scenes[1:]})())  # --only: two of the three
    assert [c["shape_set"] for c in calls] == ["spring_gaus"]
    assert calls[0]["only"] == {"neo_hookean/001", "neo_hookean/002"}


def test_a_suite_index_generates_only_the_selected_scenes(tmp_path, monkeypatch):
    """``only``: the scenes a benchmark's --only left out are indexed as missing (a benchmark on the
    suite skips them), never generated; the selected one is generated and complete."""
    from toolkit.benchmark.scenes import scenes_from_suite

    tiny = {k: v for k, v in TINY.items() if k not in ("shape", "shape_size", "position", "v0", "params")}
    from toolkit.synthetic import suite as suite_module

    generated, real = [], suite_module.generate_scene

    def recording(spec, path, **kwargs):
        generated.append(Path(path).name)
        return real(spec, path, **kwargs)

    monkeypatch.setattr(suite_module, "generate_scene", recording)
    index = generate_suite(tmp_path, ["neo_hookean"], 3, seed=5, size="small", spec_overrides=tiny, progress=False,
                           only={"neo_hookean/001"})
    assert generated == ["001"]
    assert [(s["name"], s["complete"]) for s in index["scenes"]] == [
        ("neo_hookean/000", False), ("neo_hookean/001", True), ("neo_hookean/002", False)]
    assert [s.name for s in scenes_from_suite(tmp_path)] == ["neo_hookean/001"]


def test_suite_writes_an_index_and_skips_complete_scenes(tmp_path, monkeypatch):
    tiny = {k: v for k, v in TINY.items() if k not in ("shape", "shape_size", "position", "v0", "params")}
    index = generate_suite(tmp_path, ["neo_hookean"], 1, seed=5, size="small", spec_overrides=tiny, progress=False)
    assert [s["name"] for s in index["scenes"]] == ["neo_hookean/000"] and index["scenes"][0]["complete"]
    written = json.loads((tmp_path / "suite.json").read_text())
    assert written["ranges"]["neo_hookean"]["E"] == {"scale": "log10", "low": 4.5, "high": 6.0}
    assert read_pac_nerf(tmp_path / "neo_hookean" / "000").ground_truth.params["E"] == index["scenes"][0]["params"]["E"]

    def boom(*args, **kwargs):
        raise AssertionError("a complete scene was generated again")

    monkeypatch.setattr("toolkit.synthetic.suite.generate_scene", boom)
    again = generate_suite(tmp_path, ["neo_hookean"], 1, seed=5, size="small", spec_overrides=tiny, progress=False)
    assert again["scenes"] == index["scenes"]
    with pytest.raises(SpecError, match=r"unknown material family \['gel'\]"):
        generate_suite(tmp_path, ["gel"], 1)


def test_cli_builds_the_spec_and_reports_bad_values(capsys, tmp_path):
    import argparse

    from toolkit.cli import main
    from toolkit.synthetic.commands import configure, spec_from_args

    parser = argparse.ArgumentParser()
    configure(parser)
    args = parser.parse_args([
        "scene", "--shape", "torus", "--material", "plasticine", "--param", "E=1e5", "--param", "yield_stress=3e3",
        "--v0", "1,0,0", "--effect", "air_drag.linear=0.5", "--effect-option", "wall.normal=1,0,0",
        "--effect", "wall.strength=1", "--out", str(tmp_path), "--size", "full", "--seed", "9", "--frames", "10",
    ])
    spec = spec_from_args(args)
    assert spec == SceneSpec.preset(
        "full", shape="torus", material="plasticine", params={"E": 1e5, "yield_stress": 3e3}, v0=(1.0, 0.0, 0.0),
        effects={"air_drag": {"linear": 0.5}, "wall": {"strength": 1.0}}, effect_options={"wall": {"normal": (1.0, 0.0, 0.0)}},
        seed=9, n_frames=10, n_train_frames=7,
    )
    validate_spec(spec)
    bad = [
        (["--material", "jelly"], "invalid choice: 'jelly'"),
        (["--shape", "donut"], "invalid choice: 'donut'"),
        (["--param", "E"], "expected NAME=VALUE"),
        (["--v0", "1,0"], "expected 3 comma-separated numbers"),
        (["--effect", "drag.linear=1"], "unknown effect 'drag'"),
        (["--param", "nu=0.9"], "nu = 0.9 is out of range"),
        (["--param", "E=1e5", "--shape-size", "major_radius=0.01"], "minor_radius .* must be smaller than major_radius"),
    ]
    for extra, message in bad:
        with pytest.raises(SystemExit) as exc:
            main(["generate", "scene", "--out", str(tmp_path / "x"), *extra])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert __import__("re").search(message, err), (extra, err)
    with pytest.raises(SystemExit):
        main(["generate", "suite", "--out", str(tmp_path), "--families", "gel"])
    assert "invalid choice: 'gel'" in capsys.readouterr().err


def test_relative_output_folder_gives_valid_ground_truth_paths(tmp_path, monkeypatch):
    """ground_truth.json must point at the PLY files whatever the working directory was."""
    from toolkit.data import load_scene
    from toolkit.synthetic import SceneSpec, generate_scene

    monkeypatch.chdir(tmp_path)
    spec = SceneSpec.preset("small", shape="sphere", shape_size={"radius": 0.05}, n_frames=2, n_train_frames=1, n_cameras=3,
                           width=16, height=16, dx=0.04, substeps=20, supersample=1)
    generate_scene(spec, "scenes/relative", progress=False)
    scene = load_scene(tmp_path / "scenes" / "relative")
    assert all(p.is_file() for p in scene.ground_truth.point_clouds)
    assert len(scene.ground_truth.load_point_cloud(1)) > 0


def test_stiffness_gradient_makes_one_side_stiffer(tmp_path):
    """SceneSpec.stiffness_gradient: per-particle moduli 10^(g.(x-c)/h); the softer side squashes more."""
    import numpy as np

    from materials import get_material
    from toolkit.synthetic.truth import particle_params

    m = get_material("neo_hookean")
    x = np.array([[-0.1, 0, 0], [0.0, 0, 0], [0.1, 0, 0]], np.float32)
    p = particle_params(m, {"E": 1e5, "nu": 0.3}, x, (1.0, 0.0, 0.0))
    np.testing.assert_allclose(p[:, 0].numpy(), [1e4, 1e5, 1e6], rtol=1e-5)  # one decade per half-extent
    np.testing.assert_allclose(p[:, 1].numpy(), 0.3)
    assert particle_params(m, {"E": 1e5, "nu": 0.3}, x, None).shape == (2,)

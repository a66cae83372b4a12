"""Simulated scenes, their ground-truth renderer, and the simulation backend's roles."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import open3d as o3d
import pytest

from navcrafter.models.camera.cameras import (
    Intrinsics,
    axis_angle_to_matrix,
    invert_pose,
    look_at,
    make_pose,
    rotation_angle_deg,
    unproject_depth,
)
from navcrafter.models.simulation.backend import SimulationError, SimulationTruth, simulation_backend
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.scenes import (
    KINDS,
    MIN_CAMERA_CLEARANCE,
    Light,
    SceneObject,
    SimScene,
    generate_scene,
)
from navcrafter.models.simulation.textures import Material
from navcrafter.schemas.config import SimulationConfig


def box_wall_scene(distance: float) -> SimScene:
    """A single large box whose face z = distance faces a camera at the origin looking along +z."""
    wall = o3d.geometry.TriangleMesh.create_box(20.0, 20.0, 1.0)
    wall.translate((-10.0, -10.0, distance))
    wall.compute_triangle_normals()
    return SimScene("test", 0, [SceneObject("wall", wall, 0)], [Material("checker", (1, 1, 1), (0, 0, 0), 0.5)],
                    Light("sun", (0.0, 0.0, -1.0)), True, np.eye(4), 60.0)


def test_depth_of_known_wall_is_exact():
    scene = box_wall_scene(3.25)
    K = Intrinsics.from_fov(70, 48, 32)
    r = render(scene, np.eye(4), K)
    assert r.hit.all()
    np.testing.assert_allclose(r.depth, 3.25, rtol=1e-6)  # z-depth, not distance along the ray
    np.testing.assert_allclose(r.normal, np.broadcast_to([0, 0, -1], r.normal.shape), atol=1e-6)
    # a camera 1 m back and rotated 30 degrees about the wall normal still sees z-depth 4.25
    rot = make_pose(look_at(np.zeros(3), np.array([0, 0, 1.0]), up=np.array([0.5, -1, 0]))[:3, :3],
                    np.array([0.3, -0.2, -1.0]))
    r2 = render(scene, rot, K)
    np.testing.assert_allclose(r2.depth, 4.25, rtol=1e-6)
    # the black-and-white checker texture is visible
    grey = r.rgb.mean(-1)
    assert (grey < 60).mean() > 0.2 and (grey > 200).mean() > 0.2


def test_sky_and_miss_pixels():
    scene = box_wall_scene(2.0)
    K = Intrinsics.from_fov(60, 32, 32)
    r = render(scene, look_at(np.zeros(3), np.array([0.0, 0.0, -1.0]), up=np.array([0.0, -1.0, 0.0])), K)
    assert not r.hit.any() and (r.depth == 0).all()
    assert r.rgb.mean() > 100  # sky colour, not black


def test_texture_noise_is_the_numpy_lattice_noise_bit_for_bit():
    """The numba noise (``textures.fbm``) computes what the numpy form it replaced computed, to the bit: the demo's
    frames (and every cache key downstream of them) stay as they were."""
    from navcrafter.models.simulation.textures import _hash2, fbm, value_noise

    def noise(x, y, seed):
        ix, iy = np.floor(x), np.floor(y)
        fx, fy = x - ix, y - iy
        sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
        a, b = _hash2(ix, iy, seed), _hash2(ix + 1, iy, seed)
        c, d = _hash2(ix, iy + 1, seed), _hash2(ix + 1, iy + 1, seed)
        return (a * (1 - sx) + b * sx) * (1 - sy) + (c * (1 - sx) + d * sx) * sy

    rng = np.random.default_rng(0)
    for spread in (1.0, 40.0, 1e4):
        x, y = rng.normal(0, spread, (2, 50, 40))
        for seed in (0, 11, (1 << 30) + 400):
            np.testing.assert_array_equal(value_noise(x, y, seed), noise(x, y, seed))
            for octaves in (4, 5):
                total, amp, norm, freq = np.zeros_like(x), 1.0, 0.0, 1.0
                for o in range(octaves):
                    total += amp * noise(x * freq, y * freq, seed + 97 * o)
                    norm, amp, freq = norm + amp, amp * 0.5, freq * 2.03
                np.testing.assert_array_equal(fbm(x, y, seed, octaves), total / norm)


@pytest.mark.parametrize("supersample", [1, 2])
def test_batched_render_equals_frame_by_frame(supersample):
    """``render_many`` (one cast for many frames, or only some pixels) gives each pixel exactly what ``render`` of
    its frame gives: the synthesizer batches a clip's renders on it and its clips must not change."""
    from navcrafter.models.simulation.render import render_many

    scene = generate_scene("room", 1)
    K = Intrinsics.from_fov(70, 40, 24)
    poses = np.stack([scene.camera_c2w @ make_pose(axis_angle_to_matrix([0, 1.0, 0], a), np.array([0.1 * a, 0, 0]))
                      for a in (0.0, 0.3, -0.4)])
    one = [render(scene, c, K, supersample=supersample) for c in poses]
    many = render_many(scene, poses, K, supersample=supersample, max_rays=2 * 40 * 24 * supersample**2)
    for name in ("rgb", "depth", "normal", "hit"):
        np.testing.assert_array_equal(getattr(many, name), np.stack([getattr(r, name) for r in one]))
    pixels = np.random.default_rng(0).random((3, 24, 40)) < 0.3
    part = render_many(scene, poses, K, supersample=supersample, pixels=pixels)
    for name in ("rgb", "depth", "normal", "hit"):
        got, want = getattr(part, name), getattr(many, name)
        np.testing.assert_array_equal(got[pixels], want[pixels])
        assert not got[~pixels].any()  # the rest are left empty
    assert part.hit[pixels].mean() > 0.5


@pytest.mark.parametrize("kind", KINDS)
def test_scenes_are_deterministic_and_photo_like(kind):
    a, b = generate_scene(kind, 3), generate_scene(kind, 3)
    va = np.asarray(a.merged_mesh().vertices)
    np.testing.assert_array_equal(va, np.asarray(b.merged_mesh().vertices))
    np.testing.assert_array_equal(a.camera_c2w, b.camera_c2w)
    assert len(a.objects) >= 10
    assert a.distance(a.camera_c2w[None, :3, 3])[0] >= MIN_CAMERA_CLEARANCE
    r = render(a, a.camera_c2w, Intrinsics.from_fov(a.camera_fov_x_deg, 96, 72))
    assert r.hit.mean() > 0.5
    assert r.rgb.std() > 20  # textured, lit, not flat
    c = generate_scene(kind, 4)
    assert not np.array_equal(np.asarray(c.merged_mesh().vertices)[:50], va[:50]) or \
        not np.array_equal(c.camera_c2w, a.camera_c2w)


def _truth(kind="room", seed=0, scale=None) -> SimulationTruth:
    scene = generate_scene(kind, seed)
    K = Intrinsics.from_fov(scene.camera_fov_x_deg, 64, 48)
    record = {"scene": scene.spec, "photo_c2w": scene.camera_c2w.tolist(), "work_intrinsics": K.to_dict()}
    return SimulationTruth.from_record(record, world_scale=scale)


def test_truth_maps_world_and_ground_truth_frames():
    truth = _truth(scale=1.7)
    np.testing.assert_allclose(truth.gt_pose(np.eye(4)), truth.photo_c2w, atol=1e-12)
    pts = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_allclose(truth.world_points(truth.gt_points(pts)), pts, atol=1e-9)
    # a world translation of 1.7 units is 1 metre in the ground-truth frame
    T = np.eye(4)
    T[:3, 3] = [1.7, 0, 0]
    assert np.linalg.norm(truth.gt_pose(T)[:3, 3] - truth.photo_c2w[:3, 3]) == pytest.approx(1.0)
    with pytest.raises(SimulationError, match="world scale"):
        _truth().gt_pose(T)


def test_geometry_first_call_defines_world_and_later_calls_are_relative():
    cfg = SimulationConfig(preset="perfect", scale_sigma=0.3, depth_noise=0.0, pose_rot_deg=0.0, pose_trans=0.0)
    truth = _truth()
    backend = simulation_backend(truth, cfg)
    img = np.zeros((1, 48, 64, 3), np.uint8)
    first = backend.geometry.predict(img, seed=1, hint_c2w=np.eye(4)[None])
    s0 = first.extras["simulation_scale"]
    np.testing.assert_allclose(first.c2w[0], np.eye(4))
    true_depth = render(truth.scene, truth.photo_c2w, truth.work_intrinsics, colour=False).depth
    np.testing.assert_allclose(first.depth[0], true_depth * s0, rtol=1e-5)
    with pytest.raises(SimulationError):  # world not defined yet: only the input view can be served
        backend.geometry.predict(np.zeros((2, 48, 64, 3), np.uint8), seed=1, hint_c2w=np.stack([np.eye(4)] * 2))
    truth.world_scale = s0
    T = np.eye(4)
    T[:3, 3] = [0.5 * s0, 0.0, 0.0]  # half a metre to the right, in world units
    pred = backend.geometry.predict(np.zeros((2, 48, 64, 3), np.uint8), seed=2, hint_c2w=np.stack([np.eye(4), T]))
    s1 = pred.extras["simulation_scale"]
    assert s1 != s0  # every call has its own arbitrary scale, like VGGT
    np.testing.assert_allclose(pred.c2w[0], np.eye(4))
    np.testing.assert_allclose(pred.c2w[1][:3, 3], [0.5 * s1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(pred.depth[0], true_depth * s1, rtol=1e-5)


def test_geometry_noise_and_confidence():
    truth = _truth(scale=1.0)
    backend = simulation_backend(truth, SimulationConfig(preset="perfect", scale_sigma=0.0, depth_noise=0.01))
    pred = backend.geometry.predict(np.zeros((1, 48, 64, 3), np.uint8), seed=3, hint_c2w=np.eye(4)[None])
    true_depth = render(truth.scene, truth.photo_c2w, truth.work_intrinsics, colour=False).depth
    rel = pred.depth[0] / true_depth - 1
    assert 0.005 < rel.std() < 0.02
    assert (pred.confidence[0] < 1).any() and (pred.confidence[0] == 1).mean() > 0.7  # edges are less trusted
    again = backend.geometry.predict(np.zeros((1, 48, 64, 3), np.uint8), seed=3, hint_c2w=np.eye(4)[None])
    np.testing.assert_array_equal(again.depth, pred.depth)  # seeded


def test_mono_depth_is_affine_in_inverse_depth():
    truth = _truth("street", 0, scale=1.0)
    backend = simulation_backend(truth, SimulationConfig(preset="perfect", depth_noise=0.0))
    pred = backend.mono_depth.predict(np.zeros((48, 64, 3), np.uint8), seed=5, hint_c2w=np.eye(4)[None])
    r = render(truth.scene, truth.photo_c2w, truth.work_intrinsics, colour=False)
    assert (pred.sky == ~r.hit).all() and pred.sky.any()
    inv = 1 / r.depth[r.hit]
    A = np.stack([inv, np.ones_like(inv)], 1)
    coef, res, *_ = np.linalg.lstsq(A, pred.inv_depth[r.hit], rcond=None)
    np.testing.assert_allclose(A @ coef, pred.inv_depth[r.hit], rtol=1e-4, atol=1e-6)
    assert coef[0] > 0


def test_perfect_synthesizer_renders_the_requested_poses():
    truth = _truth(scale=2.0)
    backend = simulation_backend(truth, SimulationConfig(preset="perfect"))
    T = np.eye(4)
    T[:3, 3] = [0.2, 0.0, 0.4]
    from navcrafter.models.roles import SynthesisRequest

    frames = backend.synthesizer.synthesize(SynthesisRequest(
        np.zeros((48, 64, 3), np.uint8), np.stack([np.eye(4), T]), truth.work_intrinsics,
        np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), 0))
    assert frames.shape == (2, 48, 64, 3)
    np.testing.assert_array_equal(frames[0], render(truth.scene, truth.photo_c2w, truth.work_intrinsics).rgb)
    np.testing.assert_array_equal(frames[1], render(truth.scene, truth.gt_pose(T), truth.work_intrinsics).rgb)


def test_synthesizer_checks_the_request_and_ignores_its_images():
    from navcrafter.models.roles import SynthesisRequest

    truth = _truth(scale=2.0)
    synth = simulation_backend(truth, SimulationConfig(preset="perfect")).synthesizer
    T = np.eye(4)
    T[:3, 3] = [0.2, 0.0, 0.4]
    image = np.zeros((48, 64, 3), np.uint8)
    req = SynthesisRequest(image, np.stack([T, np.eye(4)]), truth.work_intrinsics, np.zeros((0, 3), np.float32),
                           np.zeros((0, 3), np.uint8), 0)
    plain = synth.synthesize(req)
    # a clip that starts elsewhere, with the input photo as reference: the same truth, whatever the pixels say
    photo = render(truth.scene, truth.photo_c2w, truth.work_intrinsics).rgb
    ref = SynthesisRequest(**{**vars(req), "image": np.full_like(image, 255), "reference_image": photo,
                              "reference_c2w": np.eye(4)})
    np.testing.assert_array_equal(synth.synthesize(ref), plain)
    for bad, match in (({"reference_c2w": None}, "come together"), ({"reference_image": photo[:, :32]}, "like"),
                       ({"reference_c2w": np.eye(3)}, r"\[4, 4\]"), ({"image": image[..., :2]}, "uint8"),
                       ({"trajectory": np.eye(4)}, "trajectory")):
        with pytest.raises(ValueError, match=match):
            synth.synthesize(SynthesisRequest(**{**vars(ref), **bad}))


def _request(truth, trajectory, cloud=None, image=None, seed=0):
    from navcrafter.models.roles import SynthesisRequest

    K = truth.work_intrinsics
    image = render(truth.scene, truth.gt_pose(trajectory[0]), K).rgb if image is None else image
    pts = np.zeros((0, 3), np.float32) if cloud is None else cloud.astype(np.float32)
    return SynthesisRequest(image, trajectory, K, pts, np.zeros((len(pts), 3), np.uint8), seed)


def _true_cloud(truth, poses_world):
    """World points of the true surfaces seen from ``poses_world``: a cloud that anchors those views."""
    K = truth.work_intrinsics
    parts = []
    for c2w in poses_world:
        r = render(truth.scene, truth.gt_pose(c2w), K, colour=False)
        pts, _ = unproject_depth(r.depth.astype(np.float64), truth.gt_pose(c2w), K.K, mask=r.hit)
        parts.append(truth.world_points(pts))
    return np.concatenate(parts)


def _walk(num: int, step: float, world_scale: float) -> np.ndarray:
    traj = np.tile(np.eye(4), (num, 1, 1))
    traj[:, 0, 3] = np.linspace(0.0, step * world_scale, num)  # sideways, metres x world units
    return traj


def test_honest_synthesizer_starts_from_the_conditioning_image_and_drifts():
    from navcrafter.models.simulation.backend import ClipStart

    truth = _truth(scale=2.0)
    synth = simulation_backend(truth, SimulationConfig(drift_rot_deg=3.0, drift_trans=0.1)).synthesizer
    traj = _walk(9, 0.4, 2.0)
    image = np.full((48, 64, 3), 77, np.uint8)
    clip = synth.simulate(_request(truth, traj, _true_cloud(truth, traj), image=image, seed=4))
    np.testing.assert_array_equal(clip.frames[0], image)  # frame 0 is the conditioning image, as Wan I2V
    np.testing.assert_array_equal(clip.true_c2w[0], traj[0])
    rot = [rotation_angle_deg(r[:3, :3], t[:3, :3]) for r, t in zip(traj, clip.true_c2w)]
    moved = np.linalg.norm(clip.true_c2w[:, :3, 3] - traj[:, :3, 3], axis=1)
    assert rot[0] == 0 and moved[0] == 0
    assert np.all(np.diff(rot) > 0) and np.all(np.diff(moved) > 0)  # the drift grows over the clip
    assert rot[-1] < 15 and moved[-1] < 0.5 * 0.4 * 2.0  # of the size of the configured means (half-normal)
    # the frames are where the camera really went (anchored content is the truth there)
    for i in (4, 8):
        truth_i = render(truth.scene, truth.gt_pose(clip.true_c2w[i]), truth.work_intrinsics)
        same = np.abs(clip.frames[i].astype(int) - truth_i.rgb.astype(int)).max(-1) <= 1
        assert same.mean() >= clip.true_quality[i] - 1e-6 and clip.true_quality[i] > 0.6  # soft anchoring
    # a clip that starts where its conditioning image really was continues from there, not from the request
    start = ClipStart(clip.true_c2w[-1], clip.true_depth[-1], float(clip.true_quality[-1]))
    nxt = synth.simulate(_request(truth, _walk(5, 0.2, 2.0) @ np.eye(4), seed=5), start)
    np.testing.assert_array_equal(nxt.true_c2w[0], clip.true_c2w[-1])
    np.testing.assert_array_equal(nxt.true_depth[0], clip.true_depth[-1])
    perfect = simulation_backend(truth, SimulationConfig(preset="perfect")).synthesizer
    np.testing.assert_array_equal(perfect.simulate(_request(truth, traj)).true_c2w, traj)


def test_honest_synthesizer_hallucinates_what_the_cloud_does_not_show():
    truth = _truth(scale=1.0)
    cfg = SimulationConfig(drift_rot_deg=0.0, drift_trans=0.0)
    synth = simulation_backend(truth, cfg).synthesizer
    traj = _walk(3, 0.3, 1.0)
    seen = synth.simulate(_request(truth, traj, _true_cloud(truth, traj), seed=1))
    unseen = synth.simulate(_request(truth, traj, None, seed=1))
    other = synth.simulate(_request(truth, traj, None, seed=2))
    assert seen.true_quality[1:].min() > 0.9 and unseen.true_quality[1:].max() < 0.1
    true2 = render(truth.scene, truth.gt_pose(traj[2]), truth.work_intrinsics).rgb.astype(int)
    err = [np.abs(c.frames[2].astype(int) - true2).mean() for c in (seen, unseen)]
    assert err[0] < 0.5 and err[1] > 3  # invented content is not the truth ...
    assert np.abs(unseen.frames[2].astype(int) - other.frames[2].astype(int)).mean() > 3  # ... nor twice the same
    assert (unseen.true_depth[2] > 0).mean() > 0.9  # ... but it has geometry, which the geometry model will lift


def test_honest_synthesizer_corrupts_frames_near_or_inside_surfaces():
    truth = _truth(scale=1.0)
    synth = simulation_backend(truth, SimulationConfig(drift_rot_deg=0.0, drift_trans=0.0)).synthesizer
    wall = np.eye(4)
    wall[:3, 3] = truth.world_points(np.array([[truth.photo_c2w[0, 3], -0.05, 1.3]]))[0]  # inside the south wall
    traj = np.stack([np.eye(4), np.eye(4), wall])
    clip = synth.simulate(_request(truth, traj, _true_cloud(truth, traj[:1]), seed=3))
    assert clip.true_quality[1] > 0.9 and clip.true_quality[2] == 0.0


def test_honest_geometry_estimates_from_the_frames_truth():
    truth = _truth(scale=1.0)
    cfg = SimulationConfig(scale_sigma=0.0, depth_noise=0.0, depth_lowfreq=0.0, pose_rot_deg=0.0, pose_trans=0.0,
                           pose_trans_rel=0.0, depth_clip_bias=0.0, depth_clip_shape=0.0)
    geo = simulation_backend(truth, cfg).geometry
    T = np.eye(4)
    T[:3, 3] = [0.3, 0.0, 0.0]
    shown = np.full((48, 64), 2.5, np.float32)  # what the frame shows (e.g. hallucinated), not the true scene
    pred = geo.predict(np.zeros((2, 48, 64, 3), np.uint8), seed=1, hint_c2w=np.stack([np.eye(4), T]),
                       hint_depth=[None, shown])
    np.testing.assert_allclose(pred.depth[1], shown, rtol=1e-6)
    np.testing.assert_allclose(pred.c2w[1][:3, 3], [0.3, 0, 0], atol=1e-9)
    noisy = simulation_backend(truth, SimulationConfig(scale_sigma=0.0)).geometry.predict(
        np.zeros((2, 48, 64, 3), np.uint8), seed=1, hint_c2w=np.stack([np.eye(4), T]), hint_depth=[None, shown])
    rel = noisy.depth[1] / shown - 1
    assert 0.005 < np.abs(rel).mean() < 0.15  # the smooth per-view error of feed-forward depth


def test_demo_collection_writes_photos_and_ground_truth(demo_photos):
    pngs = sorted(demo_photos.glob("*.png"))
    assert [p.stem for p in pngs] == ["room-0", "street-0", "tabletop-0"]
    for p in pngs:
        record = json.loads((demo_photos / ".groundtruth" / p.stem / "scene.json").read_text())
        assert record["photo"]["sha256"] == hashlib.sha256(p.read_bytes()).hexdigest()
        assert "SIMULATION" in record["note"]
        mesh = o3d.io.read_triangle_mesh(str(demo_photos / ".groundtruth" / p.stem / "mesh.ply"))
        assert len(mesh.triangles) > 100
        scene = generate_scene(record["scene"]["kind"], record["scene"]["seed"])
        np.testing.assert_allclose(np.asarray(record["photo"]["c2w"]), scene.camera_c2w)
        assert np.allclose(invert_pose(scene.camera_c2w) @ scene.camera_c2w, np.eye(4))


# --------------------------------------------------------------------------------------------------
# Fidelity of the honest preset (issue 30)
# --------------------------------------------------------------------------------------------------
def test_variants_move_the_structure_too():
    from navcrafter.models.simulation.backend import variant_scene

    cfg = SimulationConfig()
    base = generate_scene("room", 0)

    def walls(scene):
        return {o.name: np.asarray(o.mesh.get_min_bound()) for o in scene.objects if o.name.startswith("wall_")}

    lo, hi = np.asarray(base.objects[0].mesh.get_min_bound()), np.asarray(base.objects[0].mesh.get_max_bound())
    extent = (hi - lo)[:2]
    for v in range(4):
        var = variant_scene("room", 0, v, cfg)
        b, w = walls(base), walls(var)
        dx = (w["wall_east"][0] - w["wall_west"][0]) - (b["wall_east"][0] - b["wall_west"][0])
        dy = (w["wall_north"][1] - w["wall_south"][1]) - (b["wall_north"][1] - b["wall_south"][1])
        # each extent changes by 10-20 %, floors stay put
        assert 0.09 < abs(dx) / extent[0] < 0.21 and 0.09 < abs(dy) / extent[1] < 0.21
        assert np.array_equal(next(o for o in var.objects if o.name == "floor").mesh.get_min_bound(),
                              base.objects[0].mesh.get_min_bound())
    # openings: some variants have a wall split around a door (more wall pieces than the base)
    counts = [sum(o.name.startswith("wall_") for o in variant_scene("room", 0, v, cfg).objects) for v in range(8)]
    assert min(counts) == 4 and max(counts) == 6
    street = generate_scene("street", 0)
    var = variant_scene("street", 0, 1, cfg)
    moved = [abs(np.asarray(a.mesh.get_min_bound()) - np.asarray(b.mesh.get_min_bound())).max()
             for a, b in zip(street.objects, var.objects) if a.name.startswith("building")]
    assert all(0.29 < m < 1.01 for m in moved)  # facades 0.3-1 m off
    # the dispatch hook: another kind of world brings its own builder
    from navcrafter.models.simulation import backend as sim

    calls = []
    sim.register_variant_builder("test-world", lambda scene, rng, c: calls.append(scene) or scene)
    try:
        world = box_wall_scene(2.0)
        world.kind = "test-world"
        assert sim.variant_of(world, 3, cfg) is world and calls == [world]
    finally:
        sim.VARIANT_BUILDERS.pop("test-world")


def test_soft_anchoring_falls_off_with_distance_from_the_cloud():
    from scipy.spatial import cKDTree

    from navcrafter.models.simulation.backend import anchored

    scene = box_wall_scene(3.0)
    K = Intrinsics.from_fov(70, 64, 48)
    r = render(scene, np.eye(4), K, colour=False)
    pts, _ = unproject_depth(r.depth.astype(np.float64), np.eye(4), K.K, mask=r.hit)
    cfg = SimulationConfig()
    rng = np.random.default_rng(0)
    shares = []
    for off in (0.0, 0.05, 0.15, 0.4):
        tree = cKDTree(pts + np.array([0, 0, off]))
        shares.append(np.mean([anchored(tree, r.depth, r.hit, np.eye(4), K, cfg, rng).mean() for _ in range(20)]))
    assert shares[0] > 0.97 and shares[-1] < 0.01
    assert shares[0] > shares[1] > shares[2] > shares[3]
    assert 0.35 < shares[1] < 0.85  # exp(-0.05 / 0.072) = 0.5 on average
    hard = cfg.model_copy(update={"anchor_falloff_m": 0.0})
    assert anchored(cKDTree(pts + [0, 0, 0.04]), r.depth, r.hit, np.eye(4), K, hard, rng).all()
    assert not anchored(cKDTree(pts + [0, 0, 0.06]), r.depth, r.hit, np.eye(4), K, hard, rng).any()
    # a clip's frames in one query: what each frame gets alone, with the clip's field
    from navcrafter.models.simulation.backend import AnchorField

    field, tree = AnchorField.draw(rng), cKDTree(pts + [0, 0, 0.05])
    c2w = np.stack([np.eye(4), make_pose(np.eye(3), np.array([0.2, 0.1, 0.5]))])
    rs = [render(scene, c, K, colour=False) for c in c2w]
    both = anchored(tree, np.stack([x.depth for x in rs]), np.stack([x.hit for x in rs]), c2w, K, cfg, rng, field)
    for i, x in enumerate(rs):
        np.testing.assert_array_equal(both[i], anchored(tree, x.depth, x.hit, c2w[i], K, cfg, rng, field))
    assert 0.1 < both.mean() < 0.9


def test_closeup_corruption_follows_how_much_of_the_frame_a_near_surface_fills():
    from navcrafter.models.simulation.backend import closeup_severity

    cfg = SimulationConfig()
    hit = np.ones((10, 10), bool)
    depth = np.full((10, 10), 3.0)
    assert closeup_severity(depth, hit, 0.1, cfg) == 0.0  # near a surface, but it fills nothing: clean
    depth[:5] = 0.3  # half the frame within 0.5 m
    assert closeup_severity(depth, hit, 1.0, cfg) == pytest.approx(0.5)
    depth[:] = 0.3
    assert closeup_severity(depth, hit, 1.0, cfg) == 1.0
    legacy = cfg.model_copy(update={"corrupt_near_m": 0.0})
    assert closeup_severity(depth, hit, 0.125, legacy) == pytest.approx(0.5)


def test_geometry_depth_error_is_shared_by_the_frames_of_a_clip():
    truth = _truth(scale=1.0)
    cfg = SimulationConfig(scale_sigma=0.0, depth_noise=0.0, depth_lowfreq=0.0, pose_rot_deg=0.0, pose_trans=0.0,
                           pose_trans_rel=0.0, depth_clip_shape=0.0)
    geo = simulation_backend(truth, cfg).geometry
    T = np.eye(4)
    T[:3, 3] = [0.05, 0.0, 0.0]  # nearly the same view: the same surfaces
    frames = np.zeros((2, 48, 64, 3), np.uint8)
    a = geo.predict(frames, seed=1, hint_c2w=np.stack([np.eye(4), np.eye(4)]))
    K = truth.work_intrinsics
    true = render(truth.scene, truth.gt_pose(np.eye(4)[None])[0], K, colour=False)
    rel = a.depth / np.maximum(true.depth, 1e-9) - 1
    assert 0.005 < np.abs(rel[0][true.hit]).mean() < 0.15
    np.testing.assert_allclose(rel[0][true.hit], rel[1][true.hit], atol=1e-6)  # same surface, same error
    b = geo.predict(frames, seed=2, hint_c2w=np.stack([np.eye(4), np.eye(4)]))  # another clip: another error
    assert np.abs(b.depth[0] - a.depth[0]).mean() > 1e-3


def test_refiner_repairs_towards_the_truth_only_where_the_scene_was_observed():
    truth = _truth(scale=1.0)
    cfg = SimulationConfig(refine_strength=1.0, refine_noise=0.0)
    refiner = simulation_backend(truth, cfg).refiner
    K = truth.work_intrinsics
    pose = np.eye(4)
    gt = render(truth.scene, truth.gt_pose(pose[None])[0], K, supersample=2).rgb.astype(int)
    blank = np.zeros_like(gt, dtype=np.uint8)
    refiner.observe(_true_cloud(truth, [pose]))
    seen = refiner.refine(blank, None, seed=0, hint_c2w=pose, hint_intrinsics=K)
    assert np.abs(seen.astype(int) - gt).mean() < 2
    refiner.observe(np.zeros((0, 3)))  # nothing observed: a variant, not the truth
    unseen = refiner.refine(blank, None, seed=0, hint_c2w=pose, hint_intrinsics=K)
    assert np.abs(unseen.astype(int) - gt).mean() > 3
    perfect = simulation_backend(truth, SimulationConfig(preset="perfect", refine_strength=1.0, refine_noise=0.0))
    perfect.refiner.observe(np.zeros((0, 3)))
    out = perfect.refiner.refine(blank, None, seed=0, hint_c2w=pose, hint_intrinsics=K)
    assert np.abs(out.astype(int) - gt).mean() < 2  # the perfect preset stays exact


def _shade_numpy(scene, origins, dirs, shadows, ans):
    """``render._shade`` as it was in numpy (before its per-ray arithmetic moved into numba loops)."""
    from navcrafter.models.simulation.render import SKY_HORIZON, SKY_ZENITH, _cast
    from navcrafter.models.simulation.textures import albedo

    t = ans["t_hit"]
    hit = np.isfinite(t)
    colour = np.empty((len(t), 3))
    if scene.sky:
        dn = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        elev = np.clip(dn[:, 2], 0.0, 1.0)[:, None] ** 0.6
        colour[:] = SKY_HORIZON * (1 - elev) + SKY_ZENITH * elev
    else:
        colour[:] = 0.0
    _, mat_of_geom = scene.raycasting()
    idx = np.flatnonzero(hit)
    p = origins[idx] + dirs[idx] * t[idx, None]
    n = ans["primitive_normals"][idx].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    n *= np.where((n * dirs[idx]).sum(1, keepdims=True) > 0, -1.0, 1.0)
    mats = mat_of_geom[ans["geometry_ids"][idx].astype(np.int64)]
    alb = np.empty((len(idx), 3))
    for m in np.unique(mats):
        sel = mats == m
        alb[sel] = albedo(scene.materials[m], p[sel], n[sel])
    light = scene.light
    if light.kind == "sun":
        to_l = np.broadcast_to(np.asarray(light.vector, dtype=np.float64), p.shape)
        dist = np.full(len(p), np.inf)
        atten = np.ones(len(p))
    else:
        to_l = np.asarray(light.vector, dtype=np.float64) - p
        dist = np.linalg.norm(to_l, axis=1)
        to_l = to_l / dist[:, None]
        atten = 1.0 / (1.0 + 0.04 * dist**2)
    lam = np.clip((n * to_l).sum(1), 0.0, None) * atten
    if shadows:
        sh = _cast(scene, p + n * 2e-3, to_l)["t_hit"]
        lam = np.where(sh < dist - 1e-2, 0.0, lam)
    colour[idx] = alb * (light.ambient + light.strength * lam)[:, None]
    return colour


def _mix_numpy(a, b, mix, grain):
    col = a[None] * (1 - mix[:, None]) + b[None] * mix[:, None]
    col *= (0.88 + 0.24 * grain)[:, None]
    return np.clip(col, 0.0, 1.0)


@pytest.mark.parametrize("kind", ["room", "street", "tabletop"])
def test_shading_loops_are_the_numpy_form_bit_for_bit(kind):
    """The numba loops of the renderer's shading (hit points and normals, Lambert and shadow rays, lighting, the
    facing normals and depth of a cast, the albedo mix) compute what the numpy form they replaced computed, to the
    bit, on a point-lit room and table-top and a sun-lit street with sky: the demo's frames (and every cache key
    downstream of them) stay as they were."""
    from navcrafter.models.camera.cameras import world_rays
    from navcrafter.models.simulation.render import _cast, _facing_normals, _shade
    from navcrafter.models.simulation.textures import _mix

    scene = generate_scene(kind, 2)
    K = Intrinsics.from_fov(scene.camera_fov_x_deg, 48, 32)
    rng = np.random.default_rng(1)
    poses = [scene.camera_c2w @ make_pose(axis_angle_to_matrix(rng.normal(size=3), 0.6 * rng.random()),
                                          rng.normal(0, 0.2, 3)) for _ in range(3)]
    rays = [world_rays(c, K.K, K.height, K.width) for c in poses]
    o = np.stack([np.broadcast_to(r[0], r[1].shape) for r in rays]).reshape(-1, 3).astype(np.float64)
    d = np.stack([r[1] for r in rays]).reshape(-1, 3)
    ans = _cast(scene, o, d)
    assert 0.2 < np.isfinite(ans["t_hit"]).mean() and (kind != "street" or not np.isfinite(ans["t_hit"]).all())
    for shadows in (True, False):
        np.testing.assert_array_equal(_shade(scene, o, d, shadows, ans), _shade_numpy(scene, o, d, shadows, ans))
    t = ans["t_hit"]
    h = np.isfinite(t)
    n = ans["primitive_normals"].astype(np.float32)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n *= np.where((n * d).sum(-1, keepdims=True) > 0, -1.0, 1.0).astype(np.float32)
    n[~h] = 0.0
    got_n, got_z = _facing_normals(ans["primitive_normals"], d, t)
    np.testing.assert_array_equal(got_n, n)
    np.testing.assert_array_equal(got_z, np.where(h, t, 0.0).astype(np.float32))
    a, b = rng.random(3), rng.random(3)
    mix, grain = rng.normal(0.5, 1.0, 5000), rng.normal(0.5, 1.5, 5000)  # out of [0, 1] too: the clip
    np.testing.assert_array_equal(_mix(a, b, mix, grain), _mix_numpy(a, b, mix, grain))


def test_deciding_distances_give_the_decisions_of_one_full_query():
    """Soft anchoring queries each point only out to the distance where its field value stops anchoring it
    (``backend._deciding_distances``): the decisions are those of one query out to the full bound, point for point,
    on points at every distance from a cloud (on it, near, beyond the bound) and field values from 0 to 1."""
    from scipy.spatial import cKDTree

    from navcrafter.models.simulation.backend import _deciding_distances

    rng = np.random.default_rng(3)
    cloud = rng.uniform(-1, 1, (4000, 3))
    pts = np.concatenate([cloud[:3000] + rng.normal(0, s, (3000, 3)) for s in (0.002, 0.02, 0.08, 0.3)])
    u = np.concatenate([rng.random(len(pts) - 3), [0.0, 1.0, 1e-300]])
    tree = cKDTree(cloud)
    falloff, bound = 0.072, 0.72
    full, _ = tree.query(pts, k=1, distance_upper_bound=bound)
    got = _deciding_distances(tree, pts, u, falloff, bound)
    decide = [np.isfinite(d) & (u < np.exp(-np.where(np.isfinite(d), d, bound) / falloff)) for d in (full, got)]
    np.testing.assert_array_equal(decide[1], decide[0])
    assert 0.2 < decide[0].mean() < 0.8 and np.isinf(got).mean() > np.isinf(full).mean() + 0.1  # queries stopped early
    found = np.isfinite(got)
    np.testing.assert_array_equal(got[found], full[found])

"""Worlds from real scans (models/simulation/worlds): the tests build their own scans (scan_fixtures: a
textured box room as OBJ+MTL+PNG, a coloured point-cloud room as PCD, a three-frame posed RGB-D sequence)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import open3d as o3d
import pytest
import scan_fixtures as sf

from navcrafter.models.camera.cameras import Intrinsics, look_at
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.worlds import NO_DATA_RGB, WorldError
from navcrafter.models.simulation.worlds.load import load_world
from navcrafter.models.simulation.worlds.patches import variant_world
from navcrafter.models.simulation.worlds.scene import ScanScene
from navcrafter.models.simulation.worlds.views import start_views

# the room centred by the loader: x in [-2.5, 2.5], y in [-2, 2], z in [0, 2.6]; crate x [1.1, 1.9], y [0.6, 1.4]
CRATE_INSIDE = (1.5, 1.0, 0.4)
RED, BLUE = np.array(sf.RED) / 255, np.array(sf.BLUE) / 255


def _load(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        world = load_world(path, **kw)
    return world, [str(w.message) for w in caught]


@pytest.fixture(scope="module")
def obj_room(tmp_path_factory):
    path = sf.write_obj_room(tmp_path_factory.mktemp("obj"))
    return path, ScanScene(_load(path)[0])


@pytest.fixture(scope="module")
def pcd_room(tmp_path_factory):
    path = sf.write_pcd_room(tmp_path_factory.mktemp("pcd") / "room.pcd")
    world, notes = _load(path)
    return path, ScanScene(world), notes


def _floor_colour(scene: ScanScene, x: float, y: float) -> np.ndarray:
    rc, _ = scene.raycasting()
    ray = np.array([[x, y, 1.0, 0.0, 0.0, -1.0]], dtype=np.float32)
    ans = {k: v.numpy() for k, v in rc.cast_rays(o3d.core.Tensor(ray)).items()}
    assert abs(ans["t_hit"][0] - 1.0) < 0.02  # the floor is at z = 0
    return scene.shade_hits(ans, ray[:, :3], ray[:, 3:])[0]


def test_textured_obj_room_loads_in_metres_z_up_with_uv_texture(obj_room):
    _, scene = obj_room
    w = scene.world
    assert w.colour == "texture" and len(w.textures) == 3
    assert "RANSAC" in w.info["up"] and np.allclose(np.abs(json.loads(json.dumps(w.info["file_to_world"]))[1][2]),
                                                     1.0, atol=0.02)  # the file's y became z
    lo, hi = w.bounds()
    np.testing.assert_allclose(hi - lo, [sf.W, sf.D, sf.H], atol=0.02)
    assert abs(lo[2]) < 0.02  # floor at z = 0
    # the texture at the hit's barycentric UV: the image's top half (v > 0.5, the far side y > 0) is red
    np.testing.assert_allclose(_floor_colour(scene, -1.0, 1.2), RED, atol=0.02)
    np.testing.assert_allclose(_floor_colour(scene, -1.0, -1.2), BLUE, atol=0.02)


def test_holes_render_no_data_and_unscanned_space_is_occupied(pcd_room, obj_room):
    _, scene, _ = pcd_room
    K = Intrinsics.from_fov(60.0, 32, 24)
    up_c2w = look_at(np.array([1.5, 0.0, 1.5]), np.array([1.5, 0.01, 5.0]), up=np.array([1.0, 0.0, 0.0]))
    r = render(scene, up_c2w, K)  # looking up through the missing ceiling (x > 0.5)
    assert (~r.hit).mean() > 0.5
    assert (r.depth[~r.hit] == 0).all() and (r.rgb[~r.hit] == NO_DATA_RGB).all()
    _, obj = obj_room
    for s in (scene, obj):
        occ = s.occupied(np.array([[0.0, 0.0, 1.3], [0.0, 0.0, -1.0], [0.0, 0.0, 4.0], [6.0, 0.0, 1.3],
                                   CRATE_INSIDE]))
        assert occ.tolist() == [False, True, True, True, True]
    rc, _ = obj.raycasting()  # the Open3D API the metrics and the simulated roles call
    assert rc.compute_occupancy(o3d.core.Tensor(np.array([CRATE_INSIDE], dtype=np.float32))).numpy()[0] > 0


def test_start_views_are_free_at_eye_height_and_see_the_scan(obj_room):
    _, scene = obj_room
    views = start_views(scene, 3, 0.25)
    assert len(views) == 3
    pos = np.array([v[:3, 3] for v in views])
    # START_CLEARANCE x r_safe from every surface where the room allows it (collide15: a start at r_safe collided
    # in every frame whenever the estimated scale came out below 1)
    assert (scene.distance(pos) >= 0.5).all() and not scene.occupied(pos).any()
    np.testing.assert_allclose(pos[:, 2], 1.5)
    narrow = start_views(scene, 1, 0.9)[0][:3, 3]  # no position 1.8 m from every wall in a 4 m room: r_safe itself
    assert 0.9 <= scene.distance(narrow[None])[0] < 1.8
    for v in views:
        assert render(scene, v, Intrinsics.from_fov(65.0, 64, 48), colour=False).hit.mean() >= 0.8


def test_point_cloud_room_becomes_a_coloured_surface(pcd_room):
    path, scene, notes = pcd_room
    w = scene.world
    assert w.colour == "vertex" and w.info["format"] == "point cloud"
    assert any("normals" in n for n in notes)
    pts, _ = sf.room_points(spacing=0.2, holes=True, seed=1)
    pts = pts - [sf.W / 2, sf.D / 2, 0.0]  # the loader centres the room
    assert np.median(scene.distance(pts)) < 0.03
    np.testing.assert_allclose(_floor_colour(scene, -1.0, 1.2), RED, atol=0.1)
    np.testing.assert_allclose(_floor_colour(scene, -1.0, -1.2), BLUE, atol=0.1)


def test_rgbd_sequence_is_fused_into_the_room(obj_room, tmp_path):
    _, scene = obj_room
    folder = sf.write_rgbd_sequence(tmp_path / "seq", scene)
    world, notes = _load(folder)
    assert world.colour == "vertex" and world.info["format"] == "rgbd" and any("3 RGB-D frames" in n for n in notes)
    # back in the sequence's frame (= the OBJ world's), the fused surface lies on the room's
    M = np.asarray(world.info["file_to_world"])
    pts = (world.corners.reshape(-1, 3) - M[:3, 3]) @ np.linalg.inv(M[:3, :3]).T
    d = scene.distance(pts[:: max(1, len(pts) // 20000)])
    assert np.median(d) < 0.02 and np.percentile(d, 90) < 0.05
    assert abs(M[2, 2] - 1.0) < 0.02  # z stayed up (the floor was found near the cameras' up)


def _crate(scene: ScanScene) -> np.ndarray:
    label, _ = scene.patches()
    return label == label[np.argmin(np.linalg.norm(scene.world.corners.mean(1) - [1.5, 1.0, 0.8], axis=1))]


def test_variant_moves_objects_and_redraws_colours_structure_stays_without_its_ranges(obj_room):
    _, scene = obj_room
    _, movable = scene.patches()
    crate = _crate(scene)
    assert movable[scene.patches()[0][crate][0]] and movable.sum() == 1  # the crate alone may move
    moved = []
    for v in range(6):
        var = variant_world(scene, v, 0.3, structure_shift_m=(0.0, 0.0), extent_change=(0.0, 0.0))
        delta = var.world.corners - scene.world.corners
        assert np.abs(delta[~crate]).max() == 0  # floor, walls and ceiling stay without structure ranges
        shift = delta[crate].reshape(-1, 3)
        assert np.allclose(shift, shift[0]) and shift[0, 2] == 0 and np.linalg.norm(shift[0]) <= 0.3 + 1e-6
        moved.append(np.linalg.norm(shift[0]))
        assert 0 < np.abs(var.offsets).max() <= 0.2
        # the structure draws have their own stream: the objects move exactly as with structure moves on
        full = variant_world(scene, v, 0.3, structure_shift_m=(0.3, 1.0), extent_change=(0.1, 0.2))
        np.testing.assert_array_equal(full.world.corners[crate], var.world.corners[crate])
        np.testing.assert_array_equal(full.offsets, var.offsets)
    assert max(moved) > 0.05


def _surfaces(world) -> dict[str, np.ndarray]:
    """Triangle masks of the OBJ room's floor, ceiling and four walls (ground-truth frame, centred)."""
    c = world.corners.astype(np.float64)
    hw, hd = sf.W / 2, sf.D / 2
    on = (lambda axis, v: (np.abs(c[:, :, axis] - v) < 0.01).all(1))  # the loader levels the room to ~1e-4
    return {"floor": on(2, 0.0), "ceiling": on(2, sf.H), "west": on(0, -hw), "east": on(0, hw),
            "south": on(1, -hd), "north": on(1, hd)}


def test_variant_of_a_room_scan_changes_its_extents_like_a_generated_room(obj_room):
    """Walls move along their normal so each horizontal extent changes by ``extent_change`` (split between its two
    walls), the ceiling by ``extent_change`` x the height; the floor (which carries the camera) stays."""
    _, scene = obj_room
    parts = _surfaces(scene.world)
    changes, seen = [], set()
    for v in range(8):
        var = variant_world(scene, v, 0.3, structure_shift_m=(0.3, 1.0), extent_change=(0.1, 0.2))
        delta = (var.world.corners - scene.world.corners).astype(np.float64)
        assert np.abs(delta[parts["floor"]]).max() == 0
        move = {}
        for name, sel in parts.items():
            d = delta[sel].reshape(-1, 3)
            assert np.allclose(d, d[0], atol=1e-5), name  # each surface moves rigidly
            move[name] = d[0]
        for a, b, axis, extent in (("west", "east", 0, sf.W), ("south", "north", 1, sf.D)):
            for w in (a, b):  # along its own normal only
                assert np.abs(np.delete(move[w], axis)).max() < 1e-3, (w, move[w])  # the loader levels to ~1e-4
            change = (move[b][axis] - move[a][axis]) / extent  # the new extent minus the old, as a fraction
            assert 0.1 - 1e-4 <= abs(change) <= 0.2 + 1e-4, (v, a, change)
            assert move[b][axis] * change >= -1e-6 and move[a][axis] * change <= 1e-6  # both walls out or in
            changes.append(change)
        dz = move["ceiling"]
        assert abs(dz[0]) < 1e-6 and abs(dz[1]) < 1e-6 and 0.1 - 1e-4 <= abs(dz[2]) / sf.H <= 0.2 + 1e-4
        seen.add(bool(dz[2] > 0))
    assert min(changes) < 0 < max(changes) and seen == {True, False}  # rooms grow and shrink
    again = variant_world(scene, 3, 0.3, structure_shift_m=(0.3, 1.0), extent_change=(0.1, 0.2))
    variant_world.cache_clear()
    np.testing.assert_array_equal(again.world.corners, variant_world(
        scene, 3, 0.3, structure_shift_m=(0.3, 1.0), extent_change=(0.1, 0.2)).world.corners)  # seeded


def test_variant_of_a_scan_without_ceiling_moves_walls_like_facades(obj_room):
    """No ceiling: no height to change; each wall moves along its normal by a signed ``structure_shift_m`` draw."""
    from navcrafter.models.simulation.worlds.world import World

    _, scene = obj_room
    w = scene.world
    keep = ~_surfaces(w)["ceiling"]
    open_top = ScanScene(World("open", w.corners[keep], w.colour, None if w.corner_rgb is None else w.corner_rgb[keep],
                               w.uvs[keep], w.texture_id[keep], w.textures, w.floor, w.info), source="open")
    parts = _surfaces(open_top.world)
    shifts = []
    for v in range(4):
        var = variant_world(open_top, v, 0.3, structure_shift_m=(0.3, 1.0), extent_change=(0.1, 0.2))
        delta = (var.world.corners - open_top.world.corners).astype(np.float64)
        assert np.abs(delta[parts["floor"]]).max() == 0
        for name, axis in (("west", 0), ("east", 0), ("south", 1), ("north", 1)):
            d = delta[parts[name]].reshape(-1, 3)
            assert np.allclose(d, d[0], atol=1e-5) and np.abs(np.delete(d[0], axis)).max() < 1e-3
            assert 0.3 - 1e-4 <= abs(d[0, axis]) <= 1.0 + 1e-4, (name, d[0])
            shifts.append(d[0, axis])
        still = variant_world(open_top, v, 0.3, structure_shift_m=(0.0, 0.0), extent_change=(0.1, 0.2))
        assert np.abs((still.world.corners - open_top.world.corners)[~_crate(open_top)]).max() == 0
    assert min(shifts) < 0 < max(shifts)


def test_neutral_vertex_colour_textured_ply_and_glb_meshes(obj_room, tmp_path):
    import trimesh

    _, scene = obj_room
    mesh = scene.world.merged_mesh()
    o3d.io.write_triangle_mesh(str(tmp_path / "coloured.ply"), mesh)
    plain = o3d.geometry.TriangleMesh(mesh.vertices, mesh.triangles)
    o3d.io.write_triangle_mesh(str(tmp_path / "plain.ply"), plain)
    w, _ = _load(tmp_path / "coloured.ply")
    assert w.colour == "vertex"
    w, notes = _load(tmp_path / "plain.ply")
    assert w.colour == "neutral" and "neutral grey" in w.info["colour_note"] and any("no colour" in n for n in notes)
    r = render(ScanScene(w), start_views(ScanScene(w), 1, 0.25)[0], Intrinsics.from_fov(60, 32, 24))
    assert np.ptp(r.rgb[r.hit], axis=1).max() == 0  # grey, no invented texture
    room = trimesh.load(str(sf.write_obj_room(tmp_path / "obj")))
    glb = tmp_path / "room.glb"
    room.export(str(glb))
    # a PLY with per-vertex texture coordinates (s, t) and its image named by a TextureFile comment
    merged = room.dump(concatenate=True)
    mat = merged.visual.material
    (getattr(mat, "image", None) or mat.baseColorTexture).convert("RGB").save(tmp_path / "atlas.png")
    ply = trimesh.exchange.ply.export_ply(merged, encoding="ascii")
    head, body = ply.split(b"end_header", 1)
    (tmp_path / "textured.ply").write_bytes(head.replace(b"comment https://github.com/mikedh/trimesh",
                                                         b"comment TextureFile atlas.png") + b"end_header" + body)
    assert b"property double s" in head
    for path in (glb, tmp_path / "textured.ply"):
        w, _ = _load(path)
        assert w.colour == "texture", path
        g = ScanScene(w)
        np.testing.assert_allclose(_floor_colour(g, -1.0, 1.2), RED, atol=0.03)
        np.testing.assert_allclose(_floor_colour(g, -1.0, -1.2), BLUE, atol=0.03)


def test_ply_mesh_with_face_colours(tmp_path):
    """A PLY whose faces carry the colour (``element face`` with red/green/blue, no vertex colour): drawn flat
    in each face's colour."""
    import trimesh

    tris, cols = [], []
    for name, quad in sf.room_quads():
        for t in sf._subdivide(quad):
            tris.append(t)
            y = t.mean(0)[1]
            cols.append(sf.CRATE_RGB if name == "crate" else sf.WALL if name != "floor" else
                        sf.RED if y > sf.D / 2 else sf.BLUE)
    tris = np.asarray(tris)
    mesh = trimesh.Trimesh(tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3), process=False,
                           face_colors=np.c_[np.asarray(cols, dtype=np.uint8), np.full(len(cols), 255, np.uint8)])
    mesh.merge_vertices()  # shared vertices: a face's colour must not bleed into its neighbours'
    assert len(mesh.vertices) < 3 * len(mesh.faces) and mesh.visual.kind == "face"
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary")
    head = data.split(b"end_header")[0]
    assert b"element face" in head and b"property uchar red" in head.split(b"element face")[1]
    assert b"red" not in head.split(b"element face")[0]  # no vertex colours: the faces alone carry it
    (tmp_path / "faces.ply").write_bytes(data)
    w, notes = _load(tmp_path / "faces.ply", up="z")
    assert w.colour == "vertex" and "colour_note" not in w.info and not any("no colour" in n for n in notes)
    scene = ScanScene(w)
    np.testing.assert_allclose(_floor_colour(scene, -1.0, 1.2), RED, atol=0.01)
    np.testing.assert_allclose(_floor_colour(scene, -1.0, -1.2), BLUE, atol=0.01)
    r = render(scene, start_views(scene, 1, 0.25)[0], Intrinsics.from_fov(60, 32, 24))
    shown = {tuple(c) for c in r.rgb[r.hit]}
    assert shown <= {sf.RED, sf.BLUE, sf.WALL, sf.CRATE_RGB}, shown - {sf.RED, sf.BLUE, sf.WALL, sf.CRATE_RGB}


def test_plain_point_cloud_is_neutral_grey_and_labelled(tmp_path):
    """A point cloud without colour becomes a surface drawn in the labelled neutral grey (no invented colour)."""
    path = sf.write_pcd_room(tmp_path / "plain.pcd", colours=False)
    assert b"rgb" not in path.read_bytes()[:400]
    w, notes = _load(path)
    assert w.colour == "neutral" and w.corner_rgb is None and w.info["format"] == "point cloud"
    assert "neutral grey" in w.info["colour_note"] and any("no colour" in n for n in notes), notes
    scene = ScanScene(w)
    pts, _ = sf.room_points(spacing=0.2, holes=True, seed=1)
    assert np.median(scene.distance(pts - [sf.W / 2, sf.D / 2, 0.0])) < 0.03  # the room's surface
    r = render(scene, start_views(scene, 1, 0.25)[0], Intrinsics.from_fov(60, 32, 24))
    assert r.hit.mean() > 0.5 and np.ptp(r.rgb[r.hit], axis=1).max() == 0  # grey, shaded only
    assert len(np.unique(r.rgb[r.hit][:, 0])) > 1  # headlight shading, not one flat colour


@pytest.mark.parametrize("case", ["missing", "empty", "garbage", "nan", "millimetres", "tiny", "unknown",
                                  "object only"])
def test_bad_scans_name_the_file_and_the_fix(case, tmp_path):
    path = tmp_path / "scan.obj"
    expect = {"missing": "does not exist", "empty": "empty", "garbage": "no triangles", "nan": "NaN",
              "millimetres": "--scale 0.001", "tiny": "--scale", "unknown": "unknown scan format",
              "object only": "no free space"}[case]
    if case == "empty":
        path.write_bytes(b"")
    elif case == "garbage":
        path.write_text("this is not a mesh\n")
    elif case == "nan":
        path = sf.write_obj_room(tmp_path, nan=True)
    elif case == "millimetres":
        path = sf.write_obj_room(tmp_path, unit=1000.0)
    elif case == "tiny":
        path = sf.write_obj_room(tmp_path, unit=0.01)
    elif case == "unknown":
        path = tmp_path / "scan.xyzw"
        path.write_text("1 2 3\n")
    elif case == "object only":
        path = tmp_path / "box.ply"
        box = o3d.geometry.TriangleMesh.create_box(1.5, 1.5, 1.5)
        o3d.io.write_triangle_mesh(str(path), box)
    with pytest.raises(WorldError) as err:
        world, _ = _load(path, up="z" if case == "object only" else "auto")
        start_views(ScanScene(world), 1, 0.25, source=str(path))
    assert str(path) in str(err.value) and expect in str(err.value), str(err.value)


def test_missing_texture_warns_and_falls_back(tmp_path):
    path = sf.write_obj_room(tmp_path, texture=False)
    world, notes = _load(path)
    assert any("floor.png" in n and "missing" in n and "neutral" in n for n in notes), notes
    assert world.colour == "neutral" and "colour_note" in world.info


def test_honest_synthesizer_hallucinates_a_scan_from_its_patches(obj_room):
    """With nothing in the cloud every hit pixel is unanchored: the frames come from the scan's per-clip variant
    (re-coloured patches), not the truth; holes stay no data with depth 0."""
    from navcrafter.models.roles import SynthesisRequest
    from navcrafter.models.simulation.backend import SimulationSynthesizer, SimulationTruth
    from navcrafter.schemas.config import SimulationConfig

    _, scene = obj_room
    start = start_views(scene, 1, 0.25)[0]
    K = Intrinsics.from_fov(65.0, 48, 36)
    truth = SimulationTruth(scene, start, K, world_scale=1.0)
    from navcrafter.models.camera.cameras import axis_angle_to_matrix

    traj = np.stack([np.eye(4)] * 3)
    for i, deg in ((1, 5.0), (2, 10.0)):  # a pan in place (the start is only r_safe from a wall)
        traj[i, :3, :3] = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.deg2rad(deg))
    photo = render(scene, start, K).rgb
    req = SynthesisRequest(photo, traj, K, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), seed=3)
    cfg = SimulationConfig(drift_rot_deg=0.0, drift_trans=0.0)
    clip = SimulationSynthesizer(truth, cfg).simulate(req)
    assert clip.true_quality[1:].max() < 0.05  # nothing anchored: (almost) every pixel hallucinated
    exact = render(scene, truth.gt_pose(traj[2:])[0], K, supersample=cfg.supersample).rgb
    assert np.abs(clip.frames[2].astype(int) - exact.astype(int)).mean() > 5  # re-drawn colours
    none = SimulationSynthesizer(truth, SimulationConfig(drift_rot_deg=0.0, drift_trans=0.0, hallucinate=False))
    again = none.simulate(req)
    assert np.abs(again.frames[2].astype(int) - exact.astype(int)).mean() < 1


def test_tum_poses_read_like_the_redwood_log(obj_room, tmp_path):
    from scipy.spatial.transform import Rotation

    from navcrafter.models.simulation.worlds.load import read_poses

    _, scene = obj_room
    folder = sf.write_rgbd_sequence(tmp_path / "seq", scene, size=(16, 12))
    log = read_poses(folder)
    (folder / "trajectory.log").unlink()
    lines = [f"{i * 0.1:.1f} " + " ".join(f"{v:.9f}" for v in (*M[:3, 3], *Rotation.from_matrix(M[:3, :3]).as_quat()))
             for i, M in enumerate(log)]
    (folder / "poses.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    np.testing.assert_allclose(read_poses(folder), log, atol=1e-6)
    (folder / "poses.txt").write_text("0 1 2 3\n")
    with pytest.raises(WorldError, match="poses.txt.*8 numbers"):
        read_poses(folder)


def test_table_one_skips_no_data_pixels():
    from navcrafter.schemas.config import EvaluationConfig
    from navcrafter.tasks.score import image_quality_rows

    rng = np.random.default_rng(0)
    real = rng.integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
    fake = real.copy()
    valid = np.ones((2, 32, 32), dtype=bool)
    valid[:, :, 20:] = False  # a hole in the scan
    fake[~valid] = 255 - real[~valid]  # whatever the video drew there
    rows = {r["metric"]: r for r in image_quality_rows(fake, real, EvaluationConfig(), valid=valid)}
    assert rows["PSNR"]["value"] == 100.0 and "scanned pixels only" in rows["PSNR"]["note"]
    assert rows["SSIM"]["value"] > 0.99 and "LPIPS" in rows
    unmasked = {r["metric"]: r for r in image_quality_rows(fake, real, EvaluationConfig())}
    assert unmasked["PSNR"]["value"] < 20

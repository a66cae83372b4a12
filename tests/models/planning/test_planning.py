"""Collision-aware planning: point renderer, candidates, collision detector, optimisation, planners."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from navcrafter.models.camera.cameras import Intrinsics, interpolate_poses, look_at, unproject_depth
from navcrafter.models.planning.planners import (
    WORLD_UP,
    CollisionAwarePlanner,
    CollisionDetector,
    PlanningState,
    SearchSpace,
    SeenView,
    ViewCrafterPlanner,
    candidate_rounds,
    optimise_trajectory,
    repair_candidate,
    sample_candidates,
    search_frame,
    space_positions,
    visibility_score,
)
from navcrafter.models.reconstruction.pointrender import render_points
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.scenes import Light, SceneObject, SimScene
from navcrafter.models.simulation.textures import Material
from navcrafter.schemas.config import PlanConfig

K64 = Intrinsics.from_fov(70, 64, 64)


def box(x0, y0, z0, sx, sy, sz):
    m = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
    m.translate((x0, y0, z0))
    m.compute_triangle_normals()
    return m


def scene_of(*boxes) -> SimScene:
    """Boxes in a world that is its own ground-truth frame, with a far back wall at z = 12."""
    objs = [SceneObject(f"b{i}", b, 0) for i, b in enumerate((*boxes, box(-30, -30, 12, 60, 60, 1)))]
    return SimScene("test", 0, objs, [Material("plain", (0.5, 0.5, 0.5), (0.4, 0.4, 0.4), 1.0)],
                    Light("sun", (0.0, -1.0, 0.0)), True, np.eye(4), 70.0)


def observe(scene: SimScene, poses: list[np.ndarray], K: Intrinsics = K64) -> tuple[np.ndarray, list[SeenView]]:
    """What cameras at ``poses`` saw: the cloud of their depth maps and the seen views."""
    pts, views = [], []
    for c2w in poses:
        r = render(scene, c2w, K, colour=False)
        p, _ = unproject_depth(r.depth.astype(np.float64), c2w, K.K, mask=r.hit)
        pts.append(p)
        views.append(SeenView(c2w, K.K, r.depth))
    return np.concatenate(pts), views


# --------------------------------------------------------------------------------------------------
# Point renderer
# --------------------------------------------------------------------------------------------------
def test_point_renderer_zbuffer_colours_and_brute_force_reference():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform([-1, -1, 2], [1, 1, 6], (3000, 3)), [[0.0, 0.0, 3.0], [0.0, 0.0, 5.0]]])
    cols = rng.integers(0, 255, (len(pts), 3)).astype(np.uint8)
    K = Intrinsics.from_fov(60, 40, 30).K
    out = render_points(pts, np.eye(4), K, 30, 40, point_size=1e-6, colors=cols)  # radius 0: one pixel each
    # brute force: nearest point per pixel
    ref = np.zeros((30, 40))
    ref_col = np.zeros((30, 40, 3), np.uint8)
    uv = (pts @ K.T)[:, :2] / pts[:, 2:]
    for i in np.argsort(-pts[:, 2], kind="stable"):  # far to near, nearest written last
        u, v = int(np.floor(uv[i, 0])), int(np.floor(uv[i, 1]))
        if 0 <= u < 40 and 0 <= v < 30 and (ref[v, u] == 0 or pts[i, 2] <= ref[v, u]):
            ref[v, u] = pts[i, 2]
            ref_col[v, u] = cols[i]
    np.testing.assert_allclose(out.depth, ref, rtol=1e-5)
    np.testing.assert_array_equal(out.mask, ref > 0)
    same = (ref > 0)
    assert (out.color[same] == ref_col[same]).all(1).mean() > 0.99  # exact ties may pick either point
    empty = render_points(np.zeros((0, 3)), np.eye(4), K, 30, 40, 0.1)
    assert not empty.mask.any()


def test_point_renderer_square_splats_match_brute_force():
    rng = np.random.default_rng(2)
    pts = rng.uniform([-1.5, -1, 0.5], [1.5, 1, 5], (400, 3))
    K = Intrinsics.from_fov(70, 48, 32).K
    size, R = 0.08, 3
    out = render_points(pts, np.eye(4), K, 32, 48, point_size=size, max_radius=R)
    ref = np.full((32, 48), np.inf)
    uv = (pts @ K.T)[:, :2] / pts[:, 2:]
    for (u, v), z in zip(uv, pts[:, 2]):
        r = int(np.clip(np.ceil(K[0, 0] * size / (2 * z) - 0.5), 0, R))
        j, i = int(np.floor(u)), int(np.floor(v))
        for y in range(max(0, i - r), min(32, i + r + 1)):
            for x in range(max(0, j - r), min(48, j + r + 1)):
                ref[y, x] = min(ref[y, x], z)
    np.testing.assert_array_equal(out.mask, np.isfinite(ref))
    np.testing.assert_allclose(out.depth[out.mask], ref[np.isfinite(ref)], rtol=1e-5)


def test_point_renderer_splats_grow_with_proximity():
    K = Intrinsics.from_fov(60, 64, 64).K
    near = render_points(np.array([[0.0, 0.0, 1.0]]), np.eye(4), K, 64, 64, point_size=0.1)
    far = render_points(np.array([[0.0, 0.0, 10.0]]), np.eye(4), K, 64, 64, point_size=0.1)
    assert near.mask.sum() > far.mask.sum() >= 1
    behind = render_points(np.array([[0.0, 0.0, -1.0]]), np.eye(4), K, 64, 64, point_size=0.1)
    assert not behind.mask.any()


# --------------------------------------------------------------------------------------------------
# Candidates and score
# --------------------------------------------------------------------------------------------------
def test_candidates_lie_on_the_quarter_sphere_about_the_centre_and_look_at_it():
    centre = np.array([0.0, 0.0, 5.0])
    space = SearchSpace((0.6, 1.0), (-60.0, 60.0), (-20.0, 20.0))
    c = sample_candidates(centre, 5.0, space, 20, np.random.default_rng(1))
    back, right, up = search_frame(centre)
    np.testing.assert_allclose(back, [0, 0, -1])  # from o towards the input camera
    np.testing.assert_allclose(up, -np.array([0, 1, 0]))
    off = c[:, :3, 3] - centre
    r = np.linalg.norm(off, axis=1)
    assert ((r >= 3.0 - 1e-9) & (r <= 5.0 + 1e-9)).all()
    el = np.rad2deg(np.arcsin(off @ up / r))
    az = np.rad2deg(np.arctan2(off @ right, off @ back))
    assert (np.abs(el) <= 20 + 1e-6).all() and (np.abs(az) <= 60 + 1e-6).all()
    assert az.min() < -30 and az.max() > 30  # stratified over the whole range
    for T in c:  # every candidate looks at o, upright
        to_o = (centre - T[:3, 3]) / np.linalg.norm(centre - T[:3, 3])
        assert T[:3, 2] @ to_o > 1 - 1e-9 and T[:3, 1] @ WORLD_UP < 0
    again = sample_candidates(centre, 5.0, space, 20, np.random.default_rng(1))
    np.testing.assert_array_equal(c, again)
    # the input camera itself lies on S (azimuth 0, elevation 0, radius d0)
    np.testing.assert_allclose(space_positions(centre, np.array(0.0), np.array(0.0), np.array(5.0)), [0, 0, 0],
                               atol=1e-12)


def test_a_colliding_candidate_is_moved_to_the_nearest_free_position_of_the_search_space():
    _, state = room_state()
    det = CollisionDetector(state.cloud_points, 0.25, state.views)
    space = SearchSpace()
    side = look_at(space_positions(state.centre, np.deg2rad(80.0), 0.0, 4.0), state.centre)  # beyond the wall
    assert det.collides(side[None, :3, 3])[0]
    moved = repair_candidate(side, state.current, state.centre, state.d0, space, det)
    assert moved is not None and not det.collides(moved[None, :3, 3])[0]
    to_o = state.centre - moved[:3, 3]
    np.testing.assert_allclose(moved[:3, 2], to_o / np.linalg.norm(to_o), atol=1e-9)  # still looks at o
    # the nearest free one: no free grid position of S is closer to the candidate
    grid = space_positions(state.centre, *np.meshgrid(np.deg2rad(np.arange(-90, 91, 10.0)),
                                                      np.deg2rad(np.arange(-30, 31, 10.0)),
                                                      state.d0 * np.linspace(0.6, 1.0, 3), indexing="ij"))
    grid = grid.reshape(-1, 3)[~det.collides(grid.reshape(-1, 3))]
    assert np.linalg.norm(moved[:3, 3] - side[:3, 3]) <= np.linalg.norm(grid - side[:3, 3], axis=1).min() + 1e-9
    blocked = CollisionDetector(state.cloud_points, 50.0, state.views)  # nothing is free
    assert repair_candidate(side, state.current, state.centre, state.d0, space, blocked) is None


def test_the_clearance_a_path_needs_grows_with_the_distance_travelled():
    _, state = room_state()
    det = CollisionDetector(state.cloud_points, 0.25, state.views, follow_error=0.1)
    x = np.stack([np.zeros(3), [1.0, 0, 0], [1.0, 0, 2.0]])
    np.testing.assert_allclose(det.path_clearance(x), [0.25, 0.35, 0.55])
    # a path that keeps r_safe but not the growing margin collides only with the follow error
    wall_x = 2.9  # the east wall's inner face is at x = 3.0
    path = interpolate_poses(look_at(np.array([wall_x - 1.5, 0.0, 4.0]), state.centre),
                             look_at(np.array([wall_x - 0.3, 0.0, 4.5]), state.centre), 21)
    free_space = CollisionDetector(state.cloud_points, 0.25, state.views, unknown_is_free=True)
    drifting = CollisionDetector(state.cloud_points, 0.25, state.views, unknown_is_free=True, follow_error=0.2)
    assert free_space.clearance(path[:, :3, 3]).min() > 0.25  # 0.4 m from the wall the cloud saw at its end
    assert not free_space.trajectory_collides(path) and drifting.trajectory_collides(path)


def test_visibility_score_formula():
    def mask(m):
        a = np.zeros(100, bool)
        a[: int(m * 100)] = True
        return a

    assert visibility_score(mask(0.0), 0.5) == 0.0  # nothing anchors the view
    assert visibility_score(mask(1.0), 0.5) == 0.0  # nothing new
    assert visibility_score(mask(0.5), 0.5) == pytest.approx(0.5)
    assert visibility_score(mask(0.25), 0.5) == pytest.approx(0.75 * 0.5)
    assert visibility_score(mask(0.8), 0.5) == pytest.approx(0.2)


# --------------------------------------------------------------------------------------------------
# Collision detector
# --------------------------------------------------------------------------------------------------
def test_candidate_inside_an_obstacle_is_rejected():
    scene = scene_of(box(-0.75, -0.75, 4.0, 1.5, 1.5, 1.5))  # a cabinet 4 m in front of the camera
    cloud, views = observe(scene, [np.eye(4)])
    det = CollisionDetector(cloud, 0.25, views)
    inside = np.array([[0.0, 0.0, 4.75]])
    assert det.clearance(inside)[0] > 0.25  # far from every observed point...
    assert det.collides(inside)[0]  # ...but behind the surface the camera saw
    assert not det.collides(np.array([[0.5, 0.2, 2.0]]))[0]  # open space in front of it
    assert det.collides(np.array([[0.0, 0.0, 3.9]]))[0]  # within r_safe of the front face
    assert det.collides(np.array([[0.0, 0.0, -2.0]]))[0]  # never seen (behind the camera)
    assert not det.collides(np.array([[0.0, 0.1, -0.1]]))[0]  # next to a camera that stood there
    lenient = CollisionDetector(cloud, 0.25, views, unknown_is_free=True)
    assert not lenient.collides(np.array([[0.0, 0.0, -2.0]]))[0]  # unseen space allowed...
    assert lenient.collides(inside)[0]  # ...but not space behind an observed surface


def panel_world():
    """A thin panel (the plane x = 0 around z = 4) between two points, seen from both sides."""
    scene = scene_of(box(-0.02, -0.6, 3.4, 0.04, 1.2, 1.2))
    cams = [look_at(np.array([-3.0, 0.0, 4.0]), np.array([0.0, 0.0, 4.0])),
            look_at(np.array([3.0, 0.0, 4.0]), np.array([0.0, 0.0, 4.0])),
            look_at(np.zeros(3), np.array([0.0, 0.0, 4.0]))]
    cloud, views = observe(scene, cams, Intrinsics.from_fov(90, 96, 96))
    return scene, cloud, views


def test_straight_path_through_a_wall_is_bent_around_it_keeping_r_safe():
    scene, cloud, views = panel_world()
    r_safe = 0.25
    det = CollisionDetector(cloud, r_safe, views)
    centre = np.array([0.0, 0.0, 8.0])
    a = look_at(np.array([-1.5, 0.0, 4.0]), centre)
    b = look_at(np.array([1.5, 0.0, 4.0]), centre)
    straight = interpolate_poses(a, b, 41)
    assert det.trajectory_collides(straight)
    assert scene.distance(straight[:, :3, 3]).min() < 0.05  # it really goes through the panel
    res = optimise_trajectory(straight, det, centre, smoothness=1.0)
    assert res.collision_free and res.optimised
    assert np.array_equal(res.trajectory[0], a) and np.array_equal(res.trajectory[-1], b)
    pos = res.trajectory[:, :3, 3]
    assert det.clearance(pos).min() >= r_safe * 0.999
    # against the true panel (the detector works on the cloud thinned to r_safe / 8)
    assert scene.distance(pos).min() >= r_safe * 0.85
    assert not det.trajectory_collides(res.trajectory)
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert steps.max() < 4 * steps.mean()  # smooth: no jumps
    for T in res.trajectory[1:-1]:  # interior cameras look at o
        to_o = (centre - T[:3, 3]) / np.linalg.norm(centre - T[:3, 3])
        assert T[:3, 2] @ to_o > 1 - 1e-9


def test_optimiser_runs_on_one_blas_thread_with_the_same_result_and_restores_the_limit(monkeypatch):
    """The L-BFGS starts run with one BLAS thread (with OpenBLAS's two they waited on each other: 17.4 s against
    4.2 s for one plan, benchmarks/results/planning-explore8-speed); the result is the one without the limit,
    bit for bit, and the caller's BLAS threads are restored."""
    import contextlib

    from threadpoolctl import threadpool_info

    from navcrafter.models.planning import planners as planners_mod

    def blas_threads():
        return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    _, cloud, views = panel_world()
    det = CollisionDetector(cloud, 0.25, views)
    centre = np.array([0.0, 0.0, 8.0])
    straight = interpolate_poses(look_at(np.array([-1.5, 0.0, 4.0]), centre),
                                 look_at(np.array([1.5, 0.0, 4.0]), centre), 41)
    before = blas_threads()
    assert before, "numpy has no BLAS library threadpoolctl can see"
    seen, real_minimize = [], planners_mod.minimize

    def minimize(*args, **kwargs):
        seen.append(blas_threads())
        return real_minimize(*args, **kwargs)

    monkeypatch.setattr(planners_mod, "minimize", minimize)
    limited = optimise_trajectory(straight, det, centre)
    assert seen and all(t == [1] * len(before) for t in seen)
    assert blas_threads() == before
    monkeypatch.setattr(planners_mod, "one_blas_thread", contextlib.nullcontext)
    free = optimise_trajectory(straight, det, centre)
    assert limited.optimised and limited.collision_free
    assert np.array_equal(limited.trajectory, free.trajectory)
    assert (limited.starts, limited.iterations, limited.cost) == (free.starts, free.iterations, free.cost)


def test_optimiser_leaves_a_collision_free_path_unchanged():
    scene, cloud, views = panel_world()
    det = CollisionDetector(cloud, 0.25, views)
    centre = np.array([0.0, 0.0, 8.0])
    path = interpolate_poses(look_at(np.array([-1.5, 0.0, 2.0]), centre),
                             look_at(np.array([1.5, 0.0, 2.0]), centre), 21, centre=centre)
    assert not det.trajectory_collides(path)
    res = optimise_trajectory(path, det, centre)
    assert res.collision_free and not res.optimised
    assert np.array_equal(res.trajectory, path)


def test_unreachable_target_is_reported():
    scene, cloud, views = panel_world()
    det = CollisionDetector(cloud, 0.25, views)
    centre = np.array([0.0, 0.0, 8.0])
    inside = look_at(np.array([0.0, 0.0, 4.0]), centre)  # the end point is in the panel
    res = optimise_trajectory(interpolate_poses(look_at(np.array([-1.5, 0.0, 4.0]), centre), inside, 21),
                              det, centre)
    assert not res.collision_free and res.starts == 0  # an end point in the panel: reported at once
    behind = look_at(np.array([0.0, 0.0, 5.5]), centre)  # free, but only reachable around the panel...
    res = optimise_trajectory(interpolate_poses(inside, behind, 21), det, centre)
    assert not res.collision_free


# --------------------------------------------------------------------------------------------------
# Planners
# --------------------------------------------------------------------------------------------------
def room_state(num_frames: int = 21) -> tuple[SimScene, PlanningState]:
    """A closed 6 x 3 x 8 m room with a pillar in front of the camera."""
    walls = [box(-3.1, -1.6, -1, 0.1, 3.2, 9), box(3.0, -1.6, -1, 0.1, 3.2, 9), box(-3.1, -1.7, -1, 6.2, 0.1, 9),
             box(-3.1, 1.5, -1, 6.2, 0.1, 9), box(-3.1, -1.6, 7.0, 6.2, 3.2, 0.1)]
    scene = scene_of(*walls, box(-0.3, -1.5, 3.0, 0.6, 3.0, 0.6))
    K = Intrinsics.from_fov(80, 64, 64)
    cloud, views = observe(scene, [np.eye(4)], K)
    state = PlanningState(current=np.eye(4), centre=np.array([0.0, 0.0, 5.0]), d0=5.0, K=K.K, height=64, width=64,
                          cloud_points=cloud, views=views, num_frames=num_frames, point_size=0.05)
    return scene, state


def test_collision_aware_planner_returns_a_safe_trajectory_to_its_choice():
    scene, state = room_state()
    res = CollisionAwarePlanner(PlanConfig(num_candidates=6)).plan(state, np.random.default_rng(3))
    assert res.chosen >= 0 and res.fallback in ("", "next-candidate")
    assert not res.collides[res.chosen] and res.scores[res.chosen] > 0
    assert np.array_equal(res.trajectory[0], state.current)
    assert np.array_equal(res.trajectory[-1], res.candidates[res.chosen])
    assert res.trajectory.shape == (21, 4, 4) and res.collision_free
    det = CollisionDetector(state.cloud_points, 0.25, state.views)
    assert not det.trajectory_collides(res.trajectory)
    assert (scene.distance(res.trajectory[:, :3, 3]) > 0.2).all()  # clear of the true walls and pillar
    assert len(res.candidates) == 6 * res.rounds and res.rounds == PlanConfig().max_resample + 1  # K, no redraw
    if res.fallback == "":  # the next-best view: the best score among collision-free candidates
        assert res.chosen == int(np.argmax(np.where(res.collides, -1, res.scores)))
    assert (res.scores[res.collides] == 0).all() and not res.masks[res.collides].any()  # empty masks


def test_baseline_is_viewcrafters_nbv_on_the_same_candidates():
    _, state = room_state()
    cfg = PlanConfig(num_candidates=6)
    res = ViewCrafterPlanner(cfg).plan(state, np.random.default_rng(3))
    assert not res.collides.any() and res.collision_free is None and not res.optimised
    # the same K candidates as ours would draw from the same seed, scored by the empty area of their render
    np.testing.assert_array_equal(res.candidates, candidate_rounds(state, cfg, np.random.default_rng(3), 1))
    np.testing.assert_allclose(res.scores, [1 - m.mean() for m in res.masks])
    assert res.chosen == int(np.argmax(res.scores))
    p = res.trajectory[:, :3, 3]
    r = np.linalg.norm(p - state.centre, axis=1)  # on the arc about o (radius interpolated linearly)
    np.testing.assert_allclose(r, np.linspace(r[0], r[-1], len(r)), atol=1e-9)
    assert np.array_equal(res.trajectory[-1], res.candidates[res.chosen])

"""The safe explorer (models/planning/explore.py): voxel map, trajectory shapes, optimistic-but-safe unknown space,
the planner end to end."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_planning import box, observe, room_state, scene_of

import navcrafter.models.planning.explore as explore_mod
import navcrafter.models.planning.planners as planners_mod
from navcrafter.models.camera.cameras import Intrinsics, camera_directions, look_at
from navcrafter.models.planning.explore import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    ExplorerDetector,
    ExplorerPlanner,
    VoxelMap,
    anchored_pixels,
    carving_views,
    end_yaws,
    open_sky,
    repairable,
    shaped_trajectory,
)
from navcrafter.models.planning.planners import (
    CollisionDetector,
    PlanningState,
    SeenView,
    retrace_trajectory,
    retreat_trajectory,
)
from navcrafter.models.planning.registry import PLANNERS
from navcrafter.models.planning.voxel_kernels import march
from navcrafter.schemas.config import PlanConfig

K = Intrinsics.from_fov(80, 64, 64)


def wall_state(num_frames: int = 21) -> PlanningState:
    """A camera at the origin looking down +z at a wall at z = 4 (the test world's far wall is at z = 12)."""
    scene = scene_of(box(-3, -3, 4.0, 6, 6, 0.2))
    cloud, views = observe(scene, [np.eye(4)], K)
    return PlanningState(current=np.eye(4), centre=np.array([0.0, 0.0, 3.0]), d0=3.0, K=K.K, height=64, width=64,
                         cloud_points=cloud, views=views, num_frames=num_frames, point_size=0.05)


def test_voxel_map_carves_free_space_and_marks_surfaces_and_what_lies_behind():
    state = wall_state()
    vmap = VoxelMap.build(state, state.cloud_points, 48)
    _, st = vmap.lookup(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 4.05], [0.0, 0.0, -1.0], [3.5, 0.0, 0.5]]))
    assert st.tolist() == [FREE, OCCUPIED, UNKNOWN, UNKNOWN]  # in view / on the wall / behind the camera / aside
    idx, _ = vmap.lookup(np.array([[0.0, 0.0, 4.8]]))
    assert vmap.occluded[idx[0]]  # behind the observed wall


def test_trajectory_shapes_keep_their_ends_and_differ_on_the_way():
    centre = np.array([0.0, 0.0, 3.0])
    start = look_at(np.zeros(3), centre)
    end = look_at(np.array([2.0, -0.5, 1.5]), centre)
    paths = {s: shaped_trajectory(start, end, centre, 11, s) for s in ("arc", "dolly", "orbit")}
    for p in paths.values():
        assert np.array_equal(p[0], start) and np.array_equal(p[-1], end)
    mid = {s: p[5, :3, 3] for s, p in paths.items()}
    np.testing.assert_allclose(mid["dolly"], (start[:3, 3] + end[:3, 3]) / 2, atol=1e-9)  # straight
    r = [np.linalg.norm(p[:3, 3] - centre) for p in paths["orbit"]]
    np.testing.assert_allclose(r, np.linspace(r[0], r[-1], 11), atol=1e-9)  # radius linear about o
    assert np.linalg.norm(mid["arc"] - mid["dolly"]) > 0.05
    with pytest.raises(ValueError, match="shape"):
        shaped_trajectory(start, end, centre, 11, "zigzag")


def test_unknown_space_is_entered_only_after_the_clip_looked_at_it_and_never_behind_a_surface():
    state = wall_state()
    vmap = VoxelMap.build(state, state.cloud_points, 48)
    det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap, prefix=0.25, reach=2.0)
    # turn right on the spot first (the clip looks 50 deg right, beyond the input view's 40), then move there:
    # allowed once seen, after the prefix, within two cells of the space the input view saw free
    turn = look_at(np.zeros(3), np.array([3.0, 0.0, 2.5]))
    path = np.concatenate([np.repeat(np.eye(4)[None], 3, 0), np.repeat(turn[None], 5, 0)])
    moved = []
    for d in np.linspace(0.1, 1.5, 12):  # along the turned camera's axis
        p = turn.copy()
        p[:3, 3] = d * turn[:3, 2]
        moved.append(p)
    path = np.concatenate([path, np.stack(moved)])
    near, unseen, _ = det.path_flags(path)
    assert not near.any() and not unseen.any()
    assert (vmap.reach(path[-3:, :3, 3]) > 0).all()  # those were unknown cells, not seen free
    far = path.copy()
    far[-1, :3, 3] = 6.0 * turn[:3, 2]  # looked at, but far from all free space: refused
    assert det.path_flags(far)[1][-1] and vmap.reach(far[-1:, :3, 3])[0] > det.max_reach
    # the same positions without having looked there first: refused (outside the space seen free)
    blind = np.concatenate([np.repeat(np.eye(4)[None], 8, 0), np.stack(moved)])
    blind[:, :3, :3] = np.eye(3)  # always looking down +z: the clip never looks at x = 2
    _, unseen_blind, _ = det.path_flags(blind)
    assert unseen_blind[-3:].all()
    # behind the observed wall: never, however it was looked at
    behind = np.repeat(np.eye(4)[None], 12, 0)
    behind[6:, :3, 3] = [0.0, 0.0, 4.8]
    near_b, unseen_b, _ = det.path_flags(behind)
    assert (near_b | unseen_b)[6:].all()


def test_a_frame_in_unknown_space_needs_its_whole_clearance_ball_seen_not_only_its_position():
    """explore_ball (explore11): the clip turns right and looks down 40 deg, then moves level along that heading:
    each position was in view (40 deg above the axis, inside the 42 deg half field of view), the space above it never
    was (an unseen ceiling within r_safe would be met). Without the rule the path is admitted; with it refused; a
    clip looking level (the ball in view) is admitted either way."""
    state = wall_state()
    vmap = VoxelMap.build(state, state.cloud_points, 48)
    heading = np.array([np.sin(np.deg2rad(50)), 0.0, np.cos(np.deg2rad(50))])  # level, 50 deg right of +z
    down = np.array([0.0, np.tan(np.deg2rad(40)), 0.0])  # OpenCV: +y is down

    def clip(look: np.ndarray) -> np.ndarray:
        turn = look_at(np.zeros(3), look)
        path = [np.eye(4)] * 3 + [turn] * 5
        for d in np.linspace(0.1, 1.2, 12):
            p = turn.copy()
            p[:3, 3] = d * heading
            path.append(p)
        return np.stack(path)

    looking_down, looking_level = clip(heading + down), clip(heading)
    flags = {}
    for ball in (0.0, 1.0):
        det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap, prefix=0.25, reach=2.0,
                               ball=ball)
        for name, path in (("down", looking_down), ("level", looking_level)):
            near, unseen, _ = det.path_flags(path)
            assert not near.any()
            flags[name, ball] = unseen
    assert not flags["down", 0.0].any()  # the positions alone were looked at
    assert flags["down", 1.0][-1] and flags["down", 1.0][8:].sum() >= 6  # their space above was not
    assert not flags["level", 0.0].any() and not flags["level", 1.0].any()
    # explore_ball_up (collide13): only the ball above the frame is asked for. Looking up instead (the space above
    # each position in view, the space below never), the whole ball refuses the clip and the upper ball admits it;
    # looking down, the upper ball refuses it as the whole ball does
    looking_up = clip(heading - down)
    for name, path, refused in (("up", looking_up, (True, False)), ("down", looking_down, (True, True))):
        for up, want in zip((False, True), refused):
            det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap, prefix=0.25,
                                   reach=2.0, ball=1.0, ball_up=up)
            near, unseen, _ = det.path_flags(path)
            assert not near.any()
            assert bool(unseen[8:].any()) == want, (name, up)
    # the ball's radius: explore_ball x (r_safe + its follow error x the distance travelled), G's follow error by
    # default (explore11), explore_ball_follow_error when set (explore12); G's clearance keeps its own
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(looking_level[:, :3, 3], axis=0), axis=1))])
    for ball_fe, grows in ((None, 0.26), (0.07, 0.07)):
        det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap, prefix=0.25, reach=2.0,
                               ball=0.5, follow_error=0.26, ball_follow_error=ball_fe)
        radii = {}
        det.ball_seen = lambda trajectory, t, radius, radii=radii: radii.setdefault(t, radius) > 0  # records
        near, unseen, _ = det.path_flags(looking_level)
        assert radii and not unseen.any()
        t = np.array(sorted(radii))
        assert np.allclose([radii[i] for i in t], 0.5 * (0.25 + grows * travelled[t]))
        assert np.allclose(det.path_clearance(looking_level[:, :3, 3]), 0.25 + 0.26 * travelled)


def test_with_explore_ball_seen_free_the_ball_is_asked_in_seen_free_space_too():
    """explore_ball_seen_free (collide14): a clip rising ahead to (0, -1.2, 1.5) (OpenCV: -y is up) looking ahead
    stays in the photo's view, so every frame is seen free and explore_ball never asks its ball; the space above its
    last frames was in no view (the photo's half field of view is 40 deg, the clip's frames look level), so with the
    setting the ball refuses them. The same clip moving level is admitted either way (the space above it in view)."""
    state = wall_state()
    vmap = VoxelMap.build(state, state.cloud_points, 48)
    path = np.repeat(np.eye(4)[None], 21, 0)
    rising, level = path.copy(), path.copy()
    rising[:, 1, 3], rising[:, 2, 3] = -np.linspace(0.0, 1.2, 21), np.linspace(0.0, 1.5, 21)
    level[:, 2, 3] = np.linspace(0.0, 1.5, 21)
    for seen_free in (False, True):
        det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap, prefix=0.1, reach=1.0,
                               follow_error=0.26, ball=0.5, ball_up=True, ball_seen_free=seen_free)
        assert det._visibility(rising[:, :3, 3])[0][3:].all()  # every frame past the start is seen free
        near, unseen, _ = det.path_flags(rising)
        assert not near.any() and bool(unseen[-3:].all()) == seen_free and bool(unseen.any()) == seen_free
        near, unseen, _ = det.path_flags(level)
        assert not near.any() and not unseen.any()


def test_without_explore_ball_open_sky_the_ball_is_not_asked_where_the_input_photo_shows_sky(monkeypatch):
    """explore_ball_open_sky (collide14): the planner hands its detector the ball of explore_ball, or none when the
    setting is false and the input photo shows sky; a photo without sky (a room), or a generated frame's empty
    pixels (no observation), keep the ball."""
    state = wall_state()
    photo = state.views[0]
    depth = photo.depth.copy()
    depth[: depth.shape[0] // 4] = 0.0  # a quarter of the photo is sky
    sky = dataclasses.replace(state, views=[SeenView(photo.c2w, photo.K, depth)])
    invented = dataclasses.replace(state, views=[photo, SeenView(photo.c2w, photo.K, depth, np.ones_like(depth, bool))])
    assert explore_mod.under_open_sky(sky.views) and not explore_mod.under_open_sky(state.views)
    assert not explore_mod.under_open_sky(invented.views)
    few = depth.copy()
    few[:] = photo.depth
    few[0, : int(0.5 * explore_mod.SKY_SHARE * few.size)] = 0.0  # holes, not sky
    assert not explore_mod.under_open_sky([SeenView(photo.c2w, photo.K, few)])
    balls = {}

    class Recording(ExplorerDetector):
        def __init__(self, *args, **kwargs):
            balls[key] = kwargs.get("ball")
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(explore_mod, "ExplorerDetector", Recording)
    for key in [(name, flag) for name in ("sky", "room", "invented") for flag in (True, False)]:
        st = {"sky": sky, "room": state, "invented": invented}[key[0]]
        cfg = PlanConfig(explore_candidates=6, explore_ball=0.5, explore_ball_up=True, explore_ball_open_sky=key[1])
        ExplorerPlanner(cfg).plan(st, np.random.default_rng(0))
    assert balls == {("sky", True): 0.5, ("sky", False): 0.0, ("room", True): 0.5, ("room", False): 0.5,
                     ("invented", True): 0.5, ("invented", False): 0.5}


def test_the_input_photos_sky_is_free_space_a_generated_frames_is_not():
    state = wall_state()
    photo = state.views[0]
    depth = photo.depth.copy()
    depth[: depth.shape[0] // 2] = 0.0  # the upper half shows sky: no surface on those rays
    sky_photo = SeenView(photo.c2w, photo.K, depth)
    generated = SeenView(photo.c2w, photo.K, depth, anchored=np.ones(depth.shape, bool))
    up_ahead = np.array([[0.0, -2.0, 6.0], [0.0, -1.0, 2.5]])  # above the axis (OpenCV: -y is up), in the sky's rays
    for views, expect in (([sky_photo], FREE), ([generated], UNKNOWN)):
        opened = open_sky(views)
        vmap = VoxelMap.build(dataclasses.replace(state, views=opened), state.cloud_points, 48)
        assert (vmap.lookup(up_ahead)[1] == expect).all()
        det = CollisionDetector(state.cloud_points, 0.25, views, thin=False)
        det.views = opened
        assert det._visibility(up_ahead)[0].tolist() == [expect == FREE] * 2
    assert open_sky([generated])[0] is generated and np.isinf(open_sky([sky_photo])[0].depth[0, 0])
    assert (open_sky([sky_photo])[0].depth[-1] == depth[-1]).all()  # the wall's depth unchanged


def test_the_clips_first_frames_may_stand_within_one_map_cell_of_the_start():
    """A street's clip moves ~0.5 m a frame, more than 2 r_safe: its first frames, beside the input camera and so
    outside its frustum, are admitted within one cell of the voxel map (d0 / 16 by default)."""
    state = wall_state()
    aside = np.repeat(np.eye(4)[None], 10, 0)
    aside[1:, :3, 3] = np.linspace(0.0, 0.8, 10)[1:, None] * np.array([-1.0, 0.0, 0.0])  # straight left
    flags = {}
    for cells in (48, 8):  # cells of 0.19 and 1.1 scene units (2 r_safe = 0.5)
        vmap = VoxelMap.build(state, state.cloud_points, cells)
        det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap, prefix=1.0, reach=1.0)
        flags[cells] = det.path_flags(aside)[1]
    assert flags[48][-1] and not flags[48][1]  # 0.8 beyond 2 r_safe: refused; 0.09 from the start: admitted
    assert not flags[8].any()  # all within one 1.1-unit cell of the start


@pytest.mark.parametrize("falloff", [0.0, 0.05])  # 0.05: unknown cells weighted by their distance to known content
def test_explorer_plans_a_safe_clip_that_sees_more_unknown_than_staying(falloff):
    scene, state = room_state()
    assert PLANNERS["explorer"] is ExplorerPlanner
    cfg = PlanConfig(explore_candidates=30, explore_anchor_falloff=falloff)
    res = ExplorerPlanner(cfg).plan(state, np.random.default_rng(0))
    assert res.trajectory.shape == (21, 4, 4) and np.array_equal(res.trajectory[0], state.current)
    assert res.masks is None and len(res.candidates) == len(res.scores) == len(res.collides)
    assert res.timings["trajectories"] == 30
    if res.chosen >= 0:  # a safe trajectory was found: it clears every true surface
        assert (scene.distance(res.trajectory[:, :3, 3]) > 0.2).all()
        assert res.scores[res.chosen] > 0
    else:
        assert res.fallback in ("retreat", "static")


def test_end_poses_turn_by_each_multiple_of_the_yaw_up_to_explore_yaw_turns():
    assert end_yaws(35.0) == (0.0, 35.0, -35.0)  # the default: the explorer before explore_yaw_turns
    assert end_yaws(35.0, 2) == (0.0, 35.0, -35.0, 70.0, -70.0)
    assert end_yaws(0.0, 3) == (0.0,)
    _, state = room_state()
    one = ExplorerPlanner(PlanConfig(explore_candidates=30)).plan(state, np.random.default_rng(0))
    two = ExplorerPlanner(PlanConfig(explore_candidates=30, explore_yaw_turns=2)).plan(state, np.random.default_rng(0))
    assert two.timings["ends"] == one.timings["ends"] * 5 / 3  # every admitted end position, 5 turns instead of 3


def test_a_generated_frame_carves_free_space_only_where_it_copied_the_cloud_it_was_shown():
    state = wall_state()
    # what the input view showed is anchored where a frame shows it again (here: the same camera and depth)
    again = anchored_pixels(state.views[0].depth, np.eye(4), K.K, state.cloud_points, 0.05, 0.08)
    assert again[state.views[0].depth > 0].mean() > 0.9
    # a clip turns right, where the cloud shows nothing; the video model invents the room there and leaves out
    # the box that truly stands at x = 2.3 (a variant with a side wall at x = 5 and no box)
    right = look_at(np.zeros(3), np.array([5.0, 0.0, 0.0]))
    invented = scene_of(box(-3, -3, 4.0, 6, 6, 0.2), box(5, -3, -3, 0.2, 6, 8))
    _, (gen,) = observe(invented, [right], K)
    mask = anchored_pixels(gen.depth, right, K.K, state.cloud_points, 0.05, 0.08)
    assert not mask[gen.depth > 0].any()  # nothing it showed was in the cloud
    inside_box = np.array([[2.3, 0.0, 0.0]])
    views = [state.views[0], SeenView(right, K.K, gen.depth, mask)]
    vmap = VoxelMap.build(dataclasses.replace(state, views=views), state.cloud_points, 48)
    det = ExplorerDetector(state.cloud_points, 0.25, views, thin=False, vmap=vmap)
    assert not det._visibility(inside_box)[0][0]  # not free: the frame invented what stands there
    assert vmap.lookup(inside_box)[1][0] != FREE
    trusting = [state.views[0], SeenView(right, K.K, gen.depth)]  # every pixel trusted: the box's place looks free
    det_all = ExplorerDetector(state.cloud_points, 0.25, trusting, thin=False, vmap=vmap)
    assert det_all._visibility(inside_box)[0][0]
    assert VoxelMap.build(dataclasses.replace(state, views=trusting), state.cloud_points, 48).lookup(inside_box)[1][0] \
        == FREE


def test_share_a_mostly_anchored_frame_carves_with_every_pixel_a_mostly_invented_one_with_its_anchored_pixels():
    """``explore_free_space: share``: the same invented frame (it leaves out the box at x = 2.3) carves the box's
    place free only when at least ``explore_invented_share`` of its pixels are anchored; its empty pixels stay
    unknown (not sky) either way, and the input photo is untouched."""
    state = wall_state()
    right = look_at(np.zeros(3), np.array([5.0, 0.0, 0.0]))
    invented = scene_of(box(-3, -3, 4.0, 6, 6, 0.2), box(5, -3, -3, 0.2, 6, 8))
    _, (gen,) = observe(invented, [right], K)
    depth = gen.depth.copy()
    depth[: depth.shape[0] // 4] = 0.0  # the top quarter empty: no depth there
    inside_box, up_ahead = np.array([[2.3, 0.0, 0.0]]), np.array([[4.0, -3.0, 0.0]])
    mask = np.zeros(depth.shape, bool)
    mask[-depth.shape[0] // 3:] = True  # its lower third anchored (a third of its pixels: 0.33)
    views = [state.views[0], SeenView(right, K.K, depth, mask)]
    for share, freed in ((0.3, True), (0.5, False)):
        carving = carving_views(views, "share", share)
        assert carving[0] is views[0] and (carving[1].anchored.all() if freed else carving[1] is views[1])
        vmap = VoxelMap.build(dataclasses.replace(state, views=views), state.cloud_points, 48, free_views=carving)
        det = ExplorerDetector(state.cloud_points, 0.25, views, thin=False, vmap=vmap, visibility_views=carving)
        assert det._visibility(inside_box)[0][0] == freed
        assert (vmap.lookup(inside_box)[1][0] == FREE) == freed
        opened = open_sky(carving)
        assert not np.isinf(opened[1].depth).any()  # a generated frame's empty pixels stay unknown
        assert not CollisionDetector(state.cloud_points, 0.25, views, thin=False,
                                     visibility_views=opened)._visibility(up_ahead)[0][0]
    for mode in ("anchored", "all"):
        assert carving_views(views, mode, 0.0) is views


def test_a_clip_that_starts_too_near_a_surface_may_back_away_but_not_stay_or_come_closer():
    state = wall_state()
    vmap = VoxelMap.build(state, state.cloud_points, 48)
    det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap)
    start = np.eye(4)
    start[:3, 3] = [0.0, 0.0, 3.85]  # 0.15 from the wall: an earlier clip drifted there
    away = np.repeat(start[None], 11, 0)
    away[:, 2, 3] = np.linspace(3.85, 2.5, 11)
    near, unseen, clearance = det.path_flags(away)
    assert clearance[0] < 0.25 and not near.any() and not unseen.any()
    stay = np.repeat(start[None], 11, 0)
    assert det.path_flags(stay)[0].all()  # staying is no escape
    back_and_forth = away.copy()
    back_and_forth[1, 2, 3] = 3.9  # first closer, then away
    assert det.path_flags(back_and_forth)[0][1]


def test_the_paper_planner_may_also_back_away_from_a_start_too_near_a_surface():
    """G of Algorithm 1 forgives the same escape (``planners.forgive_escape``): before, every path from such a start
    failed G, the camera stayed put, and every later frame of the run counted as a collision."""
    state = wall_state()
    det = CollisionDetector(state.cloud_points, 0.25, state.views)
    start = np.eye(4)
    start[:3, 3] = [0.0, 0.0, 3.85]
    away = np.repeat(start[None], 11, 0)
    away[:, 2, 3] = np.linspace(3.85, 2.5, 11)
    near, _, clearance = det.path_flags(away)
    assert clearance[0] < 0.25 and not near.any()
    assert det.path_flags(np.repeat(start[None], 11, 0))[0].all()  # staying is no escape
    closer = away.copy()
    closer[1, 2, 3] = 3.9
    assert det.path_flags(closer)[0][1]


# --------------------------------------------------------------------------------------------------
# The fallback when no planned path passes G (planners.retreat_trajectory), and what the optimisation can repair
# --------------------------------------------------------------------------------------------------
def near_wall_state() -> PlanningState:
    """``wall_state`` with the camera drifted to 0.3 m from the wall (r_safe 0.25), still looking at it."""
    state = wall_state()
    current = np.eye(4)
    current[:3, 3] = [0.5, 0.0, 3.7]
    return dataclasses.replace(state, current=current)


def test_the_retreat_backs_away_from_the_nearest_surface_on_a_path_g_passes():
    state = near_wall_state()
    det = CollisionDetector(state.cloud_points, 0.25, state.views, follow_error=0.1)
    traj = retreat_trajectory(state.current, state.centre, state.d0, det, 21)
    assert traj is not None and traj.shape == (21, 4, 4) and np.array_equal(traj[0], state.current)
    assert not det.trajectory_collides(traj)
    start, end = det.clearance(traj[[0, -1], :3, 3])
    assert end > start + 0.25 and end >= 0.5  # well away from the wall, not just over the line
    blind = CollisionDetector(state.cloud_points, 0.25, [], follow_error=0.1)  # nothing seen free: no move passes
    assert retreat_trajectory(state.current, state.centre, state.d0, blind, 21) is None


@pytest.mark.parametrize("name", ["collision_aware", "explorer"])
def test_a_planner_with_no_safe_path_moves_away_instead_of_standing_next_to_the_wall(name, monkeypatch):
    """Before: with no candidate path passing G both planners kept the camera still (the demo room: two static
    clips 0.26 m from a wall, 162 collision frames). Here no planned path can pass: the paper planner's optimisation
    never finds one, and every explorer path (shortened ones too) has a frame behind the wall."""

    def fail(trajectory, detector, centre, smoothness=1.0, **_):
        return planners_mod.OptimisationResult(trajectory, False, True)

    shaped = explore_mod.shaped_trajectory

    def through_wall(current, end, centre, num, shape):
        out = shaped(current, end, centre, num, shape)
        out[num // 2, :3, 3] = [0.0, 0.0, 4.8]
        return out

    monkeypatch.setattr(planners_mod, "optimise_trajectory", fail)
    monkeypatch.setattr(explore_mod, "shaped_trajectory", through_wall)
    state = near_wall_state()
    res = PLANNERS[name](PlanConfig(explore_candidates=9)).plan(state, np.random.default_rng(0))
    assert res.fallback in ("retrace", "retreat") and res.chosen == -1  # back towards the input camera here
    det = CollisionDetector(state.cloud_points, 0.25, state.views)
    start, end = det.clearance(res.trajectory[[0, -1], :3, 3])
    assert end > start + 0.25


def test_the_optimisation_is_not_tried_on_paths_it_cannot_repair():
    state = wall_state()
    vmap = VoxelMap.build(state, state.cloud_points, 48)
    det = ExplorerDetector(state.cloud_points, 0.25, state.views, thin=False, vmap=vmap, follow_error=0.1)
    path = np.repeat(np.eye(4)[None], 11, 0)
    path[:, 2, 3] = np.linspace(0.0, 2.0, 11)  # towards the wall in seen free space, ending 2 m from it
    assert repairable(det, path) and not det.trajectory_collides(path)
    to_wall = path.copy()
    to_wall[:, 2, 3] = np.linspace(0.0, 3.65, 11)  # ends 0.35 from the wall: past r_safe, short of r_safe + 0.1 x 3.8
    assert det.trajectory_collides(to_wall) and not repairable(det, to_wall)
    behind = path.copy()
    behind[5, 2, 3] = 4.8  # one frame behind the wall: not admissible, the optimiser has no term for it
    assert not repairable(det, behind)


# --------------------------------------------------------------------------------------------------
# The numba kernels against the numpy arithmetic they replaced
# --------------------------------------------------------------------------------------------------
def _reference_gain(vmap: VoxelMap, poses: np.ndarray, unit: np.ndarray, dist: np.ndarray, weight: np.ndarray,
                    per_frame: bool, prox: np.ndarray | None = None, acc: np.ndarray | None = None,
                    revisit: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Every sample of every ray at once (the explorer's former numpy ``_cast``), reduced per frame or over all;
    unknown cells weighted by ``prox``, plus ``revisit`` x the accuracy gained (over ``acc``) on each ray's first
    occupied cell."""
    d_world = np.einsum("rj,fij->fri", unit, poses[:, :3, :3])
    pts = poses[:, None, None, :3, 3] + dist[None, None, :, None] * d_world[:, :, None, :]
    idx, st = vmap.lookup(pts)
    occ = st == OCCUPIED
    hit = occ.any(2)
    first = np.where(hit, occ.argmax(2), len(dist))
    unk = (st == UNKNOWN) & (np.arange(len(dist))[None, None, :] < first[..., None])
    w = np.broadcast_to(weight[None], unk.shape)
    if prox is not None:
        w = w * prox[np.maximum(idx, 0)]
    at_first = hit[..., None] & (np.arange(len(dist))[None, None, :] == first[..., None])
    w_occ = np.broadcast_to(weight[None], unk.shape)
    if acc is not None:
        w_occ = revisit * np.maximum(0.0, w_occ - acc[np.maximum(idx, 0)])
    frames = range(len(poses)) if per_frame else [slice(None)]
    gain = []
    for f in frames:
        best: dict[int, float] = {}
        for c, x in zip(idx[f][unk[f]].ravel(), w[f][unk[f]].ravel()):
            best[int(c)] = max(best.get(int(c), 0.0), float(x))
        if revisit > 0:
            for c, x in zip(idx[f][at_first[f]].ravel(), w_occ[f][at_first[f]].ravel()):
                best[int(c)] = max(best.get(int(c), 0.0), float(x))
        gain.append(sum(best.values()))
    return np.array(gain), hit.mean(1)


def test_the_ray_march_and_carving_kernels_agree_with_the_numpy_arithmetic():

    scene, state = room_state()
    vmap = VoxelMap.build(state, state.cloud_points, 24)
    # the carving kernel: the input view's free cells are those in front of its depth, by the same projection
    idx = np.stack(np.meshgrid(*[np.arange(24)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = vmap.origin + (idx + 0.5) * vmap.voxel
    v = state.views[0]
    pc = centres @ v.c2w[:3, :3] - v.c2w[:3, 3] @ v.c2w[:3, :3]
    z = pc[:, 2]
    ok = z > 1e-6
    u = np.floor(v.K[0, 0] * pc[:, 0] / np.where(ok, z, 1) + v.K[0, 2]).astype(int)
    w = np.floor(v.K[1, 1] * pc[:, 1] / np.where(ok, z, 1) + v.K[1, 2]).astype(int)
    ok &= (u >= 0) & (u < 64) & (w >= 0) & (w < 64)
    d = np.where(ok, v.depth[np.clip(w, 0, 63), np.clip(u, 0, 63)], 0)
    free = ok & (d > 0) & (z < d - vmap.voxel)
    occupied = vmap.state == OCCUPIED
    assert free.sum() > 100
    np.testing.assert_array_equal(vmap.state == FREE, free & ~occupied)  # a cloud point's cell stays occupied
    # the march: random poses about the room, per frame and as one union
    rng = np.random.default_rng(3)
    poses = np.stack([look_at(rng.uniform([-2, -1, 0.5], [2, 1, 4]), rng.uniform([-2, -1, 3], [2, 1, 7]))
                      for _ in range(6)])
    dirs = camera_directions(Intrinsics.from_fov(80, 8, 8).K, 8, 8).reshape(-1, 3)
    unit = dirs / np.linalg.norm(dirs, axis=1)[:, None]
    dist = (np.arange(40) + 0.5) * vmap.voxel
    weight = rng.random((len(unit), len(dist)))
    for per_frame in (True, False):
        ref_gain, ref_hit = _reference_gain(vmap, poses, unit, dist, weight, per_frame)
        group = np.arange(6) if per_frame else np.zeros(6, dtype=np.int64)
        gain, hit = march(vmap.state, vmap.size, vmap.origin, float(vmap.voxel),
                          np.ascontiguousarray(poses[:, :3, :3]), np.ascontiguousarray(poses[:, :3, 3]),
                          np.ascontiguousarray(unit), dist, weight, group, len(ref_gain), np.ones(24 ** 3),
                          np.zeros(24 ** 3), 0.0)
        assert ref_gain.sum() > 1
        np.testing.assert_allclose(gain, ref_gain, rtol=1e-9)
        np.testing.assert_allclose(hit, ref_hit)
    # the accuracy-aware utility: unknown cells weighted by their expected anchoring, known ones gain by accuracy
    n = 24 ** 3
    prox, acc = rng.random(n), rng.random(n)
    for per_frame in (True, False):
        group = np.arange(6) if per_frame else np.zeros(6, dtype=np.int64)
        plain, _ = _reference_gain(vmap, poses, unit, dist, weight, per_frame)
        ref_gain, _ = _reference_gain(vmap, poses, unit, dist, weight, per_frame, prox, acc, 1.7)
        gain, _ = march(vmap.state, vmap.size, vmap.origin, float(vmap.voxel),
                        np.ascontiguousarray(poses[:, :3, :3]), np.ascontiguousarray(poses[:, :3, 3]),
                        np.ascontiguousarray(unit), dist, weight, group, len(ref_gain), prox, acc, 1.7)
        assert not np.allclose(ref_gain, plain)
        np.testing.assert_allclose(gain, ref_gain, rtol=1e-9)


def test_the_voxel_map_keeps_the_nearest_range_each_occupied_cell_was_seen_at():
    """``VoxelMap.zmin``: the input view sees the room's far wall at its depth; cells it never saw stay at inf."""
    scene, state = room_state()
    vmap = VoxelMap.build(state, state.cloud_points, 24)
    occ = np.flatnonzero(vmap.state == OCCUPIED)
    seen = np.isfinite(vmap.zmin[occ])
    assert seen.mean() > 0.5  # the cloud comes from the views: most occupied cells were seen
    assert np.isinf(vmap.zmin[vmap.state != OCCUPIED]).all()
    v = state.views[0]
    idx = np.stack(np.unravel_index(occ[seen], (24, 24, 24)), -1)
    centres = vmap.origin + (idx + 0.5) * vmap.voxel
    z = (centres - v.c2w[:3, 3]) @ v.c2w[:3, 2]  # z-depth in the (only / nearest) view
    np.testing.assert_allclose(vmap.zmin[occ[seen]], z)


def test_the_retrace_goes_back_along_the_earlier_cameras_past_what_their_clip_put_on_the_path():

    scene = scene_of(box(-3, -3, 4.0, 6, 6, 0.2))
    path = [np.eye(4)]
    for z in (0.8, 1.6, 2.4, 3.2, 3.7):
        p = np.eye(4)
        p[:3, 3] = [0.0, 0.2 * z, z]  # the earlier clip came in along this line, ending 0.3 from the wall
        path.append(p)
    cloud, views = observe(scene, path, K)
    phantom = np.array([[0.05, 0.2 * z, z] for z in np.linspace(1.0, 3.0, 20)])  # the clip's lifting drew these
    det = CollisionDetector(np.concatenate([cloud, phantom]), 0.25, views, follow_error=0.1)
    current = path[-1]
    assert det.clearance(phantom[:1])[0] < 0.1  # G sees a surface on the way back
    traj = retrace_trajectory(current, np.array([0.0, 0.0, 3.0]), 3.0, det, 21)
    assert traj is not None and np.array_equal(traj[0], current)
    x = traj[:, :3, 3]
    assert x[-1, 2] < 3.7 - 0.5 and np.all(np.diff(x[:, 2]) <= 1e-9)  # back, never forwards
    np.testing.assert_allclose(x[:, 1], 0.2 * x[:, 2], atol=1e-9)  # on the earlier cameras' line
    alone = CollisionDetector(cloud, 0.25, views[-1:], follow_error=0.1)  # no earlier camera to go back to
    assert retrace_trajectory(current, np.array([0.0, 0.0, 3.0]), 3.0, alone, 21) is None

"""Trajectory presets (models/camera/trajectories.py) and the camera-file parsers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from navcrafter.models.camera import trajectories as tr
from navcrafter.models.camera.cameras import Intrinsics, invert_pose, look_at, make_pose, project

INTR = Intrinsics.from_fov(60, 32, 32)
N = 9


def start_frame() -> tr.Frame:
    """A camera at (1, -0.5, -4) looking at (0.5, 0, 1), world up -y (a scene's world frame)."""
    return tr.Frame(look_at(np.array([1.0, -0.5, -4.0]), np.array([0.5, 0.0, 1.0])), np.array([0.5, 0.0, 1.0]))


def assert_rigid(c2w: np.ndarray) -> None:
    R = c2w[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    np.testing.assert_allclose(c2w[:, 3], np.broadcast_to([0, 0, 0, 1.0], (len(c2w), 4)), atol=0)


def in_view(c2w: np.ndarray, K: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Per frame: whether ``point`` projects inside the image, in front of the camera."""
    out = []
    for T, k in zip(c2w, K):
        uv, z = project(point[None], T, k)
        out.append(z[0] > 0 and 0 <= uv[0, 0] <= INTR.width and 0 <= uv[0, 1] <= INTR.height)
    return np.array(out)


@pytest.mark.parametrize("name", list(tr.PRESETS))
def test_every_preset_starts_at_the_start_camera_with_rigid_poses(name):
    frame = start_frame()
    path = tr.preset_trajectory(name, frame, N)
    assert path.c2w.shape == (N, 4, 4) and path.focal_scale.shape == (N,) and len(path) == N
    assert_rigid(path.c2w)
    np.testing.assert_allclose(path.c2w[0], frame.c2w, atol=1e-12)
    assert path.focal_scale[0] == 1.0
    K = path.intrinsics(INTR)
    assert K.shape == (N, 3, 3)
    if name in ("orbit", "arc", "dolly", "zoom", "spiral", "truck", "pedestal", "pan", "tilt"):
        assert in_view(path.c2w, K, frame.target).all(), name
    if name not in ("zoom",):
        assert not np.allclose(path.c2w[-1], path.c2w[0]), f"{name} does not move"
    one = tr.preset_trajectory(name, frame, 1)
    np.testing.assert_allclose(one.c2w[0], frame.c2w, atol=1e-12)


def test_orbit_moves_right_about_the_target_and_loops():
    frame = start_frame()
    path = tr.orbit(frame, 8)
    d = np.linalg.norm(path.c2w[:, :3, 3] - frame.target, axis=1)
    np.testing.assert_allclose(d, frame.distance, rtol=1e-9)  # on a circle about the target
    height = path.c2w[:, :3, 3] @ frame.up
    np.testing.assert_allclose(height, height[0], atol=1e-9)  # about the vertical axis
    step = path.c2w[1, :3, 3] - path.c2w[0, :3, 3]
    assert step @ frame.c2w[:3, 0] > 0.3 * np.linalg.norm(step)  # degrees > 0: to the camera's right
    # a full turn: 8 frames 45 degrees apart, the last not repeating the first
    ang = np.rad2deg(np.arccos(np.clip(np.einsum("i,ni->n", path.c2w[0, :3, 2], path.c2w[:, :3, 2]), -1, 1)))
    assert ang[4] == pytest.approx(180, abs=1e-6) and ang[1] == pytest.approx(45, abs=1e-6)
    left = tr.orbit(frame, 8, degrees=-90)
    assert (left.c2w[1, :3, 3] - left.c2w[0, :3, 3]) @ frame.c2w[:3, 0] < 0
    arc = tr.preset_trajectory("arc", frame, 5)
    end = np.rad2deg(np.arccos(arc.c2w[0, :3, 2] @ arc.c2w[-1, :3, 2]))
    assert end == pytest.approx(60, abs=1e-6)  # a partial turn includes its end


def test_translations_follow_the_camera_axes():
    frame = start_frame()
    x, y, z = frame.c2w[:3, 0], frame.c2w[:3, 1], frame.c2w[:3, 2]
    for name, axis, amount in (("dolly", z, 0.5), ("truck", x, 0.5), ("pedestal", -y, 0.25)):
        path = tr.preset_trajectory(name, frame, N)
        moved = path.c2w[-1, :3, 3] - frame.eye
        np.testing.assert_allclose(moved, amount * frame.distance * axis, atol=1e-9)
        np.testing.assert_allclose(path.c2w[:, :3, :3], np.broadcast_to(frame.c2w[:3, :3], (N, 3, 3)), atol=1e-12)
    out = tr.dolly(frame, N, amount=-1.0)
    assert np.linalg.norm(out.c2w[-1, :3, 3] - frame.target) == pytest.approx(2 * frame.distance)
    with pytest.raises(ValueError, match="reach the target"):
        tr.dolly(frame, N, amount=1.0)


def test_rotations_turn_the_expected_way_in_place():
    frame = start_frame()
    x, y, z = frame.c2w[:3, 0], frame.c2w[:3, 1], frame.c2w[:3, 2]
    pan = tr.pan(frame, N, degrees=30)
    np.testing.assert_allclose(pan.c2w[:, :3, 3], np.broadcast_to(frame.eye, (N, 3)), atol=1e-12)
    assert pan.c2w[-1, :3, 2] @ x == pytest.approx(np.sin(np.deg2rad(30)))  # turned right
    np.testing.assert_allclose(pan.c2w[:, :3, 1], np.broadcast_to(y, (N, 3)), atol=1e-12)  # about its own y
    tilt = tr.tilt(frame, N, degrees=20)
    assert tilt.c2w[-1, :3, 2] @ -y == pytest.approx(np.sin(np.deg2rad(20)))  # turned up
    around = tr.look_around(frame, 12)
    np.testing.assert_allclose(around.c2w[:, :3, 3], np.broadcast_to(frame.eye, (12, 3)), atol=1e-12)
    fwd = around.c2w[:, :3, 2]
    assert fwd[1] @ x > 0  # turning right
    yaw = np.rad2deg(np.arctan2(fwd @ x, fwd @ z))
    assert np.allclose(np.diff(np.unwrap(np.deg2rad(yaw))), np.deg2rad(30))  # all around, 30 degrees apart
    np.testing.assert_allclose(fwd @ frame.up, fwd[0] @ frame.up, atol=1e-9)  # the horizon stays level


def test_zoom_and_spiral():
    frame = start_frame()
    z = tr.zoom(frame, 5, amount=4.0)
    np.testing.assert_allclose(z.focal_scale, [1, 2 ** 0.5, 2, 2 ** 1.5, 4])
    K = z.intrinsics(INTR)
    assert K[-1, 0, 0] == pytest.approx(4 * INTR.fx) and K[-1, 0, 2] == INTR.cx
    np.testing.assert_allclose(z.c2w, np.broadcast_to(frame.c2w, (5, 4, 4)))
    s = tr.spiral(frame, 17, amount=0.2, turns=2)
    off = s.c2w[:, :3, 3] - frame.eye
    r = np.linalg.norm(off, axis=1)
    assert np.all(np.diff(r) > 0) and r[-1] == pytest.approx(0.2 * frame.distance)
    np.testing.assert_allclose(off @ frame.c2w[:3, 2], 0, atol=1e-9)  # in the image plane
    for T in s.c2w:  # re-aimed: the start's look at the target is kept
        np.testing.assert_allclose(T[:3, 2], (frame.target - T[:3, 3]) / np.linalg.norm(frame.target - T[:3, 3]),
                                   atol=1e-9)


def test_preset_options_are_checked():
    frame = start_frame()
    with pytest.raises(ValueError, match="unknown trajectory preset 'circle'"):
        tr.preset_trajectory("circle", frame, 3)
    with pytest.raises(ValueError, match="sized by degrees"):
        tr.preset_trajectory("orbit", frame, 3, amount=0.5)
    with pytest.raises(ValueError, match="sized by amount"):
        tr.preset_trajectory("dolly", frame, 3, degrees=10)
    assert np.rad2deg(np.arccos(tr.preset_trajectory("pan", frame, 3, degrees=10).c2w[-1, :3, 2]
                                @ frame.c2w[:3, 2])) == pytest.approx(10)
    with pytest.raises(ValueError, match="at least 1 frame"):
        tr.orbit(frame, 0)


def test_framing_a_point_set_fits_its_robust_box():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-1, -0.5, 3], [1, 0.5, 5], (500, 3))
    op = np.full(500, 0.9)
    pts[:5] = [100.0, 100.0, 100.0]  # strays
    pts[5:60] = rng.uniform(-50, 50, (55, 3))
    op[5:60] = 0.01  # and near-transparent floaters
    op[:5] = 0.9
    lo, hi = tr.robust_bounds(pts, op)
    assert np.all(lo > [-1.1, -0.6, 2.9]) and np.all(hi < [1.1, 0.6, 5.1])
    lo_all, hi_all = tr.robust_bounds(pts, None)
    assert (hi_all - lo_all).max() > 10  # the floaters count without opacities
    few = np.full(500, 0.01)
    few[:3] = 0.9  # too few opaque ones: all points count
    np.testing.assert_allclose(tr.robust_bounds(pts, few), (lo_all, hi_all))
    frame = tr.frame_bounds(lo, hi, INTR)
    np.testing.assert_allclose(frame.target, (lo + hi) / 2)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    uv, zc = project(corners, frame.c2w, INTR.K)
    assert (zc > 0).all() and (uv >= 0).all() and (uv <= 32).all()  # the whole box is in view
    assert frame.c2w[:3, 2] @ [0, 0, 1] == pytest.approx(1)  # looks horizontally, along +z
    r = np.linalg.norm(hi - lo) / 2
    assert frame.distance == pytest.approx(r / np.sin(np.deg2rad(30)))  # just fits: no wasted frame
    z_up = tr.frame_bounds(lo, hi, INTR, up=(0.0, 0.0, 1.0))
    assert z_up.c2w[:3, 1] @ [0, 0, 1] == pytest.approx(-1)  # image up is +z
    with pytest.raises(ValueError, match="no finite"):
        tr.robust_bounds(np.full((3, 3), np.nan))


# --------------------------------------------------------------------------------------------------
# Camera files
# --------------------------------------------------------------------------------------------------
def known_poses() -> np.ndarray:
    return np.stack([look_at(np.array([0.3 * i, -0.2, -3.0]), np.array([0.0, 0.0, 1.0])) for i in range(3)])


def test_re10k_file_round_trips_to_its_poses(tmp_path):
    c2w = known_poses()
    lines = ["https://www.youtube.com/watch?v=abc"]
    for i, T in enumerate(c2w):
        w2c = invert_pose(T)[:3].reshape(-1)
        lines.append(" ".join([str(1000 * (i + 1)), *(repr(float(v)) for v in [0.5, 0.8, 0.5, 0.5, 0.0, 0.0, *w2c])]))
    path = tmp_path / "seq.txt"
    path.write_text("\n".join(lines) + "\n")
    cams = tr.read_camera_file(path)
    assert cams.format == "re10k" and len(cams) == 3 and cams.size is None
    np.testing.assert_allclose(cams.c2w, c2w, atol=1e-12)
    K = cams.intrinsics_at(64, 32)
    np.testing.assert_allclose(K[0], [[32, 0, 32], [0, 25.6, 16], [0, 0, 1]])
    bad = tmp_path / "bad.txt"
    bad.write_text("\n".join([*lines[:2], lines[2].rsplit(" ", 1)[0]]) + "\n")
    with pytest.raises(ValueError, match=r"bad.txt:3: expected 19 numbers"):
        tr.read_camera_file(bad)


def test_transforms_json_flips_opengl_to_opencv(tmp_path):
    c2w_cv = known_poses()
    gl = c2w_cv @ np.diag([1.0, -1.0, -1.0, 1.0])
    doc = {"w": 64, "h": 48, "fl_x": 50.0, "fl_y": 52.0, "cx": 31.0, "cy": 25.0,
           "frames": [{"file_path": f"images/frame_{i + 1:05d}.png", "transform_matrix": gl[i].tolist()}
                      for i in range(3)]}
    doc["frames"][2]["fl_x"] = 60.0  # per-frame intrinsics win
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(doc))
    cams = tr.read_camera_file(path)
    assert cams.format == "transforms" and cams.size == (64, 48)
    np.testing.assert_allclose(cams.c2w, c2w_cv, atol=1e-12)
    # a point in front of the OpenGL camera (its -z) is in front of the OpenCV one (+z)
    p_world = gl[0] @ np.array([0.0, 0.0, -2.0, 1.0])
    assert (invert_pose(cams.c2w[0]) @ p_world)[2] == pytest.approx(2.0)
    np.testing.assert_allclose(cams.K[0], [[50, 0, 31], [0, 52, 25], [0, 0, 1]])
    assert cams.K[2, 0, 0] == 60.0
    np.testing.assert_allclose(cams.intrinsics_at(32, 24)[0], [[25, 0, 15.5], [0, 26, 12.5], [0, 0, 1]])
    del doc["frames"][1]["transform_matrix"]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"frames\[1\]: needs 'file_path' and 'transform_matrix'"):
        tr.read_camera_file(path)


def test_camera_path_json_reads_the_render_path(tmp_path):
    c2w_cv = known_poses()
    gl = c2w_cv @ np.diag([1.0, -1.0, -1.0, 1.0])
    doc = {"camera_type": "perspective", "render_width": 40, "render_height": 30, "fps": 24,
           "camera_path": [{"camera_to_world": gl[i].reshape(-1).tolist(), "fov": 90.0, "aspect": 4 / 3}
                           for i in range(3)]}
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps(doc))
    cams = tr.read_camera_file(path)
    assert cams.format == "camera_path" and cams.size == (40, 30)
    np.testing.assert_allclose(cams.c2w, c2w_cv, atol=1e-12)
    np.testing.assert_allclose(cams.K[1], [[15, 0, 20], [0, 15, 15], [0, 0, 1]], atol=1e-12)  # vertical fov 90
    del doc["camera_path"][2]["fov"]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"camera_path.json: camera_path\[2\]: missing field 'fov'"):
        tr.read_camera_file(path)
    doc["camera_path"][2] = {"camera_to_world": [1.0] * 15, "fov": 50}
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"camera_path\[2\]\.camera_to_world: expected 16"):
        tr.read_camera_file(path)
    doc["camera_path"][2] = {"camera_to_world": np.diag([2.0, 2, 2, 1]).reshape(-1).tolist(), "fov": 50}
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"camera_path\[2\]\.camera_to_world: the 3x3 block is not a rotation"):
        tr.read_camera_file(path)
    del doc["render_height"]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="missing field 'render_height'"):
        tr.read_camera_file(path)


def test_camera_file_detection_errors(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        tr.read_camera_file(tmp_path / "nope.json")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"poses": []}))
    with pytest.raises(ValueError, match=r"neither a nerfstudio camera_path.json.*\['poses'\]"):
        tr.read_camera_file(other)
    broken = tmp_path / "broken.json"
    broken.write_text("{\"frames\": [")
    with pytest.raises(ValueError, match="broken.json: not valid JSON"):
        tr.read_camera_file(broken)
    (tmp_path / "x.npz").write_bytes(b"")
    with pytest.raises(ValueError, match="unknown camera file type '.npz'"):
        tr.read_camera_file(tmp_path / "x.npz")


def test_frame_checks_its_inputs():
    with pytest.raises(ValueError, match="sits on its target"):
        tr.Frame(np.eye(4), np.zeros(3))
    f = tr.Frame(make_pose(np.eye(3), np.zeros(3)), np.array([0, 0, 2.0]))
    np.testing.assert_allclose(f.up, [0, -1, 0]) and f.distance == 2.0

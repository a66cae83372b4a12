"""Camera maths: conventions, interpolation and Plücker rays (property tests)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from navcrafter.models.camera import cameras as C

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
unit_quat = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1).map(
    lambda q: np.array(q) / np.linalg.norm(q))


def random_pose(q, t) -> np.ndarray:
    return C.make_pose(C.quat_wxyz_to_matrix(q), t)


@given(unit_quat, vec3)
def test_invert_pose_is_inverse(q, t):
    T = random_pose(q, t)
    np.testing.assert_allclose(C.invert_pose(T) @ T, np.eye(4), atol=1e-9)


@given(unit_quat)
def test_quaternion_roundtrip(q):
    R = C.quat_wxyz_to_matrix(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    q2 = C.matrix_to_quat(R)
    assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-9


@given(vec3, vec3)
def test_look_at_points_camera_at_target(eye, target):
    if np.linalg.norm(target - eye) < 1e-3:
        return
    d = (target - eye) / np.linalg.norm(target - eye)
    if abs(d @ np.array([0.0, -1.0, 0.0])) > 0.999:  # ill-conditioned; exact case tested below
        return
    T = C.look_at(eye, target)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], d, atol=1e-9)  # +z forward
    assert R[:, 1] @ np.array([0.0, -1.0, 0.0]) <= 1e-9  # +y (image down) points away from world up
    K = C.Intrinsics.from_fov(60, 64, 48).K
    uv, z = C.project(target[None], T, K)
    np.testing.assert_allclose(uv[0], [32, 24], atol=1e-6)  # the target projects to the image centre
    assert z[0] == pytest.approx(np.linalg.norm(target - eye))


def test_look_at_identity_for_default_frame_and_rejects_degenerate():
    np.testing.assert_allclose(C.look_at(np.zeros(3), np.array([0, 0, 5.0])), np.eye(4), atol=1e-12)
    with pytest.raises(ValueError, match="parallel"):
        C.look_at(np.zeros(3), np.array([0.0, -3.0, 0.0]))
    with pytest.raises(ValueError, match="coincide"):
        C.look_at(np.ones(3), np.ones(3))


@given(unit_quat, unit_quat)
def test_slerp_endpoints_exact_and_constant_speed(q0, q1):
    out = C.slerp(q0, q1, np.linspace(0, 1, 9))
    assert np.array_equal(out[0], q0)
    assert np.array_equal(out[-1], q1) or np.array_equal(out[-1], -q1)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    R = C.quat_wxyz_to_matrix(out)
    steps = C.rotation_angle_deg(R[:-1], R[1:])
    np.testing.assert_allclose(steps, steps.mean(), atol=1e-5)


@given(unit_quat, vec3, unit_quat, vec3)
@settings(max_examples=50)
def test_interpolate_poses_endpoints_bit_exact(qa, ta, qb, tb):
    a, b = random_pose(qa, ta), random_pose(qb, tb)
    traj = C.interpolate_poses(a, b, 7)
    assert traj.shape == (7, 4, 4)
    assert np.array_equal(traj[0], a) and np.array_equal(traj[-1], b)
    np.testing.assert_allclose(traj[3, :3, 3], (ta + tb) / 2, atol=1e-9)  # straight line without centre


def test_interpolate_on_arc_keeps_radius():
    centre = np.array([0.0, 0.0, 4.0])
    a = C.look_at(np.zeros(3), centre)
    eye_b = centre + C.axis_angle_to_matrix([0, 1, 0], np.deg2rad(60)) @ (np.zeros(3) - centre)
    b = C.look_at(eye_b, centre)
    traj = C.interpolate_poses(a, b, 11, centre=centre)
    radii = np.linalg.norm(traj[:, :3, 3] - centre, axis=1)
    np.testing.assert_allclose(radii, 4.0, atol=1e-9)
    # every interpolated camera still looks at the centre (both ends do, and the motion is one rotation)
    for T in traj:
        fwd = T[:3, 2]
        to_c = (centre - T[:3, 3]) / np.linalg.norm(centre - T[:3, 3])
        assert fwd @ to_c > 1 - 1e-9


def test_pixel_centres_and_unproject_roundtrip():
    K = C.Intrinsics(50.0, 55.0, 16.0, 12.0, 32, 24)
    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 5, (24, 32))
    T = C.look_at(np.array([0.3, -0.2, 0.1]), np.array([1.0, 0.5, 4.0]))
    pts, idx = C.unproject_depth(depth, T, K.K)
    uv, z = C.project(pts, T, K.K)
    i, j = np.unravel_index(idx, depth.shape)
    np.testing.assert_allclose(uv[:, 0], j + 0.5, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], i + 0.5, atol=1e-9)
    np.testing.assert_allclose(z, depth.reshape(-1)[idx], atol=1e-9)


def test_intrinsics_crop_resize_consistent():
    K = C.Intrinsics.from_fov(70, 640, 480)
    assert K.fov_x_deg == pytest.approx(70)
    cropped = K.crop(80, 0, 480, 480).resize(256, 256)
    # the principal point stays centred and the horizontal fov shrinks with the crop
    assert (cropped.cx, cropped.cy) == pytest.approx((128, 128))
    assert cropped.fov_x_deg < 70
    with pytest.raises(ValueError):
        C.Intrinsics(-1, 1, 0, 0, 10, 10)


@given(unit_quat, vec3, st.sampled_from(["paper", "ray"]))
@settings(max_examples=40)
def test_plucker_shape_and_line_constraints(q, t, convention):
    T = random_pose(q, t)
    K = C.Intrinsics.from_fov(60, 8, 6).K
    p = C.plucker_rays(np.stack([T, T]), K, 6, 8, convention=convention)
    assert p.shape == (2, 6, 8, 6) and p.dtype == np.float32
    m, d = p[..., :3].astype(np.float64), p[..., 3:].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose((m * d).sum(-1), 0.0, atol=1e-4 * max(1, np.linalg.norm(t)))
    np.testing.assert_allclose(m, np.cross(t, d), atol=1e-4 * max(1, np.linalg.norm(t)))


def test_plucker_matches_paper_formula_and_ray_direction():
    T = C.look_at(np.array([1.0, -0.5, 2.0]), np.array([0.0, 0.0, 6.0]))
    K = C.Intrinsics.from_fov(50, 5, 4).K
    R, t = T[:3, :3], T[:3, 3]
    u, v = 2.5, 1.5  # centre of pixel (row 1, col 2)
    x = np.linalg.inv(K) @ np.array([u, v, 1.0])
    d_paper = R @ x + t
    d_paper /= np.linalg.norm(d_paper)
    d_ray = R @ x / np.linalg.norm(R @ x)
    paper = C.plucker_rays(T, K, 4, 5, "paper")[1, 2].astype(np.float64)
    ray = C.plucker_rays(T, K, 4, 5, "ray")[1, 2].astype(np.float64)
    np.testing.assert_allclose(paper, np.concatenate([np.cross(t, d_paper), d_paper]), atol=1e-6)
    np.testing.assert_allclose(ray, np.concatenate([np.cross(t, d_ray), d_ray]), atol=1e-6)
    # the "ray" convention is a true Plücker line: every point t + s d of the viewing ray has moment m
    X = t + 3.7 * d_ray
    np.testing.assert_allclose(np.cross(X, d_ray), ray[:3], atol=1e-5)
    # both agree for a camera at the origin
    T0 = T.copy()
    T0[:3, 3] = 0
    np.testing.assert_allclose(C.plucker_rays(T0, K, 4, 5, "paper"), C.plucker_rays(T0, K, 4, 5, "ray"))
    with pytest.raises(ValueError):
        C.plucker_rays(T, K, 4, 5, "bogus")


def _clip(rng, n=5, far=0.0):
    """``n`` random poses around ``(far, 0, 0)``."""
    return np.stack([random_pose(q / np.linalg.norm(q), np.array([far, 0.0, 0.0]) + rng.normal(size=3))
                     for q in rng.normal(size=(n, 4))])


def test_relative_poses_frame0_identity_and_recorded_scale():
    rng = np.random.default_rng(3)
    clip = _clip(rng)
    rel, scale = C.relative_poses(clip)
    np.testing.assert_allclose(rel[0], np.eye(4), atol=1e-12)
    raw = np.einsum("ij,tjk->tik", C.invert_pose(clip[0]), clip)
    assert scale == pytest.approx(np.linalg.norm(raw[:, :3, 3], axis=-1).max())
    assert np.linalg.norm(rel[:, :3, 3], axis=-1).max() == pytest.approx(1.0)
    np.testing.assert_allclose(rel[:, :3, :3], raw[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(rel[:, :3, 3] * scale, raw[:, :3, 3], atol=1e-12)
    # a pure rotation (no translation) keeps scale 1
    turn = np.stack([C.make_pose(C.axis_angle_to_matrix([0, 1, 0], a), [2.0, 0.0, 1.0]) for a in (0.0, 0.3)])
    assert C.relative_poses(turn)[1] == 1.0
    # an explicit origin and scale express other poses in the clip's frame
    extra = _clip(rng, n=2)
    got, s = C.relative_poses(extra, origin=clip[0], scale=scale)
    assert s == scale
    want = np.einsum("ij,tjk->tik", C.invert_pose(clip[0]), extra)
    want[:, :3, 3] /= scale
    np.testing.assert_allclose(got, want, atol=1e-12)
    with pytest.raises(ValueError, match="scale"):
        C.relative_poses(clip, scale=0.0)


def test_relative_is_the_default_and_the_true_line_of_the_relative_pose():
    rng = np.random.default_rng(4)
    clip = _clip(rng, far=10.0)
    K = C.Intrinsics.from_fov(60, 8, 6).K
    rel, _ = C.relative_poses(clip)
    got = C.plucker_rays(clip, K, 6, 8)  # default convention
    np.testing.assert_array_equal(got, C.plucker_rays(clip, K, 6, 8, "relative"))
    np.testing.assert_allclose(got, C.plucker_rays(rel, K, 6, 8, "ray"), atol=1e-6)
    m, d = got[..., :3].astype(np.float64), got[..., 3:].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(m, np.cross(rel[:, None, None, :3, 3], d), atol=1e-5)
    # frame 0 is the identity camera: zero moment, directions K^-1 [u, v, 1] normalised
    assert np.abs(got[0, ..., :3]).max() == 0
    # invariant to a rigid motion and a rescaling of the whole clip (world frame, units)
    G = random_pose(np.array([0.3, -0.5, 0.7, 0.2]) / np.linalg.norm([0.3, -0.5, 0.7, 0.2]), [4.0, -7.0, 2.0])
    moved = np.einsum("ij,tjk->tik", G, clip)
    moved[:, :3, 3] *= 3.0
    np.testing.assert_allclose(C.plucker_rays(moved, K, 6, 8), got, atol=1e-5)
    assert np.abs(C.plucker_rays(moved, K, 6, 8, "paper") - C.plucker_rays(clip, K, 6, 8, "paper")).max() > 0.1
    with pytest.raises(ValueError, match="origin/scale only apply"):
        C.plucker_rays(clip, K, 6, 8, "ray", scale=2.0)


def test_relative_embedding_sees_a_yaw_far_from_the_origin_that_the_paper_form_hides():
    """The defect of the literal form: with |t| = 10 the direction channels d = normalise(RK^-1[u,v,1] + t) all point
    along t, so their spread over the image collapses and a 10° yaw hardly moves them."""
    K = C.Intrinsics.from_fov(60, 32, 24).K
    start = C.make_pose(np.eye(3), [10.0, 0.0, 0.0])  # 10 units from the world origin, looking along +z
    turned = C.make_pose(C.axis_angle_to_matrix([0, 1, 0], np.deg2rad(10)), [10.0, 0.0, 0.0])
    clip = np.stack([start, turned])

    def change(convention, channels=slice(None)):
        e = C.plucker_rays(clip, K, 24, 32, convention).astype(np.float64)[..., channels]
        return float(np.linalg.norm(e[1] - e[0], axis=-1).mean())

    rel, paper = change("relative"), change("paper")
    assert rel > 3 * paper  # the whole embedding
    assert change("relative", slice(3, 6)) > 20 * change("paper", slice(3, 6))  # the direction channels
    e = C.plucker_rays(clip, K, 24, 32, "relative").astype(np.float64)  # d turns by exactly the yaw, m stays 0
    np.testing.assert_allclose(e[1, ..., 3:], e[0, ..., 3:] @ turned[:3, :3].T, atol=1e-6)
    assert np.abs(e[..., :3]).max() == 0
    spread = {c: C.plucker_rays(start, K, 24, 32, c)[..., 3:].reshape(-1, 3).std(0).sum() for c in ("relative",
                                                                                                   "paper")}
    assert spread["paper"] < 0.1 * spread["relative"]


def test_clip_relative_rays_put_extra_poses_in_the_clip_frame():
    rng = np.random.default_rng(5)
    clip = _clip(rng, far=10.0)
    K = C.Intrinsics.from_fov(60, 8, 6).K
    for convention in ("relative", "ray", "paper"):
        rays = C.plucker_rays(clip, K, 6, 8, convention)
        # an extra pose equal to one of the clip's cameras gets that camera's rays
        np.testing.assert_allclose(C.clip_relative_rays(clip, clip[3], K, 6, 8, convention), rays[3:4], atol=1e-6)
    photo = random_pose(np.array([1.0, 0.0, 0.0, 0.0]), [20.0, 0.0, 0.0])  # outside the clip
    rel, scale = C.relative_poses(clip)
    want_pose = C.invert_pose(clip[0]) @ photo
    want_pose[:3, 3] /= scale
    got = C.clip_relative_rays(clip, photo[None], K, 6, 8)
    np.testing.assert_allclose(got, C.plucker_rays(want_pose[None], K, 6, 8, "ray"), atol=1e-5)
    # not its own one-pose clip (that would put it at the origin)
    assert np.abs(got - C.plucker_rays(photo[None], K, 6, 8, "relative")).max() > 0.1


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 3))
    R = C.quat_wxyz_to_matrix(np.array([0.9, 0.1, -0.3, 0.2]))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    s, R2, t2 = C.umeyama(src, dst)
    assert s == pytest.approx(2.5)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, [1.0, -2.0, 0.5], atol=1e-9)

"""CameraCtrl-style pose errors (models/metrics/pose.py) and the metric on a video COLMAP cannot reconstruct. The
recovery itself on simulated video: tests/models/reconstruction/test_sfm.py."""

from __future__ import annotations

import numpy as np
import pytest

from navcrafter.models.camera.cameras import Intrinsics, axis_angle_to_matrix, make_pose
from navcrafter.models.metrics.pose import camera_guidance_precision, pose_errors

THREADS = 2


def random_trajectory(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        R = axis_angle_to_matrix(rng.normal(size=3), rng.uniform(0, np.pi))
        out.append(make_pose(R, rng.normal(size=3) * (1 + i)))
    return np.array(out)


def similarity(c2w: np.ndarray, R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    """The same cameras in a world moved by ``X -> s R X + t`` (rotations change by R, centres fully)."""
    out = c2w.copy()
    out[:, :3, :3] = R @ c2w[:, :3, :3]
    out[:, :3, 3] = s * c2w[:, :3, 3] @ R.T + t
    return out


@pytest.mark.parametrize("scale", ["lstsq", "farthest"])
def test_identical_trajectories_have_zero_error(scale):
    gt = random_trajectory(10)
    e = pose_errors(gt, gt.copy(), scale=scale)
    assert e["n_registered"] == e["n_frames"] == 10 and e["ref_index"] == 0
    for key in ("R_err_deg_sum", "R_err_deg_mean", "R_err_rad_sum", "T_err_sum", "T_err_mean"):
        assert e[key] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("scale", ["lstsq", "farthest"])
def test_errors_are_invariant_to_a_similarity_of_the_estimate(scale):
    gt = random_trajectory(12, seed=1)
    R = axis_angle_to_matrix(np.array([0.3, -1.0, 0.5]), 2.1)
    est = similarity(gt, R, np.array([5.0, -3.0, 10.0]), 0.037)  # COLMAP's arbitrary frame and scale
    e = pose_errors(est, gt, scale=scale)
    assert e["R_err_deg_sum"] == pytest.approx(0.0, abs=1e-5)
    assert e["T_err_sum"] == pytest.approx(0.0, abs=1e-6)
    if scale == "lstsq":
        assert e["scale"] == pytest.approx(1 / 0.037)
    # unregistered frames (including the first) are excluded; the first registered frame is the reference
    registered = np.ones(12, dtype=bool)
    registered[[0, 5]] = False
    est[5] = np.nan
    e = pose_errors(est, gt, registered, scale=scale)
    assert e["n_registered"] == 10 and e["n_frames"] == 12 and e["ref_index"] == 1
    assert np.isnan(e["R_err_deg"][0]) and np.isnan(e["T_err"][5])
    assert e["R_err_deg_sum"] == pytest.approx(0.0, abs=1e-5) and e["T_err_sum"] == pytest.approx(0.0, abs=1e-6)


def test_known_rotation_offset_on_one_frame():
    gt = random_trajectory(8, seed=2)
    est = gt.copy()
    est[3] = est[3] @ make_pose(axis_angle_to_matrix(np.array([1.0, 2.0, -0.5]), np.deg2rad(10.0)), np.zeros(3))
    e = pose_errors(est, gt)
    assert e["R_err_deg"][3] == pytest.approx(10.0, abs=1e-6)
    assert e["R_err_deg_sum"] == pytest.approx(10.0, abs=1e-6)
    assert e["R_err_deg_mean"] == pytest.approx(10.0 / 7, abs=1e-6)  # over the 7 non-reference frames
    assert e["R_err_rad_sum"] == pytest.approx(np.deg2rad(10.0), abs=1e-8)
    assert e["T_err_sum"] == pytest.approx(0.0, abs=1e-6)  # rotating a camera about its centre moves nothing


def test_too_few_registered_frames_give_nan_and_a_reason():
    gt = random_trajectory(4)
    e = pose_errors(gt, gt, np.array([False, True, False, False]))
    assert e["n_registered"] == 1 and np.isnan(e["R_err_deg_sum"]) and np.isnan(e["T_err_mean"])
    assert "at least 2" in e["reason"]


def test_recovery_failure_is_a_result(tmp_path):
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 255, (96, 96, 3), dtype=np.uint8) for _ in range(5)]
    out = camera_guidance_precision(noise, random_trajectory(5), Intrinsics.from_fov(60, 96, 96).K, tmp_path,
                                    num_threads=THREADS)
    assert out["n_registered"] == 0 and out["recovery"]["n_registered"] == 0
    assert "no reconstruction" in out["reason"] and np.isnan(out["R_err_deg_sum"])


def test_rad_mean_is_the_deg_mean_in_radians():
    gt = random_trajectory(6, seed=3)
    est = gt.copy()
    est[2] = est[2] @ make_pose(axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.deg2rad(6.0)), np.zeros(3))
    e = pose_errors(est, gt)
    assert e["R_err_rad_mean"] == pytest.approx(np.deg2rad(e["R_err_deg_mean"]))
    assert e["R_err_rad_mean"] == pytest.approx(np.deg2rad(6.0) / 5)

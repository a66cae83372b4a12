"""Lifting synthesized views into the scene cloud: scale recovery, ICP refinement, fusion on true surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from navcrafter.models.camera.cameras import Intrinsics, axis_angle_to_matrix
from navcrafter.models.reconstruction.lifting import (
    AlignmentError,
    align_scale,
    lift_prediction,
    pose_deviation,
    refine_view,
)
from navcrafter.models.reconstruction.pointcloud import views_to_cloud, voxel_fuse
from navcrafter.models.roles import GeometryPrediction
from navcrafter.models.simulation.backend import SimulationTruth, simulation_backend
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.scenes import generate_scene
from navcrafter.schemas.config import SimulationConfig

H, W = 96, 128


def _world(kind="room", seed=0):
    scene = generate_scene(kind, seed)
    K = Intrinsics.from_fov(scene.camera_fov_x_deg, W, H)
    record = {"scene": scene.spec, "photo_c2w": scene.camera_c2w.tolist(), "work_intrinsics": K.to_dict()}
    truth = SimulationTruth.from_record(record)
    cfg = SimulationConfig(preset="perfect", depth_noise=0.003, pose_rot_deg=0.0, pose_trans=0.0, focal_noise=0.0)
    backend = simulation_backend(truth, cfg)
    image = render(scene, truth.photo_c2w, K).rgb
    first = backend.geometry.predict(image[None], seed=1, hint_c2w=np.eye(4)[None])
    truth.world_scale = first.extras["simulation_scale"]
    cloud = voxel_fuse(views_to_cloud(image[None], first.depth, first.confidence, np.eye(4)[None], first.K,
                                      0.5, 2), 0.02)
    return truth, backend, image, first, cloud


def _pose(truth, yaw_deg, right_m):
    """World pose: turned by yaw and moved right by ``right_m`` metres (world units = metres × scale)."""
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.deg2rad(yaw_deg))
    T[0, 3] = right_m * truth.world_scale
    return T


def _median_mm(truth, points):
    return 1000 * float(np.median(truth.scene.distance(truth.gt_points(points))))


def test_scale_recovery_from_the_reference_view():
    rng = np.random.default_rng(0)
    ref = rng.uniform(1, 5, (40, 50)).astype(np.float32)
    conf = np.ones_like(ref)
    pred = ref / 3.7 * (1 + rng.normal(0, 0.01, ref.shape))
    pred[:5] = 100.0  # outliers barely move a median
    assert align_scale(ref, conf, pred.astype(np.float32), conf, 0.5) == pytest.approx(3.7, rel=0.01)
    with pytest.raises(AlignmentError, match="trusted depth"):
        align_scale(ref, np.zeros_like(conf), pred, conf, 0.5)


@pytest.mark.parametrize("wrong_scale", [0.25, 6.0])
def test_two_views_with_a_wrong_prediction_scale_fuse_onto_the_true_surfaces(wrong_scale):
    truth, backend, image, first, cloud = _world()
    base_mm = _median_mm(truth, cloud.points)
    poses = [_pose(truth, 12.0, 0.3), _pose(truth, -15.0, -0.4)]
    frames = np.stack([render(truth.scene, truth.gt_pose(p), truth.work_intrinsics).rgb for p in poses])
    pred = backend.geometry.predict(np.concatenate([image[None], frames]), seed=5,
                                    hint_c2w=np.stack([np.eye(4), *poses]))
    # a deliberately wrong scale on top of the call's own arbitrary one
    pred = GeometryPrediction(c2w=pred.c2w.copy(), K=pred.K, depth=pred.depth * wrong_scale,
                              confidence=pred.confidence)
    pred.c2w[:, :3, 3] *= wrong_scale
    out = lift_prediction(frames, pred, first.depth[0], first.confidence[0], cloud, confidence_threshold=0.5,
                          pixel_stride=2, max_depth=50.0, voxel_size=0.02)
    new_mm = _median_mm(truth, out.new.points)
    print(f"wrong scale x{wrong_scale}: first cloud {base_mm:.1f} mm, new views {new_mm:.1f} mm, "
          f"fused {_median_mm(truth, out.cloud.points):.1f} mm to the true surface")
    assert len(out.new) > 1000
    assert new_mm < 15.0  # the wrong scale is gone: points lie on the true surfaces
    # and cameras landed where the planner asked for them
    dev = pose_deviation(out.c2w, np.stack(poses))
    assert dev["pose_dev_trans"] < 0.02 * truth.world_scale and dev["pose_dev_rot_deg"] < 0.5
    # without recovering the scale the same points would be far off
    unscaled = views_to_cloud(frames, pred.depth[1:], pred.confidence[1:], pred.c2w[1:], pred.K[1:], 0.5, 2)
    assert _median_mm(truth, unscaled.points) > 5 * new_mm


def test_icp_removes_a_view_pose_error_and_refuses_large_corrections():
    truth, backend, image, first, cloud = _world()
    pose = _pose(truth, 8.0, 0.2)
    frame = render(truth.scene, truth.gt_pose(pose), truth.work_intrinsics).rgb
    pred = backend.geometry.predict(np.stack([image, frame]), seed=7, hint_c2w=np.stack([np.eye(4), pose]))
    s = pred.extras["simulation_scale"]
    bad = pred.c2w.copy()  # a pose error of 1.5 degrees and 4 cm, as a geometry model makes
    bad[1, :3, :3] = axis_angle_to_matrix(np.array([1.0, 0.3, 0.0]), np.deg2rad(1.5)) @ bad[1, :3, :3]
    bad[1, :3, 3] += np.array([0.04, -0.02, 0.0]) * s
    noisy = GeometryPrediction(c2w=bad, K=pred.K, depth=pred.depth, confidence=pred.confidence)
    kw = dict(confidence_threshold=0.5, pixel_stride=2, max_depth=50.0, voxel_size=0.02)
    plain = lift_prediction(frame[None], noisy, first.depth[0], first.confidence[0], cloud, icp=False, **kw)
    refined = lift_prediction(frame[None], noisy, first.depth[0], first.confidence[0], cloud, icp=True, **kw)
    plain_mm, refined_mm = _median_mm(truth, plain.new.points), _median_mm(truth, refined.new.points)
    print(f"pose error: {plain_mm:.1f} mm without ICP, {refined_mm:.1f} mm with ICP")
    assert refined.refinements[0].accepted
    assert refined_mm < 0.6 * plain_mm
    # a view displaced far beyond a model's pose error is left alone
    far = refined.new.points + np.array([0.0, 0.0, 0.5]) * truth.world_scale
    import open3d as o3d

    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points.astype(np.float64)))
    target.estimate_normals()
    T, info = refine_view(far, target, 0.03 * float(np.median(first.depth[0][first.depth[0] > 0])))
    assert not info.accepted and np.array_equal(T, np.eye(4))

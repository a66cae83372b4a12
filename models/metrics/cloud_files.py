"""Point-cloud files scored against a reference cloud (``navcrafter evaluate-cloud``): reading any cloud or mesh file
Open3D reads, ICP alignment, and the cloud metrics of ``models.metrics.cloud`` before and after it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from navcrafter.models.metrics.cloud import cloud_metrics

ICP_DISTANCE_FACTOR = 5.0  # evaluate-cloud: default ICP max correspondence distance, in thresholds
MESH_POINTS = 1_000_000  # evaluate-cloud: points sampled uniformly on a mesh file


class CloudFileError(ValueError):
    """A cloud file that cannot be read, or a bad option; the message names it and the fix."""


@dataclass(frozen=True)
class LoadedCloud:
    path: str
    points: np.ndarray  # [N, 3] float64
    from_mesh: bool  # sampled uniformly on a mesh's triangles


def read_points(path: str | Path, mesh_points: int = MESH_POINTS, seed: int = 0) -> LoadedCloud:
    """A point cloud file (any format Open3D reads: .ply, .pcd, .xyz, .pts, ...); a file with triangles is a mesh,
    sampled uniformly (``mesh_points`` points, area-weighted, seeded). Non-finite points are dropped."""
    p = Path(path)
    if not p.is_file():
        raise CloudFileError(f"{p}: no such file; give a point cloud or mesh file (.ply, .pcd, .xyz, ...)")
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    from_mesh = False
    pts = np.zeros((0, 3))
    try:
        mesh = o3d.io.read_triangle_mesh(str(p))
        if len(mesh.triangles) > 0:
            o3d.utility.random.seed(seed)
            pts = np.asarray(mesh.sample_points_uniformly(number_of_points=int(mesh_points)).points)
            from_mesh = True
        else:
            pts = np.asarray(o3d.io.read_point_cloud(str(p)).points)
    except (RuntimeError, ValueError, OSError) as exc:
        raise CloudFileError(f"{p}: cannot be read as a point cloud or mesh ({exc})") from None
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise CloudFileError(f"{p}: no points could be read (empty, or not a point cloud / mesh file that "
                               "Open3D reads: .ply, .pcd, .xyz, .xyzn, .xyzrgb, .pts, .obj, .stl, ...)")
    return LoadedCloud(str(p), pts, from_mesh)


def icp_align(points: np.ndarray, reference: np.ndarray, max_distance: float, max_iterations: int = 100):
    """Open3D's point-to-point ICP of ``points`` onto ``reference``, initialised by the identity; returns the 4x4
    transform and ICP's fitness / inlier RMSE."""
    src, dst = o3d.geometry.PointCloud(), o3d.geometry.PointCloud()
    src.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    dst.points = o3d.utility.Vector3dVector(np.asarray(reference, dtype=np.float64))
    reg = o3d.pipelines.registration
    res = reg.registration_icp(src, dst, float(max_distance), np.eye(4), reg.TransformationEstimationPointToPoint(),
                               reg.ICPConvergenceCriteria(max_iteration=int(max_iterations)))
    return np.asarray(res.transformation, dtype=np.float64), {"fitness": float(res.fitness),
                                                             "inlier_rmse": float(res.inlier_rmse)}


def evaluate_cloud_files(pred: str | Path, gt: str | Path, threshold: float = 0.02, align: bool = False,
                         icp_distance: float | None = None, mesh_points: int = MESH_POINTS) -> dict:
    """Precision, recall (= coverage), F-score and noise ratio of the cloud ``pred`` against the reference ``gt``
    (``models.metrics.cloud.cloud_metrics``), and with ``align`` the same after ICP-aligning ``pred`` onto ``gt``
    (max correspondence distance ``icp_distance``, default ``ICP_DISTANCE_FACTOR`` x ``threshold``)."""
    if not threshold > 0:
        raise CloudFileError(f"--threshold must be positive, got {threshold}")
    P, G = read_points(pred, mesh_points), read_points(gt, mesh_points)
    doc: dict = {"pred": P.path, "gt": G.path, "threshold": float(threshold),
                 "pred_sampled_from_mesh": P.from_mesh, "gt_sampled_from_mesh": G.from_mesh,
                 "n_pred": len(P.points), "n_gt": len(G.points),
                 "unaligned": cloud_metrics(P.points, G.points, threshold)}
    if align:
        dist = ICP_DISTANCE_FACTOR * threshold if icp_distance is None else float(icp_distance)
        if not dist > 0:
            raise CloudFileError(f"--icp-distance must be positive, got {icp_distance}")
        T, info = icp_align(P.points, G.points, dist)
        moved = P.points @ T[:3, :3].T + T[:3, 3]
        doc["aligned"] = {**cloud_metrics(moved, G.points, threshold), "transform": T.tolist(),
                          "icp": {"method": "Open3D point-to-point ICP, identity initialisation",
                                  "max_correspondence_distance": dist, **info}}
    return doc

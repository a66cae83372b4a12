"""Lifting a geometry prediction of synthesized views into the scene's world frame and cloud.

The geometry model sees the scene's reference view (the input image, the world origin) first and then
frames of a synthesized clip, so its output frame is the world frame up to an unknown scale (VGGT-style
models return the first camera as the identity and depth at their own scale). Lifting then

1. recovers the **scale** from the reference view, whose depth the scene already has (the initial
   geometry): the median ratio over pixels both predictions trust (``align_scale``);
2. optionally refines each new view by **ICP** (Open3D, point-to-plane, rigid) of its points against
   the existing cloud, accepted only where the view overlaps the cloud enough and the correction is
   small (``refine_views``): it removes the per-view pose error of the geometry model where the new
   view sees known surfaces, and leaves views that look at new territory alone;
3. unprojects confident pixels and fuses them with the existing cloud by voxel averaging.

Every frame this produces — cameras, depth, points — is in the world frame in which the planner wrote
the trajectory and in which the synthesizer was asked to render it; ``pose_deviation`` measures how far
the aligned cameras are from the requested ones (a diagnostic stored with the lift step).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from navcrafter.models.camera.cameras import axis_angle_to_matrix, invert_pose, rotation_angle_deg
from navcrafter.models.reconstruction.pointcloud import Cloud, views_to_cloud, voxel_fuse
from navcrafter.models.roles import GeometryPrediction


class AlignmentError(ValueError):
    """A prediction cannot be aligned to the scene (too little trusted overlap with the reference)."""


def select_views(num_frames: int, max_views: int) -> np.ndarray:
    """Evenly spaced frame indices in ``1 .. T-1`` (frame 0 is the current pose, already lifted),
    always including the last frame."""
    if num_frames < 2:
        raise ValueError("a clip needs at least 2 frames")
    n = min(max_views, num_frames - 1)
    return np.unique(np.round(np.linspace(num_frames - 1, 1, n)).astype(np.int32))


def align_scale(ref_depth: np.ndarray, ref_conf: np.ndarray, pred_depth: np.ndarray,
                pred_conf: np.ndarray, min_confidence: float) -> float:
    """Scale ``s`` with ``s * pred_depth ~ ref_depth``: the median ratio over mutually trusted pixels."""
    ok = (ref_conf >= min_confidence) & (pred_conf >= min_confidence) & (ref_depth > 0) & (pred_depth > 0)
    ok &= np.isfinite(ref_depth) & np.isfinite(pred_depth)
    if ok.sum() < 16:
        raise AlignmentError(f"only {int(ok.sum())} pixels of the reference view have trusted depth in both "
                             f"predictions; cannot align the new geometry to the scene")
    return float(np.median(ref_depth[ok] / pred_depth[ok]))


@dataclass
class ViewRefinement:
    accepted: bool
    fitness: float = 0.0  # fraction of the view's points with a correspondence within max_distance
    rmse_before: float = float("nan")
    rmse_after: float = float("nan")
    rotation_deg: float = 0.0
    translation: float = 0.0
    reason: str = ""


@dataclass
class Lifted:
    """One lift's output, all in the world frame."""

    c2w: np.ndarray  # [V, 4, 4]
    K: np.ndarray  # [V, 3, 3]
    depth: np.ndarray  # [V, H, W] float32, world units
    confidence: np.ndarray  # [V, H, W] float32
    new: Cloud  # points of these views alone
    cloud: Cloud  # the fused scene cloud
    scale: float
    refinements: list[ViewRefinement] = field(default_factory=list)

    def attrs(self) -> dict:
        acc = [r for r in self.refinements if r.accepted]
        out = {"scale": self.scale, "n_new_points": len(self.new), "n_points": len(self.cloud),
               "icp_views": len(self.refinements), "icp_accepted": len(acc)}
        if acc:
            out["icp_median_rotation_deg"] = float(np.median([r.rotation_deg for r in acc]))
            out["icp_median_translation"] = float(np.median([r.translation for r in acc]))
        return out


def _o3d_cloud(points: np.ndarray, normals: bool, radius: float):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals:
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=20))
    return pc


@dataclass
class _Registration:
    transformation: np.ndarray
    fitness: float
    inlier_rmse: float


class _Target:
    """An ICP target: points with normals and a KD-tree (scipy's: queries are deterministic)."""

    def __init__(self, cloud) -> None:
        from scipy.spatial import cKDTree

        self.points = np.asarray(cloud.points, dtype=np.float64)
        self.normals = np.asarray(cloud.normals, dtype=np.float64)
        self.tree = cKDTree(self.points)

    def match(self, pts: np.ndarray, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
        # one worker: ICP queries a few thousand points 30 times a view; scipy starts Python threads for each query
        # with workers > 1, which cost more than they saved while scenes ran side by side (per point: same result)
        d, idx = self.tree.query(pts, k=1, distance_upper_bound=max_distance)
        ok = np.isfinite(d)
        return ok, idx[ok]


def _evaluate(source: np.ndarray, target: _Target, max_distance: float, T: np.ndarray) -> _Registration:
    pts = np.einsum("kj,ij->ki", source, T[:3, :3]) + T[:3, 3]
    ok, idx = target.match(pts, max_distance)
    if not ok.any():
        return _Registration(T, 0.0, 0.0)
    d2 = np.einsum("ij,ij->i", pts[ok] - target.points[idx], pts[ok] - target.points[idx])
    return _Registration(T, float(ok.mean()), float(np.sqrt(np.sum(d2) / len(d2))))


def icp_point_to_plane(source: np.ndarray, target: _Target, max_distance: float, max_iteration: int = 30,
                       tolerance: float = 1e-6) -> _Registration:
    """Rigid point-to-plane ICP (linearised, Gauss-Newton), written out so that its result is bit-reproducible:
    Open3D's ``registration_icp`` sums its normal equations in parallel, in an order that changes from run to
    run, which would break exact resumes. Sums here are sequential (``einsum``, no BLAS)."""
    T = np.eye(4)
    for _ in range(max_iteration):
        pts = np.einsum("kj,ij->ki", source, T[:3, :3]) + T[:3, 3]
        ok, idx = target.match(pts, max_distance)
        if ok.sum() < 6:
            break
        p, q, n = pts[ok], target.points[idx], target.normals[idx]
        A = np.concatenate([np.cross(p, n), n], axis=1)
        b = np.einsum("ij,ij->i", q - p, n)
        x = np.linalg.solve(np.einsum("ni,nj->ij", A, A) + 1e-12 * np.eye(6), np.einsum("ni,n->i", A, b))
        step = np.eye(4)
        angle = float(np.linalg.norm(x[:3]))
        step[:3, :3] = axis_angle_to_matrix(x[:3] / angle, angle) if angle > 0 else np.eye(3)
        step[:3, 3] = x[3:]
        T = np.einsum("ij,jk->ik", step, T)
        if np.linalg.norm(x) < tolerance:
            break
    return _evaluate(source, target, max_distance, T)


def refine_view(points: np.ndarray, target, max_distance: float, *, min_fitness: float = 0.3,
                max_rotation_deg: float = 5.0, max_translation: float | None = None,
                min_gain: float = 0.85) -> tuple[np.ndarray, ViewRefinement]:
    """Rigid ICP (point-to-plane, ``icp_point_to_plane``) of one view's world points onto ``target`` (an Open3D
    cloud with normals).

    Returns the correction ``T`` (world → world, applied on the left of the view's pose) and what was
    decided. The correction is the identity unless the view overlaps the target with at least
    ``min_fitness``, the correction is within ``max_rotation_deg`` / ``max_translation`` and the residual
    drops below ``min_gain`` times its value before (so depth noise alone does not move a camera).
    """
    if len(points) < 50:
        return np.eye(4), ViewRefinement(False, reason="too few points")
    target = target if isinstance(target, _Target) else _Target(target)
    source = np.asarray(points, dtype=np.float64)
    before = _evaluate(source, target, max_distance, np.eye(4))
    if before.fitness < min_fitness:
        return np.eye(4), ViewRefinement(False, fitness=before.fitness, rmse_before=before.inlier_rmse,
                                         reason="little overlap with the scene cloud")
    result = icp_point_to_plane(source, target, max_distance)
    T = result.transformation
    rot = float(rotation_angle_deg(T[:3, :3], np.eye(3)))
    trans = float(np.linalg.norm(T[:3, 3]))
    info = ViewRefinement(False, fitness=result.fitness, rmse_before=before.inlier_rmse,
                          rmse_after=result.inlier_rmse, rotation_deg=rot, translation=trans)
    if result.fitness < min_fitness:
        info.reason = "overlap fell below the minimum during ICP"
    elif rot > max_rotation_deg or (max_translation is not None and trans > max_translation):
        info.reason = "correction larger than a geometry model's pose error; kept the prediction"
    elif not result.inlier_rmse < min_gain * before.inlier_rmse:
        info.reason = "ICP did not reduce the residual clearly (depth noise, not a pose error)"
    else:
        info.accepted = True
        return T, info
    return np.eye(4), info


def lift_prediction(frames: np.ndarray, pred: GeometryPrediction, ref_depth: np.ndarray, ref_conf: np.ndarray,
                    existing: Cloud, *, confidence_threshold: float, pixel_stride: int, max_depth: float,
                    voxel_size: float, icp: bool = True, icp_distance: float = 0.03) -> Lifted:
    """Align ``pred`` (reference view first, then ``frames``) to the world and fuse it into ``existing``.

    ``ref_depth``/``ref_conf``: the scene's depth of the reference view (world units). ``icp_distance`` is
    the ICP correspondence distance relative to the reference view's median depth.
    """
    if not np.allclose(pred.c2w[0], np.eye(4), atol=1e-6):
        raise AlignmentError("geometry backend returned a first-view pose that is not the identity")
    if len(pred.c2w) != len(frames) + 1:
        raise ValueError(f"prediction has {len(pred.c2w)} views for 1 reference + {len(frames)} frames")
    scale = align_scale(ref_depth, ref_conf, pred.depth[0], pred.confidence[0], confidence_threshold)
    c2w = pred.c2w[1:].astype(np.float64).copy()
    c2w[:, :3, 3] *= scale
    depth = np.nan_to_num(pred.depth[1:] * scale, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    conf = np.nan_to_num(pred.confidence[1:], nan=0.0).astype(np.float32)
    K = pred.K[1:].astype(np.float64)
    refinements: list[ViewRefinement] = []
    if icp and len(existing) >= 50:
        ref_valid = (ref_depth > 0) & (ref_conf >= confidence_threshold)
        distance = icp_distance * float(np.median(ref_depth[ref_valid]))
        target = _Target(_o3d_cloud(existing.points, normals=True, radius=max(3 * voxel_size, distance)))
        for i in range(len(frames)):
            view = views_to_cloud(frames[i:i + 1], depth[i:i + 1], conf[i:i + 1], c2w[i:i + 1], K[i:i + 1],
                                  confidence_threshold, max(pixel_stride, 2), max_depth)
            T, info = refine_view(view.points, target, distance, max_translation=3 * distance)
            refinements.append(info)
            if info.accepted:
                c2w[i] = T @ c2w[i]
    new = views_to_cloud(frames, depth, conf, c2w, K, confidence_threshold, pixel_stride, max_depth)
    cloud = voxel_fuse(Cloud.concat([existing, new]), voxel_size)
    return Lifted(c2w=c2w, K=K, depth=depth, confidence=conf, new=new, cloud=cloud, scale=scale,
                  refinements=refinements)


def pose_deviation(c2w: np.ndarray, requested: np.ndarray) -> dict[str, float]:
    """Median rotation (degrees) and camera-centre distance between aligned and requested poses."""
    rel = np.einsum("nij,njk->nik", invert_pose(requested), c2w)
    rot = rotation_angle_deg(rel[:, :3, :3], np.eye(3)[None])
    trans = np.linalg.norm(c2w[:, :3, 3] - requested[:, :3, 3], axis=-1)
    return {"pose_dev_rot_deg": float(np.median(rot)), "pose_dev_trans": float(np.median(trans))}

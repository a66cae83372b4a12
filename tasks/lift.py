"""Lift: geometry of a synthesized clip, aligned to the world, fused into the scene cloud.

The geometry model sees the input (reference) view first and then up to ``lift.max_views`` frames of
the clip, so its output frame is the world frame (the input camera is the world origin) up to scale.
The scale is recovered by comparing its depth of the reference view with the initial geometry's
(median ratio over pixels both trust), then the frames are unprojected, filtered by confidence and
fused with the previous cloud by voxel averaging.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.pointcloud import Cloud, views_to_cloud, voxel_fuse
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import GEOMETRY, INGEST, LIFT, PLAN, SYNTHESIZE
from navcrafter.tasks.common import StepRef, load_backend, load_cloud, open_store, run_step


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
    if ok.sum() < 16:
        raise ValueError(f"only {int(ok.sum())} pixels of the reference view have trusted depth in both "
                         f"predictions; cannot align the new geometry to the scene")
    return float(np.median(ref_depth[ok] / pred_depth[ok]))


def lift(store_uri: str, scene_id: str, k: int, config: RunConfig, run_id: str) -> StepRef:
    cfg = config.lift

    def body(writer, seed: int, _) -> dict:
        scene = open_store(store_uri).scene(scene_id)
        work = scene.read(INGEST, None, "work_image")
        geo = scene.read_all(GEOMETRY)
        trajectory = scene.read(PLAN, k, "trajectory")
        frames = scene.read(SYNTHESIZE, k, "frames")
        views = select_views(len(frames), cfg.max_views)
        images = np.concatenate([work[None], frames[views]])
        hint = np.concatenate([np.eye(4)[None], trajectory[views]])
        pred = load_backend(scene, config).geometry.predict(images, seed=seed, hint_c2w=hint)
        if not np.allclose(pred.c2w[0], np.eye(4), atol=1e-6):
            raise ValueError("geometry backend returned a first-view pose that is not the identity")
        scale = align_scale(geo["depth"], geo["confidence"], pred.depth[0], pred.confidence[0],
                            cfg.confidence_threshold)
        c2w = pred.c2w[1:].copy()
        c2w[:, :3, 3] *= scale
        depth = (pred.depth[1:] * scale).astype(np.float32)
        conf = pred.confidence[1:].astype(np.float32)
        K = pred.K[1:].astype(np.float64)
        new = views_to_cloud(frames[views], depth, conf, c2w, K, cfg.confidence_threshold,
                             cfg.pixel_stride, cfg.max_depth)
        cloud = voxel_fuse(Cloud.concat([load_cloud(scene, k - 1), new]), cfg.voxel_size)
        writer.write("view_index", views)
        writer.write("c2w", c2w)
        writer.write("K", K)
        writer.write("depth", depth)
        writer.write("confidence", conf)
        writer.write("cloud_points", cloud.points)
        writer.write("cloud_colors", cloud.colors)
        writer.write("cloud_confidence", cloud.confidence)
        return {"scale": scale, "n_new_points": len(new), "n_points": len(cloud)}

    return run_step(store_uri, scene_id, LIFT, k, config, run_id, body)

"""Lift: geometry of a synthesized clip, aligned to the world, fused into the scene cloud.

The geometry model sees the input (reference) view first and then up to ``lift.max_views`` frames of
the clip, so its output frame is the world frame (the input camera is the world origin) up to scale.
``navcrafter.models.reconstruction.lifting.lift_prediction`` recovers the scale from the reference view, refines each
view's pose by ICP against the existing cloud where they overlap, and fuses the new points.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.reconstruction.lifting import lift_prediction, pose_deviation, select_views
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import GEOMETRY, INGEST, LIFT, PLAN, SYNTHESIZE
from navcrafter.tasks.common import StepRef, load_backend, load_cloud, open_store, run_step


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
        out = lift_prediction(frames[views], pred, geo["depth"], geo["confidence"], load_cloud(scene, k - 1),
                              confidence_threshold=cfg.confidence_threshold, pixel_stride=cfg.pixel_stride,
                              max_depth=cfg.max_depth, voxel_size=cfg.voxel_size, icp=cfg.icp,
                              icp_distance=cfg.icp_distance)
        writer.write("view_index", views)
        writer.write("c2w", out.c2w)
        writer.write("K", out.K)
        writer.write("depth", out.depth)
        writer.write("confidence", out.confidence)
        writer.write("cloud_points", out.cloud.points)
        writer.write("cloud_colors", out.cloud.colors)
        writer.write("cloud_confidence", out.cloud.confidence)
        return {**out.attrs(), **pose_deviation(out.c2w, trajectory[views])}

    return run_step(store_uri, scene_id, LIFT, k, config, run_id, body)

"""Lift: geometry of a synthesized clip, aligned to the world, fused into the scene cloud.

The geometry model sees the input (reference) view first and then up to ``lift.max_views`` frames of
the clip, so its output frame is the world frame (the input camera is the world origin) up to scale.
``navcrafter.models.reconstruction.lifting.lift_prediction`` recovers the scale from the reference view, refines
each view's pose by ICP against the existing cloud where they overlap, and fuses the new points.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.reconstruction.lifting import lift_prediction, pose_deviation, select_views
from navcrafter.schemas.layout import GEOMETRY, INGEST, PLAN, SYNTHESIZE
from navcrafter.tasks.readers import frame_truth
from navcrafter.tasks.steps import StepContext


def lift(ctx: StepContext) -> dict:
    cfg, scene, k = ctx.config.lift, ctx.scene, ctx.k
    work = scene.read(INGEST, None, "work_image")
    geo = scene.read_all(GEOMETRY)
    trajectory = scene.read(PLAN, k, "trajectory")
    frames = scene.read(SYNTHESIZE, k, "frames")
    views = select_views(len(frames), cfg.max_views)
    images = np.concatenate([work[None], frames[views]])
    # hints of the simulated geometry (ignored by learned models): where the frames really are, what they show
    true_c2w, true_depth = frame_truth(scene, k, views)
    hint = np.concatenate([np.eye(4)[None], true_c2w])
    pred = ctx.backend.geometry.predict(images, seed=ctx.seed, hint_c2w=hint, hint_depth=[None, *true_depth])
    out = lift_prediction(frames[views], pred, geo["depth"], geo["confidence"], ctx.cloud(k - 1),
                          confidence_threshold=cfg.confidence_threshold, pixel_stride=cfg.pixel_stride,
                          max_depth=cfg.max_depth, voxel_size=cfg.voxel_size, icp=cfg.icp,
                          icp_distance=cfg.icp_distance)
    ctx.write_all(view_index=views, c2w=out.c2w, K=out.K, depth=out.depth, confidence=out.confidence,
                  cloud_points=out.cloud.points, cloud_colors=out.cloud.colors,
                  cloud_confidence=out.cloud.confidence)
    return {**out.attrs(), **pose_deviation(out.c2w, trajectory[views])}

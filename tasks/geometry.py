"""Initial geometry: cameras, depth and the first cloud of the input view.

The input camera defines the scene's world frame (``c2w = I``); the world's scale is whatever the
geometry model returns for this first call (metric for metric models).
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.reconstruction.pointcloud import Cloud, views_to_cloud, voxel_fuse
from navcrafter.schemas.config import LiftConfig
from navcrafter.schemas.layout import INGEST
from navcrafter.tasks.steps import StepContext


def view_cloud(image: np.ndarray, depth: np.ndarray, confidence: np.ndarray, K: np.ndarray, cfg: LiftConfig) -> Cloud:
    """The fused cloud of one view at the identity camera (``depth``, ``confidence`` [H, W], ``K`` [3, 3]), with the
    lift step's confidence threshold, pixel stride, depth cap and voxel size."""
    cloud = views_to_cloud(image[None], depth[None], confidence[None], np.eye(4)[None], K[None],
                           cfg.confidence_threshold, cfg.pixel_stride, cfg.max_depth)
    return voxel_fuse(cloud, cfg.voxel_size)


def initial_geometry(ctx: StepContext) -> dict:
    work = ctx.scene.read(INGEST, None, "work_image")
    pred = ctx.backend.geometry.predict(work[None], seed=ctx.seed, hint_c2w=np.eye(4)[None])
    if not np.allclose(pred.c2w[0], np.eye(4), atol=1e-6):
        raise ValueError("geometry backend returned a first-view pose that is not the identity")
    cloud = view_cloud(work, pred.depth[0], pred.confidence[0], pred.K[0], ctx.config.lift)
    if len(cloud) == 0:
        raise ValueError("the geometry model found no confident depth in the input image")
    ctx.write_all(c2w=np.eye(4), K=pred.K[0].astype(np.float64), depth=pred.depth[0].astype(np.float32),
                  confidence=pred.confidence[0].astype(np.float32), cloud_points=cloud.points,
                  cloud_colors=cloud.colors, cloud_confidence=cloud.confidence)
    attrs = {"n_points": len(cloud)}
    if ctx.backend.is_simulation:
        attrs["simulation_world_scale"] = float(pred.extras["simulation_scale"])
    return attrs

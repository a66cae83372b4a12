"""Initial geometry: cameras, depth and the first cloud of the input view.

The input camera defines the scene's world frame (``c2w = I``); the world's scale is whatever the
geometry model returns for this first call (metric for metric models).
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.reconstruction.pointcloud import views_to_cloud, voxel_fuse
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import GEOMETRY, INGEST
from navcrafter.tasks.common import StepRef, load_backend, open_store, run_step


def initial_geometry(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> StepRef:
    def body(writer, seed: int, _) -> dict:
        scene = open_store(store_uri).scene(scene_id)
        work = scene.read(INGEST, None, "work_image")
        backend = load_backend(scene, config)
        pred = backend.geometry.predict(work[None], seed=seed, hint_c2w=np.eye(4)[None])
        if not np.allclose(pred.c2w[0], np.eye(4), atol=1e-6):
            raise ValueError("geometry backend returned a first-view pose that is not the identity")
        cfg = config.lift
        cloud = views_to_cloud(work[None], pred.depth[:1], pred.confidence[:1], np.eye(4)[None], pred.K[:1],
                               cfg.confidence_threshold, cfg.pixel_stride, cfg.max_depth)
        cloud = voxel_fuse(cloud, cfg.voxel_size)
        if len(cloud) == 0:
            raise ValueError("the geometry model found no confident depth in the input image")
        writer.write("c2w", np.eye(4))
        writer.write("K", pred.K[0].astype(np.float64))
        writer.write("depth", pred.depth[0].astype(np.float32))
        writer.write("confidence", pred.confidence[0].astype(np.float32))
        writer.write("cloud_points", cloud.points)
        writer.write("cloud_colors", cloud.colors)
        writer.write("cloud_confidence", cloud.confidence)
        attrs = {"n_points": len(cloud)}
        if backend.is_simulation:
            attrs["simulation_world_scale"] = float(pred.extras["simulation_scale"])
        return attrs

    return run_step(store_uri, scene_id, GEOMETRY, None, config, run_id, body)

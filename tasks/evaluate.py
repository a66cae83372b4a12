"""Scene metrics written at the end of a scene run.

In simulation mode the cloud is compared with the true surfaces: each point is mapped to the
ground-truth frame (metres) and its distance to the nearest true triangle measured (Open3D).
"""

from __future__ import annotations

import numpy as np

from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import EXPORT, LIFT, PLAN
from navcrafter.schemas.tables import utcnow
from navcrafter.tasks.common import load_cloud, open_store, simulation_truth

UNITS = {"n_points": "count", "cloud_median_dist_m": "m", "cloud_mean_dist_m": "m", "cloud_p90_dist_m": "m",
         "cloud_within_2cm": "fraction", "cloud_within_5cm": "fraction", "camera_median_err_m": "m"}


def surface_distance_stats(distances: np.ndarray) -> dict[str, float]:
    """Summary of point-to-surface distances (metres)."""
    if len(distances) == 0:
        return {}
    return {"cloud_median_dist_m": float(np.median(distances)), "cloud_mean_dist_m": float(distances.mean()),
            "cloud_p90_dist_m": float(np.quantile(distances, 0.9)),
            "cloud_within_2cm": float((distances <= 0.02).mean()),
            "cloud_within_5cm": float((distances <= 0.05).mean())}


def evaluate_scene(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> dict[str, float]:
    """Metrics of a finished scene (also appended to the ``metrics`` table, once per export)."""
    store = open_store(store_uri)
    scene = store.scene(scene_id)
    export_key = scene.require_complete(EXPORT).key
    cloud = load_cloud(scene, config.iterations)
    metrics: dict[str, float] = {"n_points": float(len(cloud))}
    truth = simulation_truth(scene) if config.backend == "simulation" else None
    if truth is not None:
        metrics.update(surface_distance_stats(truth.scene.distance(truth.gt_points(cloud.points))))
        errs = []
        for k in range(1, config.iterations + 1):
            est = scene.read(LIFT, k, "c2w")[:, :3, 3]
            req = scene.read(PLAN, k, "trajectory")[scene.read(LIFT, k, "view_index")][:, :3, 3]
            errs.append(np.linalg.norm(est - req, axis=1) / truth.world_scale)
        if errs:
            metrics["camera_median_err_m"] = float(np.median(np.concatenate(errs)))
    part = f"scene-{scene_id}-{export_key[:16]}"
    if not store.fs.exists(f"{store.tables.root}/metrics/{part}.parquet"):
        now = utcnow()
        store.tables.write("metrics", [{"scene_id": scene_id, "run_id": run_id, "name": k, "value": v,
                                        "unit": UNITS.get(k), "backend": config.backend, "created_at": now}
                                       for k, v in metrics.items()], part=part)
    return metrics

"""The evaluate step: scene metrics written at the end of a scene run (the maths: ``models.metrics.cloud``).

In simulation mode the cloud is compared with the true surfaces in the ground-truth frame, whose
unit is the metre (rooms are 5-7 m across, table-tops 6 m rooms with 0.1-0.2 m objects, streets
10-15 m wide), so the paper's 2 cm threshold is used as is (``THRESHOLD_M``):

* ``coverage``: fraction of reference surface points (``models.simulation.reference``: the true
  surfaces visible from where the explorer may go) within 2 cm of a reconstructed point;
* ``noise_ratio``: fraction of reconstructed points farther than 2 cm from every true surface;
* ``fscore``: harmonic mean of precision (1 - noise ratio) and coverage;
* ``collisions``: trajectory samples (every frame of every iteration) closer than ``r_safe`` to a
  true surface or inside an object; ``collision_rate`` is their fraction;
* distances of points to the true surfaces (median, mean, p90) and the median camera error.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.metrics.cloud import (
    UNITS,
    coverage_metrics,
    surface_distance_stats,
    trajectory_collisions,
)
from navcrafter.models.planning.planners import search_space
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import EXPORT, LIFT, PLAN
from navcrafter.schemas.tables import utcnow
from navcrafter.tasks import steps
from navcrafter.tasks.common import load_cloud, simulation_truth
from navcrafter.tasks.readers import camera_path, stored_scene_centre
from navcrafter.tasks.steps import StepContext


def evaluate(ctx: StepContext) -> dict:
    """The evaluate step: metrics of a finished scene, stored in its ``evaluation`` group (a rerun reads them
    back) and appended to the ``metrics`` table when computed."""
    config = ctx.config
    metrics = compute_metrics(ctx.scene, config)
    now = utcnow()
    ctx.scene.store.tables.write(
        "metrics", [{"scene_id": ctx.scene_id, "run_id": ctx.run_id, "name": k, "value": v,
                     "unit": UNITS.get(k), "backend": config.backend, "created_at": now}
                    for k, v in metrics.items()], part=f"scene-{ctx.scene_id}-{ctx.writer.exec_id}")
    return {"metrics": metrics, "iterations": config.iterations}


def evaluate_scene(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> dict[str, float]:
    """Run (or read back) the evaluate step of a finished scene: its metrics."""
    attrs = steps.run_attrs(store_uri, scene_id, "evaluate", config, run_id)
    return {k: float(v) for k, v in attrs["metrics"].items()}


def compute_metrics(scene, config: RunConfig) -> dict[str, float]:
    """All metrics of an exported scene (see the module docstring)."""
    scene.require_complete(EXPORT)
    cloud = load_cloud(scene, config.iterations)
    metrics: dict[str, float] = {"n_points": float(len(cloud))}
    from navcrafter.models.simulation.reference import reference_points

    plan_attrs = [scene.status(PLAN, k).attrs for k in range(1, config.iterations + 1)]
    metrics["plan_seconds"] = float(sum(a.get("seconds", 0.0) for a in plan_attrs))
    truth = simulation_truth(scene) if config.backend == "simulation" else None
    if truth is not None:
        points_gt = truth.gt_points(cloud.points)
        dist = truth.scene.distance(points_gt)
        metrics.update(surface_distance_stats(dist))
        centre = stored_scene_centre(scene, config)
        d0 = float(np.linalg.norm(centre))
        r_safe_m = config.plan.safe_radius / truth.world_scale
        reference = reference_points(truth, centre, d0, search_space(config.plan),
                                     max(1, config.iterations), r_safe_m)
        metrics.update(coverage_metrics(points_gt, reference, dist))
        path = camera_path(scene, config)
        if config.iterations:
            metrics.update(trajectory_collisions(truth, path.c2w, r_safe_m))
        errs = []
        for k in range(1, config.iterations + 1):
            est = scene.read(LIFT, k, "c2w")[:, :3, 3]
            req = path.clip(k).c2w[scene.read(LIFT, k, "view_index")][:, :3, 3]
            errs.append(np.linalg.norm(est - req, axis=1) / truth.world_scale)
        if errs:
            metrics["camera_median_err_m"] = float(np.median(np.concatenate(errs)))
    return metrics

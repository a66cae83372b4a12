"""The evaluate step: scene metrics written at the end of a scene run (the maths: ``models.metrics.cloud``).

In simulation mode the cloud is compared with the true surfaces in the ground-truth frame, whose
unit is the metre (rooms are 5-7 m across, table-tops 6 m rooms with 0.1-0.2 m objects, streets
10-15 m wide), so the paper's 2 cm threshold is used as is (``THRESHOLD_M``):

* ``coverage``: fraction of reference surface points (``models.simulation.reference``: the true
  surfaces visible from where the explorer may go) within 2 cm of a reconstructed point;
* ``noise_ratio``: fraction of reconstructed points farther than 2 cm from every true surface;
* ``fscore``: harmonic mean of precision (1 - noise ratio) and coverage;
* ``collisions``: trajectory samples (every frame of every iteration) closer than ``r_safe`` to a
  true surface or inside an object; ``collision_rate`` is their fraction. Measured on the true camera
  path (``true_c2w`` of each clip's synthesize step: where the simulated video model really took each
  frame); a clip stored without it (older stores) counts at its planned trajectory;
* ``coverage_iter_<k>`` (k = 0..N): coverage of the cloud after iteration k (0: the initial cloud), with
  the reference points of ``coverage``; ``new_surface_iter_<k>`` (k = 1..N): coverage_iter_k minus
  coverage_iter_(k-1);
* ``close_frames``: fraction of all frames of all clips (at their true cameras) dominated by a surface
  nearer than 2 r_safe: more than half of the pixels of a depth render (64 px on the longer side) hit a
  true surface at z-depth below 2 r_safe; ``close_frames_last_third``: the same over the last third of the
  frames of the whole path (a video that ends staring at a wall);
* ``true_quality_mean``: mean over all frames of the simulation's ``true_quality`` (fraction of each
  frame's pixels that show the true scene), when stored;
* the exploration metrics of ``models.metrics.cloud.exploration_metrics`` (``exploration``): ``seen`` (the
  reference surface the true frames of the input view and every clip saw, with true depth), coverage and F-score
  at 2, 5, 10 cm and at 0.5, 1, 2 % of d0, ``coverage_auc``, ``precision``, and for table-tops the object
  region's ``object_coverage``;
* distances of points to the true surfaces (median, mean, p90) and ``camera_median_err_m``: the median
  distance of the lifted camera centres to the true ones (``true_c2w``; the requested ones for a clip
  stored without it).
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.metrics.cloud import (
    close_frame_mask,
    close_frame_metrics,
    coverage_fraction,
    coverage_metrics,
    exploration_metrics,
    region_mask,
    seen_mask,
    surface_distance_stats,
    trajectory_collisions,
    unit,
)
from navcrafter.models.planning.planners import search_space
from navcrafter.models.simulation.reference import object_region_prefixes, reference_points
from navcrafter.models.simulation.render import render_many
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import EXPORT, LIFT, PLAN, STEPS, SYNTHESIZE
from navcrafter.schemas.tables import utcnow
from navcrafter.tasks import steps
from navcrafter.tasks.common import load_cloud, simulation_truth
from navcrafter.tasks.readers import stored_scene_centre, true_cameras
from navcrafter.tasks.steps import StepContext


def evaluate(ctx: StepContext) -> dict:
    """The evaluate step: metrics of a finished scene, stored in its ``evaluation`` group (a rerun reads them
    back) and appended to the ``metrics`` table when computed."""
    config = ctx.config
    metrics = compute_metrics(ctx.scene, config)
    now = utcnow()
    ctx.scene.store.tables.write(
        "metrics", [{"scene_id": ctx.scene_id, "run_id": ctx.run_id, "name": k, "value": v,
                     "unit": unit(k), "backend": config.backend, "created_at": now}
                    for k, v in metrics.items()], part=f"scene-{ctx.scene_id}-{ctx.writer.exec_id}")
    return {"metrics": metrics, "iterations": config.iterations}


def evaluate_scene(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> dict[str, float]:
    """Run (or read back) the evaluate step of a finished scene: its metrics."""
    attrs = steps.execute_attrs(store_uri, scene_id, STEPS["evaluate"], config, run_id, evaluate)
    return {k: float(v) for k, v in attrs["metrics"].items()}


def true_array(scene, k: int, name: str) -> np.ndarray | None:
    """An optional simulation-only array of clip ``k``'s synthesize step (``true_c2w``, ``true_depth``,
    ``true_quality``), or ``None`` when the store has none (older stores, other backends)."""
    return scene.read(SYNTHESIZE, k, name) if scene.has(SYNTHESIZE, k, name) else None


def true_camera_path(scene, config: RunConfig) -> np.ndarray:
    """``readers.true_cameras`` of clips 1..N, concatenated."""
    parts = [true_cameras(scene, k) for k in range(1, config.iterations + 1)]
    return np.concatenate(parts) if parts else np.zeros((0, 4, 4))


SEEN_SIDE = 128  # longer image side (px) at which the true frames are rendered for ``seen``
SEEN_SAMPLE = 100_000  # ``seen`` is measured on at most this many reference points (evenly strided)


def exploration(truth, points_gt: np.ndarray, dist: np.ndarray, reference: np.ndarray, d0_m: float,
                frames_gt: np.ndarray, K) -> dict[str, float]:
    """``exploration_metrics`` of one explored scene, from its ground truth: ``truth`` (``SimulationTruth``-like:
    ``.scene`` renders with ``models.simulation.render.render_many``), the reconstruction ``points_gt`` and their
    distances ``dist`` to the true surfaces, the ``reference`` surface points, the scene scale ``d0_m`` (metres),
    ``frames_gt`` ``[T, 4, 4]``: every true camera of the run (input camera included) in the ground-truth frame,
    ``K``: their ``Intrinsics``. Reusable by any loop over scenes with a ground truth (the benchmark's)."""
    s = min(1.0, SEEN_SIDE / max(K.width, K.height))
    Ks = K.resize(max(1, round(K.width * s)), max(1, round(K.height * s))) if s < 1.0 else K
    depths = list(render_many(truth.scene, np.asarray(frames_gt), Ks, colour=False).depth)  # one batched cast
    sample = np.arange(0, len(reference), max(1, -(-len(reference) // SEEN_SAMPLE)))
    seen = seen_mask(reference[sample], frames_gt, Ks.K, depths)
    prefixes = object_region_prefixes(truth.scene.kind)
    region = region_mask(truth.scene, reference, prefixes) if prefixes else None
    return exploration_metrics(points_gt, reference, dist, d0_m, seen=seen, region=region, seen_index=sample)


def compute_metrics(scene, config: RunConfig) -> dict[str, float]:
    """All metrics of an exported scene (see the module docstring)."""
    scene.require_complete(EXPORT)
    cloud = load_cloud(scene, config.iterations)
    metrics: dict[str, float] = {"n_points": float(len(cloud))}

    plan_attrs = [scene.status(PLAN, k).attrs for k in range(1, config.iterations + 1)]
    metrics["plan_seconds"] = float(sum(a.get("seconds", 0.0) for a in plan_attrs))
    quality = [q for q in (true_array(scene, k, "true_quality") for k in range(1, config.iterations + 1))
               if q is not None]
    if quality and sum(len(q) for q in quality):
        metrics["true_quality_mean"] = float(np.concatenate(quality).astype(np.float64).mean())
    truth = simulation_truth(scene) if config.backend == "simulation" else None
    if truth is not None:
        points_gt = truth.gt_points(cloud.points)
        dist = truth.scene.distance(points_gt)
        metrics.update(surface_distance_stats(dist))
        centre = stored_scene_centre(scene, config)
        d0 = float(np.linalg.norm(centre))
        r_safe_m = config.plan.safe_radius / truth.world_scale
        reference = reference_points(truth, centre, d0, search_space(config.plan), r_safe_m)
        metrics.update(coverage_metrics(points_gt, reference, dist))
        previous = None
        for k in range(config.iterations + 1):
            cov = metrics["coverage"] if k == config.iterations else \
                coverage_fraction(truth.gt_points(load_cloud(scene, k).points), reference)
            metrics[f"coverage_iter_{k}"] = cov
            if previous is not None:
                metrics[f"new_surface_iter_{k}"] = cov - previous
            previous = cov
        true_path = true_camera_path(scene, config)
        K_syn = truth.intrinsics_for(config.synthesis.height, config.synthesis.width)
        frames_gt = np.concatenate([truth.photo_c2w[None], truth.gt_pose(true_path)]) if len(true_path) \
            else truth.photo_c2w[None]
        metrics.update(exploration(truth, points_gt, dist, reference, d0 / truth.world_scale, frames_gt, K_syn))
        if config.iterations:
            metrics.update(trajectory_collisions(truth, true_path, r_safe_m))
            K = truth.intrinsics_for(config.synthesis.height, config.synthesis.width)
            close = close_frame_mask(truth.scene, truth.gt_pose(true_path), K, 2 * r_safe_m)
            metrics.update(close_frame_metrics(close))
        errs = []
        for k in range(1, config.iterations + 1):
            est = scene.read(LIFT, k, "c2w")[:, :3, 3]
            req = true_cameras(scene, k)[scene.read(LIFT, k, "view_index")][:, :3, 3]
            errs.append(np.linalg.norm(est - req, axis=1) / truth.world_scale)
        if errs:
            metrics["camera_median_err_m"] = float(np.median(np.concatenate(errs)))
    return metrics

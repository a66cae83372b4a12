"""Metrics of a reconstructed cloud against the true surfaces, and of trajectories against them (paper, Table V).

At the paper's 2 cm threshold (``THRESHOLD_M``), for points in the ground-truth frame (metres):

* ``coverage``: fraction of reference surface points within the threshold of a reconstructed point;
* ``noise_ratio``: fraction of reconstructed points farther than the threshold from every true surface;
* ``fscore``: harmonic mean of precision (1 - noise ratio) and coverage;
* ``collisions``: camera positions closer than ``r_safe`` to a true surface or inside an object;
* ``close_frames``: frames dominated by a surface nearer than ``2 r_safe`` (``close_frame_mask``);
* distances of points to the true surfaces (median, mean, p90, fractions within 2 and 5 cm).

Against a reference *cloud* instead of the true surfaces (``navcrafter evaluate-cloud``): ``cloud_metrics``, the same
definitions with nearest-reference-point distances (precision = 1 - noise ratio, recall = coverage).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

THRESHOLD_M = 0.02
CLOSE_FRAME_SIDE = 64  # longer image side (px) at which close frames are rendered
UNITS = {  # of every scene metric (tasks/scene_metrics.py); per-iteration names: ``unit``
    "n_points": "count", "cloud_median_dist_m": "m", "cloud_mean_dist_m": "m", "cloud_p90_dist_m": "m",
    "cloud_within_2cm": "fraction", "cloud_within_5cm": "fraction", "camera_median_err_m": "m",
    "coverage": "fraction", "noise_ratio": "fraction", "fscore": "fraction", "collisions": "count",
    "collision_rate": "fraction", "plan_seconds": "s", "close_frames": "fraction",
    "close_frames_last_third": "fraction", "true_quality_mean": "fraction",
    # per iteration k: coverage_iter_<k> (k = 0..N), new_surface_iter_<k> (k = 1..N)
    "coverage_iter": "fraction", "new_surface_iter": "fraction"}


def unit(name: str) -> str | None:
    """The unit of a scene metric, per-iteration names (``coverage_iter_2``) included."""
    if name in UNITS:
        return UNITS[name]
    base, sep, k = name.rpartition("_")
    return UNITS.get(base) if sep and k.isdigit() else None


def coverage_fraction(points: np.ndarray, reference: np.ndarray, threshold: float = THRESHOLD_M) -> float:
    """Fraction of ``reference`` points within ``threshold`` of one of ``points`` (both ground-truth frame)."""
    if len(points) == 0 or len(reference) == 0:
        return 0.0
    # Only "within threshold or not" matters: the bound lets far queries stop early (30x faster).
    d_ref, _ = cKDTree(points).query(reference, k=1, distance_upper_bound=threshold * (1 + 1e-9), workers=-1)
    return float((d_ref <= threshold).mean())


def coverage_metrics(points: np.ndarray, reference: np.ndarray, surface_distance: np.ndarray,
                     threshold: float = THRESHOLD_M) -> dict[str, float]:
    """Coverage, noise ratio and F-score of reconstructed ``points`` (ground-truth frame) given the
    reference surface points and each reconstructed point's distance to the true surfaces."""
    if len(points) == 0 or len(reference) == 0:
        return {"coverage": 0.0, "noise_ratio": 1.0 if len(points) else 0.0, "fscore": 0.0}
    coverage = coverage_fraction(points, reference, threshold)
    precision = float((surface_distance <= threshold).mean())
    f = 2 * precision * coverage / (precision + coverage) if precision + coverage > 0 else 0.0
    return {"coverage": coverage, "noise_ratio": 1.0 - precision, "fscore": f}


def nearest_distances(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Distance of each of ``points`` to its nearest ``reference`` point (inf when ``reference`` is empty)."""
    if len(points) == 0:
        return np.zeros(0)
    if len(reference) == 0:
        return np.full(len(points), np.inf)
    d, _ = cKDTree(reference).query(points, k=1, workers=-1)
    return d


def cloud_metrics(points: np.ndarray, reference: np.ndarray, threshold: float = THRESHOLD_M) -> dict[str, float]:
    """``coverage_metrics`` against a reference *cloud* (``navcrafter evaluate-cloud``; Tanks and Temples style):
    a point's distance to the true surfaces is its distance to the nearest reference point. ``precision`` (points
    within ``threshold`` of the reference) = 1 - ``noise_ratio``, ``recall`` (reference points within ``threshold``
    of a point) = ``coverage``, ``fscore`` their harmonic mean; with the medians of both nearest distances."""
    points, reference = np.asarray(points, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    d_pred = nearest_distances(points, reference)
    m = coverage_metrics(points, reference, d_pred, threshold)
    d_ref = nearest_distances(reference, points)
    return {"precision": float((d_pred <= threshold).mean()) if len(points) else 0.0, "recall": m["coverage"], **m,
            "median_dist_to_reference": float(np.median(d_pred)) if len(points) else float("nan"),
            "median_dist_from_reference": float(np.median(d_ref)) if len(reference) else float("nan")}


def trajectory_collisions(truth, trajectories_world: np.ndarray, r_safe_m: float) -> dict[str, float]:
    """Camera positions closer than ``r_safe_m`` to a true surface, or inside an object."""
    import open3d as o3d

    pos = truth.gt_points(trajectories_world[:, :3, 3])
    rc, _ = truth.scene.raycasting()
    inside = rc.compute_occupancy(o3d.core.Tensor(pos.astype(np.float32))).numpy() > 0
    hit = (truth.scene.distance(pos) < r_safe_m) | inside
    return {"collisions": float(hit.sum()), "collision_rate": float(hit.mean()) if len(hit) else 0.0}


def close_frame_mask(scene, c2w_gt: np.ndarray, intrinsics, near_m: float,
                     max_side: int = CLOSE_FRAME_SIDE) -> np.ndarray:
    """Per camera (``c2w_gt`` ``[T, 4, 4]``, ground-truth frame, metres): whether more than half of its
    pixels show a true surface nearer (z-depth) than ``near_m``. Rendered (depth only) with ``intrinsics``
    scaled down to ``max_side`` pixels on the longer side."""
    from navcrafter.models.simulation.render import render

    w, h = intrinsics.width, intrinsics.height
    s = min(1.0, max_side / max(w, h))
    K = intrinsics.resize(max(1, round(w * s)), max(1, round(h * s))) if s < 1.0 else intrinsics
    out = np.zeros(len(c2w_gt), dtype=bool)
    for i, c2w in enumerate(np.asarray(c2w_gt, dtype=np.float64)):
        r = render(scene, c2w, K, colour=False)
        out[i] = float((r.hit & (r.depth < near_m)).mean()) > 0.5
    return out


def close_frame_metrics(close: np.ndarray) -> dict[str, float]:
    """``close_frames`` (fraction of all frames that are close) and ``close_frames_last_third`` (the same
    over the last ceil(T/3) frames)."""
    close = np.asarray(close, dtype=bool)
    if len(close) == 0:
        return {"close_frames": 0.0, "close_frames_last_third": 0.0}
    last = close[len(close) - int(np.ceil(len(close) / 3)):]
    return {"close_frames": float(close.mean()), "close_frames_last_third": float(last.mean())}


def surface_distance_stats(distances: np.ndarray) -> dict[str, float]:
    """Summary of point-to-surface distances (metres)."""
    if len(distances) == 0:
        return {}
    return {"cloud_median_dist_m": float(np.median(distances)), "cloud_mean_dist_m": float(distances.mean()),
            "cloud_p90_dist_m": float(np.quantile(distances, 0.9)),
            "cloud_within_2cm": float((distances <= 0.02).mean()),
            "cloud_within_5cm": float((distances <= 0.05).mean())}



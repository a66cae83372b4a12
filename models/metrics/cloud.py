"""Metrics of a reconstructed cloud against the true surfaces, and of trajectories against them (paper, Table V).

At the paper's 2 cm threshold (``THRESHOLD_M``), for points in the ground-truth frame (metres):

* ``coverage``: fraction of reference surface points within the threshold of a reconstructed point;
* ``noise_ratio``: fraction of reconstructed points farther than the threshold from every true surface;
* ``fscore``: harmonic mean of precision (1 - noise ratio) and coverage;
* ``collisions``: camera positions closer than ``r_safe`` to a true surface or inside an object;
* ``close_frames``: frames dominated by a surface nearer than ``2 r_safe`` (``close_frame_mask``);
* distances of points to the true surfaces (median, mean, p90, fractions within 2 and 5 cm).

Exploration (issue 30: the 2 cm columns measure depth error as much as exploration), ``exploration_metrics``:

* ``seen``: fraction of the reference surface that the method's *true* frames saw (true cameras, true depth: the
  ceiling any lifting can reach; ``seen_mask``);
* ``coverage_at`` / ``fscore_at`` at 2, 5 and 10 cm (``THRESHOLDS_M``) and ``coverage_rel`` / ``fscore_rel`` at
  0.5, 1 and 2 % of the scene scale d0 (``THRESHOLDS_REL``; d0 = the input camera's distance to the scene centre
  o, in metres), flattened as ``coverage_at_0.05``, ``coverage_rel_0.01``, ...;
* ``coverage_auc``: the area under coverage(threshold) for thresholds from 0 to 2 % of d0, normalised to 0-1;
* ``precision`` (1 - noise ratio at 2 cm);
* with an object region (table-tops: the table and what stands on it), ``object_coverage`` (2 cm),
  ``object_coverage_at_0.05`` and ``object_seen`` over that region's reference points alone.

Against a reference *cloud* instead of the true surfaces (``navcrafter evaluate-cloud``): ``cloud_metrics``, the same
definitions with nearest-reference-point distances (precision = 1 - noise ratio, recall = coverage).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

THRESHOLD_M = 0.02
THRESHOLDS_M = (0.02, 0.05, 0.10)  # absolute thresholds of ``coverage_at`` (metres)
THRESHOLDS_REL = (0.005, 0.01, 0.02)  # thresholds of ``coverage_rel``, fractions of the scene scale d0
AUC_STEPS = 20  # thresholds of ``coverage_auc``: k / AUC_STEPS x max(THRESHOLDS_REL) x d0, k = 1..AUC_STEPS
CLOSE_FRAME_SIDE = 64  # longer image side (px) at which close frames are rendered
UNITS = {  # of every scene metric (tasks/scene_metrics.py); per-iteration names: ``unit``
    "n_points": "count", "cloud_median_dist_m": "m", "cloud_mean_dist_m": "m", "cloud_p90_dist_m": "m",
    "cloud_within_2cm": "fraction", "cloud_within_5cm": "fraction", "camera_median_err_m": "m",
    "coverage": "fraction", "noise_ratio": "fraction", "fscore": "fraction", "collisions": "count",
    "collision_rate": "fraction", "plan_seconds": "s", "close_frames": "fraction",
    "close_frames_last_third": "fraction", "true_quality_mean": "fraction",
    # per iteration k: coverage_iter_<k> (k = 0..N), new_surface_iter_<k> (k = 1..N)
    "coverage_iter": "fraction", "new_surface_iter": "fraction",
    "seen": "fraction", "coverage_auc": "fraction", "precision": "fraction", "object_coverage": "fraction",
    "object_seen": "fraction", "d0_m": "m",
    **{f"{m}_at_{t:.2f}": "fraction" for m in ("coverage", "fscore", "object_coverage") for t in THRESHOLDS_M},
    **{f"{m}_rel_{t:g}": "fraction" for m in ("coverage", "fscore") for t in THRESHOLDS_REL}}


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


def _fscore(precision: float, coverage: float) -> float:
    return 2 * precision * coverage / (precision + coverage) if precision + coverage > 0 else 0.0


def exploration_metrics(points: np.ndarray, reference: np.ndarray, surface_distance: np.ndarray, d0_m: float,
                        seen: np.ndarray | None = None, region: np.ndarray | None = None,
                        seen_index: np.ndarray | None = None) -> dict[str, float]:
    """The exploration metrics of the module docstring, flat (``coverage_at_0.05``, ``coverage_rel_0.01``, ...).

    ``points``: the reconstruction (ground-truth frame, metres); ``reference``: the reference surface points;
    ``surface_distance``: each point's distance to the true surfaces; ``d0_m``: the scene scale (metres);
    ``seen``: per reference point, whether a true frame saw it (``seen_mask``), or per point of the subset
    ``seen_index`` of the reference (an evenly strided sample, for speed); ``region``: per reference point, whether
    it belongs to the object region (table-tops), or None."""
    if d0_m <= 0:
        raise ValueError(f"d0_m must be positive (the scene scale in metres), got {d0_m}")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    reference = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    rel = np.asarray(THRESHOLDS_REL) * d0_m
    auc_t = np.arange(1, AUC_STEPS + 1) / AUC_STEPS * rel.max()
    t_max = max(max(THRESHOLDS_M), float(rel.max()))
    if len(points) and len(reference):  # one bounded query serves every threshold
        d_ref, _ = cKDTree(points).query(reference, k=1, distance_upper_bound=t_max * (1 + 1e-9), workers=-1)
    else:
        d_ref = np.full(len(reference), np.inf)
    dist = np.asarray(surface_distance, dtype=np.float64)

    def cov(t: float, mask: np.ndarray | None = None) -> float:
        d = d_ref if mask is None else d_ref[mask]
        return float((d <= t).mean()) if len(d) else 0.0

    def prec(t: float) -> float:
        return float((dist <= t).mean()) if len(dist) else 0.0

    out: dict[str, float] = {"d0_m": float(d0_m), "precision": prec(THRESHOLD_M)}
    for t in THRESHOLDS_M:
        out[f"coverage_at_{t:.2f}"] = cov(t)
        out[f"fscore_at_{t:.2f}"] = _fscore(prec(t), cov(t))
    for f, t in zip(THRESHOLDS_REL, rel):
        out[f"coverage_rel_{f:g}"] = cov(t)
        out[f"fscore_rel_{f:g}"] = _fscore(prec(t), cov(t))
    out["coverage_auc"] = float(np.mean([cov(t) for t in auc_t]))
    sample = np.arange(len(reference)) if seen_index is None else np.asarray(seen_index)
    if seen is not None:
        seen = np.asarray(seen, dtype=bool)
        if seen.shape != (len(sample),):
            raise ValueError(f"seen must hold one flag per reference point or per seen_index ({len(sample)}), "
                             f"got {seen.shape}")
        out["seen"] = float(seen.mean()) if len(seen) else 0.0
    if region is not None:
        region = np.asarray(region, dtype=bool)
        if region.shape != (len(reference),):
            raise ValueError(f"region must hold one flag per reference point ({len(reference)}), got {region.shape}")
        out["object_coverage"] = cov(THRESHOLD_M, region)
        for t in THRESHOLDS_M:
            out[f"object_coverage_at_{t:.2f}"] = cov(t, region)
        if seen is not None:
            sub = region[sample]
            out["object_seen"] = float(seen[sub].mean()) if sub.any() else 0.0
    return out


def seen_mask(reference: np.ndarray, c2ws: np.ndarray, K: np.ndarray, depths, tolerance_m: float = 0.02,
              tolerance_rel: float = 0.03) -> np.ndarray:
    """Per reference point ``[M, 3]``: whether some camera (``c2ws`` ``[T, 4, 4]``, one intrinsics ``K``, the true
    z-depth ``depths[i]`` ``[H, W]`` of what camera i shows, 0 = nothing) saw it: it projects into the image in
    front of the camera, and its depth is within ``tolerance_m + tolerance_rel * depth`` of the true depth at its
    pixel (not hidden behind a nearer surface; the tolerance absorbs the pixel quantisation of oblique surfaces)."""
    ref = np.asarray(reference, dtype=np.float32).reshape(-1, 3)
    out = np.zeros(len(ref), dtype=bool)
    K = np.asarray(K, dtype=np.float64)
    for c2w, depth in zip(np.asarray(c2ws, dtype=np.float64), depths):
        todo = np.flatnonzero(~out)  # only points no camera has seen yet
        if not len(todo):
            break
        depth = np.asarray(depth)
        H, W = depth.shape
        R, t = c2w[:3, :3].astype(np.float32), c2w[:3, 3].astype(np.float32)
        pc = (ref[todo] - t) @ R
        z = pc[:, 2]
        front = z > 1e-6
        todo, pc, z = todo[front], pc[front], z[front]
        u = np.floor(K[0, 0] * pc[:, 0] / z + K[0, 2]).astype(np.int64)
        v = np.floor(K[1, 1] * pc[:, 1] / z + K[1, 2]).astype(np.int64)
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        todo, z, u, v = todo[ok], z[ok], u[ok], v[ok]
        d = depth[v, u]
        out[todo[(d > 0) & (np.abs(z - d) <= tolerance_m + tolerance_rel * d)]] = True
    return out


def region_mask(scene, reference: np.ndarray, prefixes: tuple[str, ...], within_m: float = 0.01) -> np.ndarray:
    """Per reference point: within ``within_m`` of one of ``scene``'s objects whose name starts with one of
    ``prefixes`` (a simulated scene's objects: e.g. the table and what stands on it)."""
    import open3d as o3d

    objs = [o for o in scene.objects if o.name.startswith(prefixes)]
    ref = np.asarray(reference, dtype=np.float32).reshape(-1, 3)
    if not objs or not len(ref):
        return np.zeros(len(ref), dtype=bool)
    rc = o3d.t.geometry.RaycastingScene()
    for o in objs:
        rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(o.mesh))
    return rc.compute_distance(o3d.core.Tensor(ref)).numpy() <= within_m


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
    # deferred: open3d (the simulation's renderer) loads only for ground-truth scenes
    from navcrafter.models.simulation.render import render_many

    w, h = intrinsics.width, intrinsics.height
    s = min(1.0, max_side / max(w, h))
    K = intrinsics.resize(max(1, round(w * s)), max(1, round(h * s))) if s < 1.0 else intrinsics
    c2w_gt = np.asarray(c2w_gt, dtype=np.float64).reshape(-1, 4, 4)
    r = render_many(scene, c2w_gt, K, colour=False)  # one cast: each frame's pixels as its own render's
    return np.array([float((hit & (depth < near_m)).mean()) > 0.5 for hit, depth in zip(r.hit, r.depth, strict=True)],
                    dtype=bool)


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



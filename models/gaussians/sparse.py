"""Sparse-view evaluation of a 3DGS fit (the maths of ``benchmarks/fitting.py --views``): which views to train on,
which test pixels can be judged, and how to compare renders with the truth when the fit's cameras are estimates.

* :func:`farthest_views`: V training views by farthest-point sampling of the camera centres (the standard way to
  spread a few views over a capture, e.g. the sparse-view protocols of RegNeRF / DropGaussian's LLFF splits pick
  evenly spaced views; farthest-point is the same idea for an irregular path).
* :func:`visibility_mask`: the test pixels whose true surface point some training view saw: the point (test
  pixel unprojected with the true depth at the true camera) projects inside a training view, in front of it, and
  its depth there agrees with that view's true depth to ``rel_tol`` (else something nearer hides it).
  Sky pixels (depth 0) are never in the mask.
* :func:`align_to_estimated`: a similarity (Umeyama) from matched estimated to true points, and the true test
  poses mapped into the estimated frame, so a model fitted on estimated cameras is rendered where the true test
  camera is (pose error removed); rendered depth times the similarity's scale is in true units. The points are
  the training frames' camera centres and :func:`depth_pairs`, their pixels lifted with estimated and true depth
  and camera: centres alone leave the similarity undetermined when the cameras barely move (turns in place).
* :func:`masked_psnr`, :func:`masked_ssim`, :func:`depth_absrel`: scores over a pixel mask.
* :func:`converged`: whether a curve changed less than ``tol`` (relative) over its last fraction.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.camera.cameras import camera_directions, umeyama, unproject_depth
from navcrafter.models.metrics.image import SSIM_WINDOW, ssim_map


def farthest_views(centres: np.ndarray, n: int, first: int = 0) -> np.ndarray:
    """Indices of ``n`` of the camera ``centres`` [N, 3] by greedy farthest-point sampling from ``first`` (each
    next view is the one farthest from every view already chosen; ties: the lowest index). Sorted."""
    c = np.asarray(centres, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centres must be [N, 3], got {c.shape}")
    if not 1 <= n <= len(c):
        raise ValueError(f"cannot choose {n} views from {len(c)} cameras (1 <= n <= {len(c)})")
    chosen = [int(first)]
    dist = np.linalg.norm(c - c[first], axis=1)
    while len(chosen) < n:
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(c - c[nxt], axis=1))
    return np.sort(np.asarray(chosen, dtype=np.int64))


def visibility_mask(depth: np.ndarray, c2w: np.ndarray, K: np.ndarray, train_depth: np.ndarray,
                    train_c2w: np.ndarray, train_K: np.ndarray, rel_tol: float = 0.03) -> np.ndarray:
    """[H, W] bool: the pixels of a test view (true z-depth ``depth`` [H, W], 0 = sky; camera ``c2w``, ``K``)
    whose surface point some training view (true depths [V, h, w], cameras [V, 4, 4], [V, 3, 3]) saw unoccluded:
    it projects inside that view with positive depth z, and ``|z - train_depth| <= rel_tol * z`` at the pixel it
    lands on (nearest pixel). All depths and poses in one frame and unit."""
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    train_depth = np.asarray(train_depth, dtype=np.float64)
    if train_depth.ndim != 3 or len(train_depth) != len(train_c2w) or len(train_K) != len(train_c2w):
        raise ValueError(f"train_depth [V, h, w], train_c2w [V, 4, 4] and train_K [V, 3, 3] must agree, got "
                         f"{train_depth.shape}, {np.shape(train_c2w)}, {np.shape(train_K)}")
    surface = depth > 0
    pts = (camera_directions(K, H, W) * depth[..., None])[surface]  # camera frame
    c2w = np.asarray(c2w, dtype=np.float64)
    world = pts @ c2w[:3, :3].T + c2w[:3, 3]
    seen = np.zeros(len(world), dtype=bool)
    h, w = train_depth.shape[1:]
    for d, T, Kt in zip(train_depth, np.asarray(train_c2w, dtype=np.float64), np.asarray(train_K, dtype=np.float64)):
        x = (world - T[:3, 3]) @ T[:3, :3]  # world -> camera (R^T (p - t))
        z = x[:, 2]
        front = z > 1e-9
        uvw = x @ Kt.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvw[:, 0] / z, uvw[:, 1] / z
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        j = np.clip(np.floor(np.where(inside, u, 0)).astype(np.int64), 0, w - 1)
        i = np.clip(np.floor(np.where(inside, v, 0)).astype(np.int64), 0, h - 1)
        dt = d[i, j]
        seen |= inside & (dt > 0) & (np.abs(z - dt) <= rel_tol * np.abs(z))
    out = np.zeros((H, W), dtype=bool)
    out[surface] = seen
    return out


def align_to_estimated(est_centres: np.ndarray, true_centres: np.ndarray, true_c2w: np.ndarray
                       ) -> tuple[np.ndarray, float, dict]:
    """Umeyama similarity ``true ~ s R est + t`` from matched points [N, 3] (camera centres, :func:`depth_pairs`),
    and ``true_c2w`` [M, 4, 4]
    mapped into the estimated frame (rotation ``R^T R_c``, centre ``R^T (t_c - t) / s``). Returns (those poses,
    s, {"scale", "rmse"} with the alignment's residual RMS in true units). Depth rendered at the mapped poses is
    ``1 / s`` of true depth."""
    s, R, t = umeyama(est_centres, true_centres, with_scale=True)
    resid = np.linalg.norm(s * np.asarray(est_centres) @ R.T + t - np.asarray(true_centres), axis=1)
    tc = np.asarray(true_c2w, dtype=np.float64)
    out = np.array(tc, copy=True)
    out[:, :3, :3] = R.T @ tc[:, :3, :3]
    out[:, :3, 3] = ((tc[:, :3, 3] - t) @ R) / s
    return out, float(s), {"scale": float(s), "rmse": float(np.sqrt(np.mean(resid**2)))}


def depth_pairs(est_depth: np.ndarray, est_c2w: np.ndarray, true_depth: np.ndarray, true_c2w: np.ndarray,
                K: np.ndarray, valid: np.ndarray | None = None, stride: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """One frame's pixels (each ``stride``-th row and column, ``valid`` [H, W], positive finite depth in both)
    lifted twice: with the estimated z-depth at the estimated camera and with the true z-depth at the true camera
    (intrinsics ``K`` for both). Returns matched points ``(est [M, 3], true [M, 3])`` for
    :func:`align_to_estimated`."""
    est_depth = np.asarray(est_depth, dtype=np.float64)
    true_depth = np.asarray(true_depth, dtype=np.float64)
    if est_depth.shape != true_depth.shape:
        raise ValueError(f"depth_pairs: estimated depth {est_depth.shape} and true depth {true_depth.shape} differ")
    both = np.isfinite(est_depth) & (est_depth > 0) & np.isfinite(true_depth) & (true_depth > 0)
    if valid is not None:
        both &= np.asarray(valid, dtype=bool)
    pe, ie = unproject_depth(est_depth, est_c2w, K, mask=both, stride=stride)
    pt, it = unproject_depth(true_depth, true_c2w, K, mask=both, stride=stride)
    if not np.array_equal(ie, it):  # the same mask and stride select the same pixels
        raise AssertionError("depth_pairs: the two liftings chose different pixels")
    return pe, pt


def masked_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, data_range: float = 1.0) -> float:
    """PSNR over the pixels of ``mask`` [H, W] (images [H, W, C]); NaN for an empty mask."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return float("nan")
    mse = float(np.mean((np.asarray(pred, dtype=np.float64)[mask] - np.asarray(gt, dtype=np.float64)[mask]) ** 2))
    return float(10 * np.log10(data_range**2 / max(mse, 1e-20)))


def masked_ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean of the SSIM map (``models.metrics.image``, valid region) over the pixels of ``mask`` whose window
    centre lies in that region; NaN when none does."""
    m = ssim_map(pred, gt)[0].mean(axis=-1)  # [H-10, W-10]
    r = SSIM_WINDOW // 2
    sub = np.asarray(mask, dtype=bool)[r:r + m.shape[0], r:r + m.shape[1]]
    return float(m[sub].mean()) if sub.any() else float("nan")


def depth_absrel(pred: np.ndarray, true: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean ``|pred - true| / true`` over ``mask`` and ``true > 0``; NaN when no pixel qualifies."""
    true = np.asarray(true, dtype=np.float64)
    sel = true > 0
    if mask is not None:
        sel &= np.asarray(mask, dtype=bool)
    if not sel.any():
        return float("nan")
    return float(np.mean(np.abs(np.asarray(pred, dtype=np.float64)[sel] - true[sel]) / true[sel]))


def converged(values: list[float] | np.ndarray, tol: float = 0.02) -> tuple[bool, float]:
    """(whether, relative change) of a curve sampled at increasing iterations: ``|v[-1] - v[-2]| / |v[-1]|``
    (the samples are taken at 80 % and 100 % of the fit, so this is the change over its last 20 %)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) < 2:
        raise ValueError("convergence needs at least two samples of the curve")
    change = float(abs(v[-1] - v[-2]) / max(abs(v[-1]), 1e-12))
    return change <= tol, change

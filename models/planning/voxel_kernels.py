"""Numba kernels of the explorer's voxel map (``explore.py``): carving free space with a depth map, and marching
the scoring rays through the map. The numpy versions they replace built [frames x rays x samples] arrays of every
sample (millions per planning call at paper sizes) and read the map for all of them, where a ray only needs its
samples up to the first occupied cell; these loops stop there and reduce as they go. Same arithmetic (the cell of a
point is the floor of its offset over the cell size), so the same cells up to floating-point ties."""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)

UNKNOWN, FREE, OCCUPIED = 0, 1, 2


@_jit
def carve(centres: np.ndarray, R: np.ndarray, t: np.ndarray, fx: float, fy: float, cx: float, cy: float,
          depth: np.ndarray, anchored: np.ndarray, use_anchored: bool, margin: float, free: np.ndarray,
          behind: np.ndarray) -> None:
    """For one view (camera-to-world rotation ``R``, position ``t``, pinhole ``fx, fy, cx, cy``, z-depth ``depth``
    [H, W], 0 = none): mark the cell ``centres`` [N, 3] it saw more than ``margin`` in front of its depth as ``free``
    (only where ``anchored`` when ``use_anchored``) and those more than ``margin`` behind it as ``behind``."""
    H, W = depth.shape
    for n in range(centres.shape[0]):
        a0, a1, a2 = centres[n, 0] - t[0], centres[n, 1] - t[1], centres[n, 2] - t[2]
        z = R[0, 2] * a0 + R[1, 2] * a1 + R[2, 2] * a2
        if z <= 1e-6:
            continue
        x = R[0, 0] * a0 + R[1, 0] * a1 + R[2, 0] * a2
        y = R[0, 1] * a0 + R[1, 1] * a1 + R[2, 1] * a2
        u = math.floor(fx * x / z + cx)
        w = math.floor(fy * y / z + cy)
        if u < 0 or u >= W or w < 0 or w >= H:
            continue
        d = depth[w, u]
        if d <= 0:
            continue
        if z > d + margin:
            behind[n] = True
        if z < d - margin and (not use_anchored or anchored[w, u]):
            free[n] = True


@_jit
def march(state: np.ndarray, size: int, origin: np.ndarray, voxel: float, rot: np.ndarray, pos: np.ndarray,
          unit: np.ndarray, dist: np.ndarray, weight: np.ndarray, group: np.ndarray,
          n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays ``unit`` [R, 3] (camera frame, unit length) of the frames (``rot`` [F, 3, 3], ``pos`` [F, 3]) sampled
    at distances ``dist`` [S] through the map (``state``, flat, ``size`` cells a side from ``origin``; outside it
    nothing blocks a ray). Per group of frames (``group`` [F], ids 0..n_groups-1, each group's frames contiguous):
    the sum over the
    unknown cells seen before each ray's first occupied cell of the largest ``weight`` [R, S] any of its samples
    gave that cell (a cell counts once per group); per frame: the share of rays that end on an occupied cell."""
    F, Rn, S = rot.shape[0], unit.shape[0], dist.shape[0]
    gain = np.zeros(n_groups)
    hit = np.zeros(F)
    best = np.zeros(size * size * size)
    stamp = np.full(size * size * size, -1, dtype=np.int64)
    for f in range(F):
        g = group[f]
        for r in range(Rn):
            d0 = rot[f, 0, 0] * unit[r, 0] + rot[f, 0, 1] * unit[r, 1] + rot[f, 0, 2] * unit[r, 2]
            d1 = rot[f, 1, 0] * unit[r, 0] + rot[f, 1, 1] * unit[r, 1] + rot[f, 1, 2] * unit[r, 2]
            d2 = rot[f, 2, 0] * unit[r, 0] + rot[f, 2, 1] * unit[r, 1] + rot[f, 2, 2] * unit[r, 2]
            for s in range(S):
                i = math.floor((pos[f, 0] + dist[s] * d0 - origin[0]) / voxel)
                j = math.floor((pos[f, 1] + dist[s] * d1 - origin[1]) / voxel)
                k = math.floor((pos[f, 2] + dist[s] * d2 - origin[2]) / voxel)
                if i < 0 or i >= size or j < 0 or j >= size or k < 0 or k >= size:
                    continue
                c = (i * size + j) * size + k
                st = state[c]
                if st == OCCUPIED:
                    hit[f] += 1.0
                    break
                if st == UNKNOWN:
                    w = weight[r, s]
                    if stamp[c] != g:
                        stamp[c] = g
                        best[c] = w
                        gain[g] += w
                    elif w > best[c]:
                        gain[g] += w - best[c]
                        best[c] = w
    return gain, hit / max(Rn, 1)


@_jit
def splat_depth(points: np.ndarray, w2c: np.ndarray, K: np.ndarray, height: int, width: int, point_size: float,
                max_radius: int, near: float) -> np.ndarray:
    """The z-buffer of ``reconstruction.pointrender.render_points`` without colours (its depth; > 0 = its mask): each
    point (world, float32 arithmetic as there) splatted as a square of (2r+1)^2 pixels, r = ceil(fx point_size / 2z
    - 1/2) clamped to [0, max_radius], every pixel keeping the nearest depth. A loop over the points instead of
    torch scatters and pools: the explorer renders the cloud into every lifted frame of every earlier clip
    (``explore.anchored_pixels``) on each planning call."""
    best = np.full((height, width), np.inf, dtype=np.float32)
    R = np.float32(max_radius)
    for n in range(points.shape[0]):
        p0, p1, p2 = np.float32(points[n, 0]), np.float32(points[n, 1]), np.float32(points[n, 2])
        x = w2c[0, 0] * p0 + w2c[0, 1] * p1 + w2c[0, 2] * p2 + w2c[0, 3]
        y = w2c[1, 0] * p0 + w2c[1, 1] * p1 + w2c[1, 2] * p2 + w2c[1, 3]
        z = w2c[2, 0] * p0 + w2c[2, 1] * p1 + w2c[2, 2] * p2 + w2c[2, 3]
        if not z > near:
            continue
        u = (K[0, 0] * x + K[0, 1] * y) / z + K[0, 2]
        v = K[1, 1] * y / z + K[1, 2]
        ix = math.floor(u)
        iy = math.floor(v)
        if ix < -max_radius or ix >= width + max_radius or iy < -max_radius or iy >= height + max_radius:
            continue
        r = int(min(max(math.ceil(K[0, 0] * np.float32(point_size) / (np.float32(2.0) * z) - np.float32(0.5)),
                        np.float32(0.0)), R))
        for a in range(max(iy - r, 0), min(iy + r + 1, height)):
            for b in range(max(ix - r, 0), min(ix + r + 1, width)):
                if z < best[a, b]:
                    best[a, b] = z
    return np.where(np.isfinite(best), best, np.float32(0.0))

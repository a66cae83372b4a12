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
def _pixel(c: np.ndarray, R: np.ndarray, t: np.ndarray, fx: float, fy: float, cx: float, cy: float, H: int,
           W: int) -> tuple[float, int, int]:
    """The z-depth of the point ``c`` [3] in the view (camera-to-world ``R``, position ``t``) and the pixel (u, w)
    it falls in; u = -1 when it is behind the camera or outside the image."""
    a0, a1, a2 = c[0] - t[0], c[1] - t[1], c[2] - t[2]
    z = R[0, 2] * a0 + R[1, 2] * a1 + R[2, 2] * a2
    if z <= 1e-6:
        return z, -1, -1
    x = R[0, 0] * a0 + R[1, 0] * a1 + R[2, 0] * a2
    y = R[0, 1] * a0 + R[1, 1] * a1 + R[2, 1] * a2
    u = math.floor(fx * x / z + cx)
    w = math.floor(fy * y / z + cy)
    if u < 0 or u >= W or w < 0 or w >= H:
        return z, -1, -1
    return z, u, w


@_jit
def _credit(c: int, g: int, w: float, stamp: np.ndarray, best: np.ndarray, gain: np.ndarray) -> None:
    """Cell ``c`` counts once per group ``g``, with the best weight any of the group's rays gave it."""
    if stamp[c] != g:
        stamp[c] = g
        best[c] = w
        gain[g] += w
    elif w > best[c]:
        gain[g] += w - best[c]
        best[c] = w


@_jit
def carve(centres: np.ndarray, R: np.ndarray, t: np.ndarray, fx: float, fy: float, cx: float, cy: float,
          depth: np.ndarray, anchored: np.ndarray, use_anchored: bool, margin: float, free: np.ndarray,
          behind: np.ndarray) -> None:
    """For one view (camera-to-world rotation ``R``, position ``t``, pinhole ``fx, fy, cx, cy``, z-depth ``depth``
    [H, W], 0 = none): mark the cell ``centres`` [N, 3] it saw more than ``margin`` in front of its depth as ``free``
    (only where ``anchored`` when ``use_anchored``) and those more than ``margin`` behind it as ``behind``."""
    H, W = depth.shape
    for n in range(centres.shape[0]):
        z, u, w = _pixel(centres[n], R, t, fx, fy, cx, cy, H, W)
        if u < 0:
            continue
        d = depth[w, u]
        if d <= 0:
            continue
        if z > d + margin:
            behind[n] = True
        if z < d - margin and (not use_anchored or anchored[w, u]):
            free[n] = True


@_jit
def observe(centres: np.ndarray, cells: np.ndarray, R: np.ndarray, t: np.ndarray, fx: float, fy: float, cx: float,
            cy: float, depth: np.ndarray, anchored: np.ndarray, use_anchored: bool, margin: float,
            zmin: np.ndarray) -> None:
    """For one view (as ``carve``): the smallest z-depth ``zmin`` [C] at which it saw each of the (occupied) cells
    ``cells`` [C] (flat indices into ``centres``): the cell projects onto a pixel whose depth is within ``margin``
    of the cell's (only pixels that are ``anchored`` when ``use_anchored``: copied, not invented, content)."""
    H, W = depth.shape
    for m in range(cells.shape[0]):
        z, u, w = _pixel(centres[cells[m]], R, t, fx, fy, cx, cy, H, W)
        if u < 0 or z >= zmin[m]:
            continue
        d = depth[w, u]
        if d <= 0 or abs(z - d) > margin:
            continue
        if use_anchored and not anchored[w, u]:
            continue
        zmin[m] = z


@_jit
def march(state: np.ndarray, size: int, origin: np.ndarray, voxel: float, rot: np.ndarray, pos: np.ndarray,
          unit: np.ndarray, dist: np.ndarray, weight: np.ndarray, group: np.ndarray,
          n_groups: int, prox: np.ndarray, acc: np.ndarray, revisit: float) -> tuple[np.ndarray, np.ndarray]:
    """Rays ``unit`` [R, 3] (camera frame, unit length) of the frames (``rot`` [F, 3, 3], ``pos`` [F, 3]) sampled
    at distances ``dist`` [S] through the map (``state``, flat, ``size`` cells a side from ``origin``; outside it
    nothing blocks a ray). Per group of frames (``group`` [F], ids 0..n_groups-1, each group's frames contiguous):
    the sum over the
    unknown cells seen before each ray's first occupied cell of the largest ``weight`` [R, S] any of its samples
    gave that cell, times the cell's ``prox`` [N] (how anchored its content will be: 1 everywhere = plain
    information gain; a cell counts once per group), plus ``revisit`` times the accuracy gained on the first
    occupied cell each ray meets: max(0, weight - ``acc`` [N]), ``acc`` the accuracy the cell was seen with so far
    (the largest over the group's rays, likewise once per group); per frame: the share of rays that end on an
    occupied cell."""
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
                    if revisit > 0.0:
                        w = weight[r, s] - acc[c]
                        if w > 0.0:
                            _credit(c, g, revisit * w, stamp, best, gain)
                    break
                if st == UNKNOWN:
                    _credit(c, g, weight[r, s] * prox[c], stamp, best, gain)
    return gain, hit / max(Rn, 1)

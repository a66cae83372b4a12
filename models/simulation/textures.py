"""Procedural materials for simulated scenes, evaluated at ray hit points.

Textures are functions of the 3D hit position (projected onto the plane of the dominant normal axis,
i.e. tri-planar without blending), so they need no UV unwrapping and are identical from every
viewpoint, which is what multi-view consistency (and later COLMAP in evaluation) needs.
All noise is hash-based lattice noise: deterministic, vectorised, seed-able.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

PATTERNS = ("plain", "checker", "stripes", "wood", "brick", "tiles", "windows", "noise")


@dataclass(frozen=True)
class Material:
    """A procedural surface: ``pattern`` mixes ``color_a`` and ``color_b`` (sRGB in [0, 1])."""

    pattern: str
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float]
    scale: float = 0.5  # characteristic feature size in scene units (metres)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ValueError(f"unknown pattern {self.pattern!r}; choose from {PATTERNS}")
        if self.scale <= 0:
            raise ValueError("material scale must be positive")


def _hash2(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Integer lattice hash to [0, 1)."""
    h = (ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263 + seed * 2147483647) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(0x1000000)


def value_noise(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1)."""
    return fbm(x, y, seed, octaves=1)


def fbm(x: np.ndarray, y: np.ndarray, seed: int, octaves: int = 4) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    shape = np.broadcast_shapes(x.shape, y.shape)
    x, y = np.broadcast_to(x, shape).ravel(), np.broadcast_to(y, shape).ravel()
    return _fbm(x, y, int(seed), int(octaves)).reshape(shape)


# The noise in one numba loop (the textures of a frame are most of the simulated synthesizer's time). Same
# arithmetic as the numpy form it replaced, operation by operation (IEEE, no fast-math: the same bits), and the
# lattice hash in wrapping int64 as numpy computes it: ``_hash2`` above is the array form of the same hash (the
# brick, tile and window patterns call it on arrays; the tests check the noise against it bit for bit).
@numba.njit(cache=True, nogil=True)
def _hash1(ix: float, iy: float, seed: int) -> float:
    h = (np.int64(ix) * 374761393 + np.int64(iy) * 668265263 + seed * 2147483647) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return float(h & 0xFFFFFF) / float(0x1000000)


@numba.njit(cache=True, nogil=True)
def _fbm(x: np.ndarray, y: np.ndarray, seed: int, octaves: int) -> np.ndarray:
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        total = 0.0
        amp, norm, freq = 1.0, 0.0, 1.0
        for o in range(octaves):
            xf, yf = x[i] * freq, y[i] * freq
            ix, iy = math.floor(xf), math.floor(yf)
            fx, fy = xf - ix, yf - iy
            sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
            s = seed + 97 * o
            a = _hash1(ix, iy, s)
            b = _hash1(ix + 1, iy, s)
            c = _hash1(ix, iy + 1, s)
            d = _hash1(ix + 1, iy + 1, s)
            total += amp * ((a * (1 - sx) + b * sx) * (1 - sy) + (c * (1 - sx) + d * sx) * sy)
            norm += amp
            amp *= 0.5
            freq *= 2.03
        out[i] = total / norm
    return out


def planar_coords(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2D coordinates on the plane perpendicular to each point's dominant normal axis."""
    axis = np.argmax(np.abs(normals), axis=1)
    u = np.where(axis == 0, points[:, 1], points[:, 0])
    v = np.where(axis == 2, points[:, 1], points[:, 2])
    return u, v


def albedo(material: Material, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Surface colour ``[N, 3]`` in [0, 1] of ``material`` at world ``points`` with ``normals``."""
    if len(points) == 0:
        return np.zeros((0, 3))
    u, v = planar_coords(points, normals)
    s, seed = material.scale, material.seed
    a = np.asarray(material.color_a)
    b = np.asarray(material.color_b)
    grain = fbm(u / (0.15 * s), v / (0.15 * s), seed + 11)  # fine detail present everywhere
    p = material.pattern
    if p == "plain":
        mix = 0.25 * fbm(u / s, v / s, seed)
    elif p == "noise":
        mix = fbm(u / s, v / s, seed, octaves=5)
    elif p == "checker":
        mix = ((np.floor(u / s) + np.floor(v / s)) % 2).astype(np.float64)
    elif p == "stripes":
        mix = (np.floor(u / s) % 2).astype(np.float64)
    elif p == "wood":
        warp = 0.8 * fbm(u / s, v / (4 * s), seed)
        rings = np.sin((v / s * 6.0 + warp * 6.0) * np.pi)
        mix = 0.5 + 0.5 * rings
    elif p == "brick":
        h, w = 0.5 * s, s
        row = np.floor(v / h)
        uu = u / w + 0.5 * (row % 2)
        fu, fv = uu - np.floor(uu), v / h - row
        mortar = (fu < 0.06) | (fv < 0.1)
        jitter = _hash2(np.floor(uu), row, seed) * 0.3
        mix = np.where(mortar, 1.0, jitter)
    elif p == "tiles":
        fu, fv = u / s - np.floor(u / s), v / s - np.floor(v / s)
        grout = (fu < 0.04) | (fv < 0.04)
        mix = np.where(grout, 1.0, 0.25 * _hash2(np.floor(u / s), np.floor(v / s), seed))
    elif p == "windows":
        fu, fv = u / s - np.floor(u / s), v / (1.3 * s) - np.floor(v / (1.3 * s))
        window = (fu > 0.25) & (fu < 0.75) & (fv > 0.2) & (fv < 0.75)
        lit = _hash2(np.floor(u / s), np.floor(v / (1.3 * s)), seed) > 0.8
        mix = np.where(window, np.where(lit, 0.55, 1.0), 0.15 * fbm(u / s, v / s, seed))
    else:  # pragma: no cover - guarded in Material
        raise AssertionError(p)
    return _mix(a.astype(np.float64), b.astype(np.float64), np.ascontiguousarray(mix, dtype=np.float64), grain)


@numba.njit(cache=True, nogil=True)
def _mix(a: np.ndarray, b: np.ndarray, mix: np.ndarray, grain: np.ndarray) -> np.ndarray:
    """``clip((a (1 - mix) + b mix) (0.88 + 0.24 grain), 0, 1)`` ``[N, 3]``, in one loop (the numpy form's operations
    in its order: the same bits)."""
    out = np.empty((mix.shape[0], 3))
    for i in range(mix.shape[0]):
        g = 0.88 + 0.24 * grain[i]
        for c in range(3):
            v = (a[c] * (1 - mix[i]) + b[c] * mix[i]) * g
            if v < 0.0:  # np.clip: NaN stays NaN
                v = 0.0
            elif v > 1.0:
                v = 1.0
            out[i, c] = v
    return out

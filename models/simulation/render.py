"""Ground-truth renderer of simulated scenes (Open3D ``RaycastingScene``), any pinhole camera.

Produces colour (procedural albedo, Lambert shading from one light with ray-traced hard shadows,
sky gradient outdoors, optional supersampling), z-depth, world normals and the hit mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import open3d as o3d

from navcrafter.models.camera.cameras import Intrinsics, world_rays
from navcrafter.models.simulation.scenes import SimScene
from navcrafter.models.simulation.textures import albedo

SKY_HORIZON = np.array([0.78, 0.86, 0.95])
SKY_ZENITH = np.array([0.35, 0.55, 0.85])


@dataclass
class Render:
    rgb: np.ndarray  # [H, W, 3] uint8
    depth: np.ndarray  # [H, W] float32 z-depth; 0 where no surface was hit
    normal: np.ndarray  # [H, W, 3] float32 world-frame unit normals facing the camera; 0 on misses
    hit: np.ndarray  # [H, W] bool


def _cast(scene: SimScene, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
    rays = np.empty((int(np.prod(np.shape(origins)[:-1])), 6), dtype=np.float32)  # the float32 rays, filled in place
    rays[:, :3] = np.reshape(origins, (-1, 3))
    rays[:, 3:] = np.reshape(dirs, (-1, 3))
    return _cast_rays(scene, rays)


def _cast_rays(scene: SimScene, rays: np.ndarray) -> dict[str, np.ndarray]:
    rc, _ = scene.raycasting()
    ans = rc.cast_rays(o3d.core.Tensor(rays))
    return {k: v.numpy() for k, v in ans.items()}


# The per-ray arithmetic of shading in numba loops (most of the simulated synthesizer's time was numpy passes over
# arrays of millions of rays). Each loop does the operations of the numpy form it replaced in the same order and
# precision (IEEE, no fast-math; sums of three products left to right, as numpy's reductions over a length-3 axis
# add them): the same bits (tests/models/simulation/test_simulation.py checks them against the numpy form).
@numba.njit(cache=True, nogil=True)
def _hit_geometry(origins: np.ndarray, dirs: np.ndarray, t: np.ndarray, normals: np.ndarray,
                  idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hit points ``o + d t`` and unit normals facing the ray (two-sided) ``[M, 3]`` float64 of the rays ``idx``."""
    m = idx.shape[0]
    p = np.empty((m, 3))
    n = np.empty((m, 3))
    for j in range(m):
        i = idx[j]
        tt = np.float64(t[i])
        d0, d1, d2 = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        p[j, 0] = origins[i, 0] + d0 * tt
        p[j, 1] = origins[i, 1] + d1 * tt
        p[j, 2] = origins[i, 2] + d2 * tt
        a0, a1, a2 = np.float64(normals[i, 0]), np.float64(normals[i, 1]), np.float64(normals[i, 2])
        norm = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        if norm < 1e-12:  # np.maximum(norm, 1e-12): NaN stays NaN
            norm = 1e-12
        a0, a1, a2 = a0 / norm, a1 / norm, a2 / norm
        f = -1.0 if a0 * d0 + a1 * d1 + a2 * d2 > 0 else 1.0
        n[j, 0], n[j, 1], n[j, 2] = a0 * f, a1 * f, a2 * f
    return p, n


@numba.njit(cache=True, nogil=True)
def _lambert(p: np.ndarray, n: np.ndarray, vector: np.ndarray, point: bool
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lambert factor ``[M]`` (clipped cosine x attenuation), the distance to the light (inf for the sun) and the
    float32 shadow rays ``[M, 6]`` (from 2 mm off the surface towards the light) of hit points ``p``, normals
    ``n``; ``vector``: the light's position (``point``) or the direction towards the sun."""
    m = p.shape[0]
    lam = np.empty(m)
    dist = np.empty(m)
    rays = np.empty((m, 6), dtype=np.float32)
    for j in range(m):
        if point:
            l0, l1, l2 = vector[0] - p[j, 0], vector[1] - p[j, 1], vector[2] - p[j, 2]
            dd = np.sqrt(l0 * l0 + l1 * l1 + l2 * l2)
            l0, l1, l2 = l0 / dd, l1 / dd, l2 / dd
            atten = 1.0 / (1.0 + 0.04 * (dd * dd))
        else:
            l0, l1, l2 = vector[0], vector[1], vector[2]
            dd = np.inf
            atten = 1.0
        c = n[j, 0] * l0 + n[j, 1] * l1 + n[j, 2] * l2
        if c < 0.0:  # np.clip(c, 0, None): NaN stays NaN
            c = 0.0
        lam[j] = c * atten
        dist[j] = dd
        for k in range(3):
            rays[j, k] = np.float32(p[j, k] + n[j, k] * 2e-3)
        rays[j, 3], rays[j, 4], rays[j, 5] = np.float32(l0), np.float32(l1), np.float32(l2)
    return lam, dist, rays


@numba.njit(cache=True, nogil=True)
def _lit(colour: np.ndarray, idx: np.ndarray, alb: np.ndarray, lam: np.ndarray, dist: np.ndarray,
         shadow_t: np.ndarray, ambient: float, strength: float) -> None:
    """``colour[idx] = alb * (ambient + strength * lam)``, ``lam`` 0 where the shadow ray hit a surface before the
    light (``shadow_t``: its hit distances, empty for no shadows)."""
    shadows = shadow_t.shape[0] > 0
    for j in range(idx.shape[0]):
        lj = lam[j]
        if shadows and np.float64(shadow_t[j]) < dist[j] - 1e-2:
            lj = 0.0
        k = ambient + strength * lj
        for c in range(3):
            colour[idx[j], c] = alb[j, c] * k


@numba.njit(cache=True, nogil=True)
def _facing_normals(normals: np.ndarray, dirs: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit float32 normals facing the rays (0 on misses) and z-depth (0 on misses) of a cast's rays."""
    m = t.shape[0]
    out = np.zeros((m, 3), dtype=np.float32)
    depth = np.zeros(m, dtype=np.float32)
    tiny = np.float32(1e-12)
    for i in range(m):
        if not np.isfinite(t[i]):
            continue
        depth[i] = t[i]
        a0, a1, a2 = normals[i, 0], normals[i, 1], normals[i, 2]
        norm = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        if norm < tiny:
            norm = tiny
        a0, a1, a2 = a0 / norm, a1 / norm, a2 / norm
        s = np.float64(a0) * dirs[i, 0] + np.float64(a1) * dirs[i, 1] + np.float64(a2) * dirs[i, 2]
        f = np.float32(-1.0) if s > 0 else np.float32(1.0)
        out[i, 0], out[i, 1], out[i, 2] = a0 * f, a1 * f, a2 * f
    return out, depth


def _shade(scene: SimScene, origins: np.ndarray, dirs: np.ndarray, shadows: bool,
           ans: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """Linear-light colour ``[N, 3]`` for flat ray arrays (``ans``: their cast, when already made)."""
    ans = _cast(scene, origins, dirs) if ans is None else ans
    if hasattr(scene, "shade_hits"):  # a world from a scan: its own colour (models/simulation/worlds)
        return scene.shade_hits(ans, origins, dirs)
    t = ans["t_hit"]
    hit = np.isfinite(t)
    colour = np.zeros((len(t), 3))
    if scene.sky:  # the misses' sky colour (each ray's on its own: the hits' are overwritten below)
        miss = np.flatnonzero(~hit)
        dm = dirs[miss]
        dn = dm / np.linalg.norm(dm, axis=1, keepdims=True)
        elev = np.clip(dn[:, 2], 0.0, 1.0)[:, None] ** 0.6
        colour[miss] = SKY_HORIZON * (1 - elev) + SKY_ZENITH * elev
    if not hit.any():
        return colour
    _, mat_of_geom = scene.raycasting()
    idx = np.flatnonzero(hit)
    p, n = _hit_geometry(np.ascontiguousarray(origins, dtype=np.float64), np.ascontiguousarray(dirs, dtype=np.float64),
                         t, ans["primitive_normals"], idx)
    mats = mat_of_geom[ans["geometry_ids"][idx].astype(np.int64)]
    alb = np.empty((len(idx), 3))
    for m in np.unique(mats):
        sel = mats == m
        alb[sel] = albedo(scene.materials[m], p[sel], n[sel])
    light = scene.light
    lam, dist, shadow_rays = _lambert(p, n, np.asarray(light.vector, dtype=np.float64), light.kind != "sun")
    shadow_t = _cast_rays(scene, shadow_rays)["t_hit"] if shadows else np.zeros(0, dtype=np.float32)
    _lit(colour, idx, alb, lam, dist, shadow_t, float(light.ambient), float(light.strength))
    return colour


def render(scene: SimScene, c2w: np.ndarray, intrinsics: Intrinsics, supersample: int = 1,
           shadows: bool = True, colour: bool = True) -> Render:
    """Render ``scene`` from an OpenCV camera-to-world pose in the scene's ground-truth frame.

    ``colour=False`` skips shading (``rgb`` is all zeros): depth, normals and hits only.
    """
    r = render_many(scene, np.asarray(c2w)[None], intrinsics, supersample, shadows, colour)
    return Render(rgb=r.rgb[0], depth=r.depth[0], normal=r.normal[0], hit=r.hit[0])


def render_many(scene: SimScene, c2w: np.ndarray, intrinsics: Intrinsics, supersample: int = 1,
                shadows: bool = True, colour: bool = True, pixels: np.ndarray | None = None,
                max_rays: int = 1 << 21) -> Render:
    """``render`` from every pose of ``c2w [T, 4, 4]`` at once: a ``Render`` of ``[T, H, W, ...]`` arrays.

    The rays of many frames go to Open3D in one cast (at most ``max_rays`` rays a cast, frames whole, to bound
    memory), and are shaded together. ``pixels [T, H, W]`` (bool): render only these pixels (the rest come out
    as misses: black, depth 0); each pixel's values are those of the full render (every ray is cast and shaded
    on its own).
    """
    H, W = intrinsics.height, intrinsics.width
    c2w = np.asarray(c2w)
    T = len(c2w)
    ss = max(int(supersample), 1)
    rgb = np.zeros((T, H, W, 3), dtype=np.uint8)
    depth = np.zeros((T, H, W), dtype=np.float32)
    normal = np.zeros((T, H, W, 3), dtype=np.float32)
    hit = np.zeros((T, H, W), dtype=bool)
    Ks = intrinsics.resize(W * ss, H * ss) if ss > 1 else intrinsics
    step = max(1, max_rays // (H * W * ss * ss))
    for a in range(0, T, step):
        b = min(a + step, T)
        rays = [world_rays(c2w[i], intrinsics.K, H, W) for i in range(a, b)]
        o = np.stack([r[0] for r in rays]).reshape(-1, 3)
        d = np.stack([r[1] for r in rays]).reshape(-1, 3)
        sel = slice(None) if pixels is None else np.flatnonzero(pixels[a:b])
        o, d = o[sel], d[sel]
        ans = _cast(scene, o, d)
        t = ans["t_hit"]
        h = np.isfinite(t)
        n, z = _facing_normals(ans["primitive_normals"], np.ascontiguousarray(d, dtype=np.float64), t)
        hit[a:b].reshape(-1)[sel] = h
        depth[a:b].reshape(-1)[sel] = z  # dirs have camera z = 1: t is z
        normal[a:b].reshape(-1, 3)[sel] = n
        if not colour:
            continue
        if ss > 1:
            sub = [world_rays(c2w[i], Ks.K, Ks.height, Ks.width) for i in range(a, b)]
            so = np.stack([r[0] for r in sub])  # [n, H ss, W ss, 3]
            sd = np.stack([r[1] for r in sub])
            want = np.ones(so.shape[:3], dtype=bool) if pixels is None else \
                np.repeat(np.repeat(pixels[a:b], ss, axis=1), ss, axis=2)
            col = np.zeros(so.shape)
            col[want] = _shade(scene, so[want], sd[want], shadows)
            col = np.stack([c.reshape(H, ss, W, ss, 3).mean(axis=(1, 3)) for c in col]).reshape(-1, 3)[sel]
        else:
            col = _shade(scene, o, d, shadows, ans)
        rgb[a:b].reshape(-1, 3)[sel] = (np.clip(col, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return Render(rgb=rgb, depth=depth, normal=normal, hit=hit)


def photo_finish(rgb: np.ndarray, rng: np.random.Generator, noise: float = 2.0,
                 vignette: float = 0.25) -> np.ndarray:
    """Make a render look more like a photo: lens vignetting and sensor noise."""
    H, W, _ = rgb.shape
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - W / 2) / (W / 2)) ** 2 + ((yy - H / 2) / (H / 2)) ** 2
    gain = 1.0 - vignette * r2 / 2
    out = rgb.astype(np.float64) * gain[..., None] + rng.normal(0, noise, rgb.shape)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)

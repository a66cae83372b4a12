"""Ground-truth renderer of simulated scenes (Open3D ``RaycastingScene``), any pinhole camera.

Produces colour (procedural albedo, Lambert shading from one light with ray-traced hard shadows,
sky gradient outdoors, optional supersampling), z-depth, world normals and the hit mask.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    rc, _ = scene.raycasting()
    rays = np.concatenate([origins, dirs], axis=-1).reshape(-1, 6).astype(np.float32)
    ans = rc.cast_rays(o3d.core.Tensor(rays))
    return {k: v.numpy() for k, v in ans.items()}


def _shade(scene: SimScene, origins: np.ndarray, dirs: np.ndarray, shadows: bool,
           ans: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """Linear-light colour ``[N, 3]`` for flat ray arrays (``ans``: their cast, when already made)."""
    ans = _cast(scene, origins, dirs) if ans is None else ans
    if hasattr(scene, "shade_hits"):  # a world from a scan: its own colour (models/simulation/worlds)
        return scene.shade_hits(ans, origins, dirs)
    t = ans["t_hit"]
    hit = np.isfinite(t)
    colour = np.empty((len(t), 3))
    if scene.sky:
        dn = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        elev = np.clip(dn[:, 2], 0.0, 1.0)[:, None] ** 0.6
        colour[:] = SKY_HORIZON * (1 - elev) + SKY_ZENITH * elev
    else:
        colour[:] = 0.0
    if not hit.any():
        return colour
    _, mat_of_geom = scene.raycasting()
    idx = np.flatnonzero(hit)
    p = origins[idx] + dirs[idx] * t[idx, None]
    n = ans["primitive_normals"][idx].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    n *= np.where((n * dirs[idx]).sum(1, keepdims=True) > 0, -1.0, 1.0)  # two-sided
    mats = mat_of_geom[ans["geometry_ids"][idx].astype(np.int64)]
    alb = np.empty((len(idx), 3))
    for m in np.unique(mats):
        sel = mats == m
        alb[sel] = albedo(scene.materials[m], p[sel], n[sel])
    light = scene.light
    if light.kind == "sun":
        to_l = np.broadcast_to(np.asarray(light.vector, dtype=np.float64), p.shape)
        dist = np.full(len(p), np.inf)
        atten = np.ones(len(p))
    else:
        to_l = np.asarray(light.vector, dtype=np.float64) - p
        dist = np.linalg.norm(to_l, axis=1)
        to_l = to_l / dist[:, None]
        atten = 1.0 / (1.0 + 0.04 * dist**2)
    lam = np.clip((n * to_l).sum(1), 0.0, None) * atten
    if shadows:
        sh = _cast(scene, p + n * 2e-3, to_l)["t_hit"]
        lam = np.where(sh < dist - 1e-2, 0.0, lam)
    colour[idx] = alb * (light.ambient + light.strength * lam)[:, None]
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
        n = ans["primitive_normals"].astype(np.float32)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        n *= np.where((n * d).sum(-1, keepdims=True) > 0, -1.0, 1.0).astype(np.float32)
        n[~h] = 0.0
        hit[a:b].reshape(-1)[sel] = h
        depth[a:b].reshape(-1)[sel] = np.where(h, t, 0.0).astype(np.float32)  # dirs have camera z = 1: t is z
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

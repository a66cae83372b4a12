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


def _shade(scene: SimScene, origins: np.ndarray, dirs: np.ndarray, shadows: bool) -> np.ndarray:
    """Linear-light colour ``[N, 3]`` for flat ray arrays."""
    ans = _cast(scene, origins, dirs)
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
    H, W = intrinsics.height, intrinsics.width
    o, d = world_rays(c2w, intrinsics.K, H, W)
    ans = _cast(scene, o, d)
    t = ans["t_hit"].reshape(H, W)
    hit = np.isfinite(t)
    depth = np.where(hit, t, 0.0).astype(np.float32)  # directions have camera z = 1: t is z-depth
    normal = ans["primitive_normals"].reshape(H, W, 3).astype(np.float32)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    normal *= np.where((normal * d).sum(-1, keepdims=True) > 0, -1.0, 1.0).astype(np.float32)
    normal[~hit] = 0.0
    if not colour:
        col = np.zeros((H, W, 3))
    elif supersample > 1:
        Ks = intrinsics.resize(W * supersample, H * supersample)
        os_, ds = world_rays(c2w, Ks.K, Ks.height, Ks.width)
        col = _shade(scene, os_.reshape(-1, 3), ds.reshape(-1, 3), shadows)
        col = col.reshape(H, supersample, W, supersample, 3).mean(axis=(1, 3))
    else:
        col = _shade(scene, o.reshape(-1, 3), d.reshape(-1, 3), shadows).reshape(H, W, 3)
    rgb = (np.clip(col, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
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

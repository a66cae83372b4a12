"""A vectorised, z-buffered point-cloud renderer (CPU, torch scatter operations).

Each point is splatted as a square of ``2r+1`` pixels, where ``r`` follows from its world-space
size and its depth (``r = ceil(f * point_size / (2 z) - 1/2)``, at most ``max_radius``), so a
fused cloud renders without gaps between neighbouring points. A z-buffer keeps the nearest point
per pixel; ties go to the lowest point index, so results are deterministic. Used for the planner's
visibility masks and for renders of the cloud along a trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from navcrafter.models.cameras import invert_pose


@dataclass
class PointRender:
    depth: np.ndarray  # [H, W] float32 z-depth of the nearest point, 0 where empty
    mask: np.ndarray  # [H, W] bool, True where some point covers the pixel
    color: np.ndarray | None = None  # [H, W, 3] uint8 (when colours were given)


def splat_radius(z: torch.Tensor, focal: float, point_size: float, max_radius: int) -> torch.Tensor:
    return torch.clamp(torch.ceil(focal * point_size / (2 * z) - 0.5), 0, max_radius).to(torch.int64)


def render_points(points: np.ndarray | torch.Tensor, c2w: np.ndarray, K: np.ndarray, height: int, width: int,
                  point_size: float, colors: np.ndarray | None = None, max_radius: int = 3,
                  near: float = 1e-3) -> PointRender:
    """Render world ``points [N, 3]`` from an OpenCV camera-to-world pose with intrinsics ``K``."""
    pts = torch.as_tensor(points, dtype=torch.float32)
    w2c = torch.as_tensor(invert_pose(np.asarray(c2w, dtype=np.float64)), dtype=torch.float32)
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    keep = z > near
    idx_pts = torch.nonzero(keep).squeeze(1)
    pc, z = pc[keep], z[keep]
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float32)
    u = Kt[0, 0] * pc[:, 0] / z + Kt[0, 1] * pc[:, 1] / z + Kt[0, 2]
    v = Kt[1, 1] * pc[:, 1] / z + Kt[1, 2]
    # pixel (row i, col j) covers [j, j+1) x [i, i+1)
    ix, iy = torch.floor(u).to(torch.int64), torch.floor(v).to(torch.int64)
    radius = splat_radius(z, float(Kt[0, 0]), point_size, max_radius)
    inside = (ix >= -max_radius) & (ix < width + max_radius) & (iy >= -max_radius) & (iy < height + max_radius)
    ix, iy, z, radius, idx_pts = ix[inside], iy[inside], z[inside], radius[inside], idx_pts[inside]
    pix_parts, z_parts, id_parts = [], [], []
    for r in range(int(radius.max()) + 1 if len(radius) else 0):
        sel = radius >= r
        if not bool(sel.any()):
            break
        sx, sy, sz, sid = ix[sel], iy[sel], z[sel], idx_pts[sel]
        offsets = [(dx, dy) for dx in range(-r, r + 1) for dy in range(-r, r + 1) if max(abs(dx), abs(dy)) == r]
        for dx, dy in offsets:
            px, py = sx + dx, sy + dy
            ok = (px >= 0) & (px < width) & (py >= 0) & (py < height)
            pix_parts.append(py[ok] * width + px[ok])
            z_parts.append(sz[ok])
            id_parts.append(sid[ok])
    depth = torch.zeros(height * width)
    if not pix_parts or sum(len(p) for p in pix_parts) == 0:
        empty = np.zeros((height, width), dtype=np.float32)
        col = np.zeros((height, width, 3), dtype=np.uint8) if colors is not None else None
        return PointRender(empty, empty.astype(bool), col)
    pix = torch.cat(pix_parts)
    zz = torch.cat(z_parts)
    ids = torch.cat(id_parts)
    zbuf = torch.full((height * width,), float("inf")).scatter_reduce(0, pix, zz, reduce="amin")
    hit = torch.isfinite(zbuf)
    depth[hit] = zbuf[hit]
    out_color = None
    if colors is not None:
        winner = zz <= zbuf[pix]
        best = torch.full((height * width,), torch.iinfo(torch.int64).max, dtype=torch.int64)
        best = best.scatter_reduce(0, pix[winner], ids[winner], reduce="amin")
        col = torch.zeros((height * width, 3), dtype=torch.uint8)
        cols = torch.as_tensor(np.asarray(colors, dtype=np.uint8))
        col[hit] = cols[best[hit]]
        out_color = col.reshape(height, width, 3).numpy()
    return PointRender(depth.reshape(height, width).numpy(), hit.reshape(height, width).numpy(), out_color)

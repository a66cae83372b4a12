"""A vectorised, z-buffered point-cloud renderer (CPU, torch).

Each point is splatted as a square of ``(2r+1)^2`` pixels, where ``r`` follows from its world-space
size and its depth (``r = ceil(f * point_size / (2 z) - 1/2)``, at most ``max_radius``), so a fused
cloud renders without gaps between neighbouring points; every pixel shows the nearest point whose
splat covers it.

How: points are grouped by splat radius. Within a group, a scatter-min puts the nearest point's
depth on its centre pixel; a min-pool with a ``(2r+1)^2`` window then gives every pixel the nearest
depth among the group's splats covering it (exactly the square-splat z-buffer), and the groups are
combined by a per-pixel minimum. Ties between points at the same depth go to the lowest point
index, so renders are deterministic. Cost: one scatter over all points plus a few image-sized
pooling passes, whatever the splat sizes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from navcrafter.models.camera.cameras import invert_pose

_BIG = torch.iinfo(torch.int64).max


@dataclass
class PointRender:
    depth: np.ndarray  # [H, W] float32 z-depth of the nearest point, 0 where empty
    mask: np.ndarray  # [H, W] bool, True where some point covers the pixel
    color: np.ndarray | None = None  # [H, W, 3] uint8 (when colours were given)


def render_points(points: np.ndarray | torch.Tensor, c2w: np.ndarray, K: np.ndarray, height: int, width: int,
                  point_size: float, colors: np.ndarray | None = None, max_radius: int = 3,
                  near: float = 1e-3) -> PointRender:
    """Render world ``points [N, 3]`` from an OpenCV camera-to-world pose with intrinsics ``K``."""
    R = int(max_radius)
    Hp, Wp = height + 2 * R, width + 2 * R  # padded so that splats of points just outside still count
    pts = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3)
    w2c = torch.as_tensor(invert_pose(np.asarray(c2w, dtype=np.float64)), dtype=torch.float32)
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    ids = torch.nonzero(z > near).squeeze(1)
    pc, z = pc[ids], z[ids]
    Kt = torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=torch.float32)
    u = (Kt[0, 0] * pc[:, 0] + Kt[0, 1] * pc[:, 1]) / z + Kt[0, 2]
    v = Kt[1, 1] * pc[:, 1] / z + Kt[1, 2]
    ix = torch.floor(u).to(torch.int64) + R  # pixel (row i, col j) covers [j, j+1) x [i, i+1)
    iy = torch.floor(v).to(torch.int64) + R
    inside = (ix >= 0) & (ix < Wp) & (iy >= 0) & (iy < Hp)
    ix, iy, z, ids = ix[inside], iy[inside], z[inside], ids[inside]
    radius = torch.clamp(torch.ceil(Kt[0, 0] * point_size / (2 * z) - 0.5), 0, R).to(torch.int64)
    pix = iy * Wp + ix

    best_z = torch.full((height, width), float("inf"))
    best_id = torch.full((height, width), _BIG, dtype=torch.int64)
    for r in torch.unique(radius).tolist():
        sel = radius == r
        p, zz, ii = pix[sel], z[sel], ids[sel]
        zc = torch.full((Hp * Wp,), float("inf")).scatter_reduce(0, p, zz, reduce="amin")
        win = zz <= zc[p]  # nearest point(s) of each centre pixel; the lowest index among ties
        ic = torch.full((Hp * Wp,), _BIG, dtype=torch.int64).scatter_reduce(0, p[win], ii[win], reduce="amin")
        if r == 0:
            zr, ir = zc.reshape(Hp, Wp), ic.reshape(Hp, Wp)
        else:
            neg, where = F.max_pool2d(-zc.reshape(1, 1, Hp, Wp), 2 * r + 1, stride=1, padding=r,
                                      return_indices=True)
            zr = -neg[0, 0]
            ir = ic[where[0, 0].reshape(-1)].reshape(Hp, Wp)
        zr, ir = zr[R:R + height, R:R + width], ir[R:R + height, R:R + width]
        better = (zr < best_z) | ((zr == best_z) & (ir < best_id))
        best_z = torch.where(better, zr, best_z)
        best_id = torch.where(better, ir, best_id)
    hit = torch.isfinite(best_z)
    depth = torch.where(hit, best_z, torch.zeros(())).numpy().astype(np.float32)
    out_color = None
    if colors is not None:
        col = np.zeros((height, width, 3), dtype=np.uint8)
        h = hit.numpy()
        col[h] = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)[best_id.numpy()[h]]
        out_color = col
    return PointRender(depth, hit.numpy(), out_color)

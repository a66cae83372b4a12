"""A world's surface split into patches: **structure** (the triangles on large bounding planes: floor, walls,
ceiling, and any connected patch more than ``MAX_OBJECT_M`` across) and **objects** (the connected components of
the rest). ``patches.variant_world`` moves the objects (see its module docstring)."""

from __future__ import annotations

import numpy as np

from navcrafter.models.simulation.worlds.world import World, ransac_planes

MAX_OBJECT_M = 3.0  # a patch larger than this is structure (the largest generated furniture is ~2.2 m)


def _planes(corners: np.ndarray, seed: int = 0) -> list[tuple[np.ndarray, float, float]]:
    """Bounding RANSAC planes ``(n, d, threshold)`` of the surface (``load.find_up``'s fits)."""
    pts, thr, planes, _ = ransac_planes(corners, 20000, 8, 0.03, seed)
    out = []
    for n, d, _ in planes:
        s = pts @ n + d
        if max((s > -thr).mean(), (s < thr).mean()) >= 0.95:
            out.append((n, d, thr))
    return out


def segment(world: World) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle its patch id ``[F]``, and per patch whether it may move ``[P]`` (see the module docstring)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    C = world.corners.astype(np.float64)
    F = len(C)
    label = np.full(F, -1, dtype=np.int64)
    fn = np.cross(C[:, 1] - C[:, 0], C[:, 2] - C[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    movable: list[bool] = []
    for n, d, thr in _planes(C):
        on = (np.abs(C @ n + d) <= 2 * thr).all(1) & (np.abs(fn @ n) > 0.9) & (label < 0)
        if on.any():
            label[on] = len(movable)
            movable.append(False)
    rest = np.flatnonzero(label < 0)
    if len(rest):
        keys = np.round(C[rest].reshape(-1, 3) / 1e-4).astype(np.int64)
        _, vid = np.unique(keys, axis=0, return_inverse=True)
        vid = vid.reshape(-1)
        m = len(rest)
        rows = np.repeat(np.arange(m), 3)
        g = coo_matrix((np.ones(3 * m), (rows, m + vid)), shape=(m + vid.max() + 1,) * 2)
        _, comp = connected_components(g, directed=False)
        comp = comp[:m]
        _, comp = np.unique(comp, return_inverse=True)
        for c in range(comp.max() + 1):
            tri = rest[comp == c]
            pts = C[tri].reshape(-1, 3)
            label[tri] = len(movable)
            movable.append(float(np.linalg.norm(pts.max(0) - pts.min(0))) <= MAX_OBJECT_M)
    return label, np.asarray(movable, dtype=bool)

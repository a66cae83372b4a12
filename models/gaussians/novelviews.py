"""Novel cameras off the explored trajectory, for the refine step (``tasks/refine.py``).

Difix3D+ refines renders at cameras the reconstruction was not trained on and adds them as pseudo-views. Here a
novel camera is a training camera moved by ``offset`` (scene units) in a seeded random direction of its own
image plane (sideways and up/down, never forward/back, so it keeps looking at what the trajectory saw) and
turned by a seeded yaw and pitch of at most ``angle_deg``. A displaced centre must keep at least half the
source camera's clearance from the cloud (the nearest cloud point), so a novel camera never sits inside a
wall; up to ``tries`` directions are tried, then the offset is halved (twice at most), then the source is
skipped.

The reference view of a novel camera is the training frame whose camera is nearest (centre distance plus
``angle_weight`` x viewing-direction angle in radians).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from navcrafter.models.camera.cameras import axis_angle_to_matrix


def novel_cameras(c2w: np.ndarray, sources: np.ndarray, cloud: np.ndarray, *, offset: float, angle_deg: float,
                  rng: np.random.Generator, tries: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Novel OpenCV c2w ``[V, 4, 4]`` displaced from ``c2w[sources]``, and the source index of each (``[V]``;
    sources that found no free position are left out)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    tree = cKDTree(np.asarray(cloud, dtype=np.float64)) if len(cloud) else None

    def clearance(x: np.ndarray) -> float:
        return float("inf") if tree is None else float(tree.query(x, k=1)[0])

    out, used = [], []
    for s in np.asarray(sources, dtype=int):
        pose = c2w[s]
        R, t = pose[:3, :3], pose[:3, 3]
        need = 0.5 * clearance(t)
        found = None
        for scale in (1.0, 0.5, 0.25):
            for _ in range(tries):
                phi = rng.uniform(0.0, 2.0 * np.pi)
                direction = R @ np.array([np.cos(phi), np.sin(phi), 0.0])  # camera x (right) / y (down)
                centre = t + scale * offset * direction
                yaw, pitch = np.deg2rad(rng.uniform(-angle_deg, angle_deg, size=2))
                if clearance(centre) >= need:
                    turn = (axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), yaw)
                            @ axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), pitch))
                    found = np.eye(4)
                    found[:3, :3] = R @ turn
                    found[:3, 3] = centre
                    break
            if found is not None:
                break
        if found is not None:
            out.append(found)
            used.append(int(s))
    return np.asarray(out, dtype=np.float64).reshape(-1, 4, 4), np.asarray(used, dtype=np.int64)


def nearest_views(targets: np.ndarray, candidates: np.ndarray, angle_weight: float = 1.0) -> np.ndarray:
    """For each target c2w ``[V, 4, 4]`` the index of the nearest candidate c2w ``[M, 4, 4]``."""
    targets, candidates = np.asarray(targets, dtype=np.float64), np.asarray(candidates, dtype=np.float64)
    d = np.linalg.norm(targets[:, None, :3, 3] - candidates[None, :, :3, 3], axis=-1)
    cos = np.clip(np.einsum("vi,mi->vm", targets[:, :3, 2], candidates[:, :3, 2]), -1.0, 1.0)
    return np.argmin(d + angle_weight * np.arccos(cos), axis=1)

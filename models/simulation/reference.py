"""Ground-truth reference surfaces for geometry metrics in simulation mode.

Coverage needs "all the surface there was to see". A generated scene has surfaces no explorer can
see (the outside of the room's walls, the inside of closed objects), so the reference is the part of
the true surfaces visible from the space the planner may explore: the input camera plus a grid of
viewpoints over the planner's search space S (the quarter sphere about the scene centre), kept only where a
camera could stand (free space, at least ``clearance`` from any surface, not inside an object), each looking at
the scene centre. Points are sampled from depth
renders of those views and thinned to ``spacing`` (metres).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from navcrafter.models.camera.cameras import Intrinsics, look_at, unproject_depth
from navcrafter.models.planning.planners import WORLD_UP, SearchSpace, space_positions
from navcrafter.models.reconstruction.pointcloud import thin_points
from navcrafter.models.simulation.backend import SimulationTruth
from navcrafter.models.simulation.render import render

OBJECT_REGIONS = {"tabletop": ("table_", "object_")}  # scene kind -> name prefixes of its object region


def object_region_prefixes(kind: str) -> tuple[str, ...]:
    """Name prefixes of the objects forming a scene kind's object region (the table and what stands on it), or ()
    for kinds without one."""
    return OBJECT_REGIONS.get(kind, ())


def reachable_viewpoints(truth: SimulationTruth, centre_world: np.ndarray, d0_world: float, space: SearchSpace,
                         clearance_m: float, azimuths: int = 9, elevations: int = 3,
                         radii: int = 3) -> np.ndarray:
    """World camera poses of the reference grid (input camera first)."""
    az = np.deg2rad(np.linspace(*space.azimuth_deg, azimuths))
    el = np.deg2rad(np.linspace(*space.elevation_deg, elevations))
    r = d0_world * np.linspace(space.radius[0], space.radius[1], radii)
    A, E, R = np.meshgrid(az, el, r, indexing="ij")
    pos = space_positions(centre_world, A, E, R).reshape(-1, 3)
    gt = truth.gt_points(pos)
    rc, _ = truth.scene.raycasting()
    inside = rc.compute_occupancy(o3d.core.Tensor(gt.astype(np.float32))).numpy() > 0
    ok = (truth.scene.distance(gt) >= clearance_m) & ~inside
    poses = [np.eye(4)]
    for p in pos[ok]:
        view = centre_world - p
        if abs(view @ WORLD_UP) < 0.99 * np.linalg.norm(view):
            poses.append(look_at(p, centre_world, up=WORLD_UP))
    return np.stack(poses)


def reference_points(truth: SimulationTruth, centre_world: np.ndarray, d0_world: float, space: SearchSpace,
                     clearance_m: float, spacing_m: float = 0.01, resolution: int = 128) -> np.ndarray:
    """Reference surface points ``[M, 3]`` in the ground-truth frame (metres)."""
    poses = reachable_viewpoints(truth, centre_world, d0_world, space, clearance_m)
    K0 = truth.work_intrinsics
    K = K0.resize(resolution, resolution) if (K0.width, K0.height) != (resolution, resolution) else K0
    K = Intrinsics.from_matrix(K.K, K.width, K.height)
    parts = []
    for c2w_world in poses:
        c2w = truth.gt_pose(c2w_world[None])[0]
        r = render(truth.scene, c2w, K, colour=False)
        pts, _ = unproject_depth(r.depth.astype(np.float64), c2w, K.K, mask=r.hit)
        parts.append(pts)
    pts = np.concatenate(parts) if parts else np.zeros((0, 3))
    return thin_points(pts, spacing_m)

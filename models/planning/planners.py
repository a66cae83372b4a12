"""Camera trajectory planning: the paper's collision-aware planner (Algorithm 1) and a
ViewCrafter-style baseline, behind one interface.

One iteration of the collision-aware planner:

1. **Candidates.** ``K`` poses sampled in the search space ``S`` (``SearchSpace``), ViewCrafter's quarter
   sphere about the scene centre ``o`` facing the reference view: positions ``o + r * dir(azimuth, elevation)``,
   ``r`` in ``radius * d0`` (``d0`` = distance from the input camera to ``o``), azimuth measured from the
   horizontal direction from ``o`` to the input camera, elevation from the horizon (world up = -y); defaults
   azimuth +-90 deg, elevation +-30 deg, r in 0.6-1.0 d0. Samples are stratified (a Halton sequence with a seeded
   random shift); every candidate looks at ``o``. A candidate that ``G`` rejects is moved to the nearest position
   ``G`` passes (``repair_candidate``: along its ray towards ``o``, then backed off along the arc from the current
   camera); with ``max_resample > 0`` (default 0: the
   baseline's budget of K) more rounds of K are drawn until K pass. Those that still collide get empty masks.
2. **Collision detector G** (``CollisionDetector``): a position collides when it lies within
   ``r_safe`` of an observed surface (the cloud, by KD-tree; the earlier views' depth maps as
   meshes, which have no holes where a surface was seen at a grazing angle; and the ground plane,
   estimated by RANSAC, since the floor under a camera is rarely in its view) or below the ground,
   or when it is not in seen free space: no earlier camera saw it in front of the surface in that
   pixel and no earlier camera stood within r_safe of it. That is ``unknown_space = "occupied"``,
   the default: the camera never enters space it has not seen. With ``"free"``, only space seen
   *behind* a surface counts as occupied (explores more, but may meet surfaces it has not seen;
   see the planning benchmark). Colliding candidates get an empty mask.
3. **Score F** of the visibility mask ``M`` rendered by splatting the cloud into the candidate
   (``navcrafter.models.reconstruction.pointrender``): with ``m`` the fraction of pixels covered by known content,

       F(M) = (1 - m) * min(1, m / m0)          (m0 = ``anchor_fraction``, default 0.5)

   i.e. the unseen area, as long as at least ``m0`` of the view stays anchored to seen content;
   below that the score falls linearly to 0 (an empty mask scores 0).
4. **SphericalInterpolate** from the current pose to the best candidate (NBV): rotation by SLERP,
   position on the arc around ``o`` (radius interpolated linearly).
5. **CollisionOptimization**, only when ``G`` flags the interpolated path: minimise over the
   interior positions (end points fixed)

       L(x) = sum_t max(0, r' - d(x_t, P)) + lambda * sum_t |x_{t+1} - x_t|^2,   r' = 1.2 r_safe

   (``r_safe`` is a physical size in scene units, ``safe_radius``; the search space scales with d0;
   the 20 % margin keeps optimised paths off the boundary, since the cloud is only an estimate)

   with L-BFGS (analytic gradient from the KD-tree's nearest points) over the knots of a cubic
   spline path, from the arc and then from detours bulging in 8 directions around the chord at
   growing amplitudes (the hinge alone cannot carry a path around an obstacle); the interior cameras
   then look at ``o``. A result counts only if ``G`` passes it (which also checks the seen free space,
   not part of ``L``); the cheapest such result at the smallest amplitude wins. If no start gives a
   collision-free path, the next-best candidate is tried; if none works the camera stays put (a
   static clip) and the result says so.

The baseline (``ViewCrafterPlanner``) is ViewCrafter's next-best view: the same K candidates (same sampler and
seed), its utility (the empty area of the candidate's render, ``occlusion_utility``), the same spherical
interpolation about ``o``, and no collision detector or optimisation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from navcrafter.models.camera.cameras import camera_directions, interpolate_poses, look_at, project
from navcrafter.models.planning.config import PlanConfig
from navcrafter.models.reconstruction.pointcloud import thin_points
from navcrafter.models.reconstruction.pointrender import render_points
from navcrafter.models.threads import one_blas_thread

WORLD_UP = np.array([0.0, -1.0, 0.0])  # a scene's world is its input camera's OpenCV frame
MAX_ELEVATION_DEG = 85.0  # look-at is degenerate straight above or below the centre


# --------------------------------------------------------------------------------------------------
# Search space and candidates
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SearchSpace:
    """The search space S: positions ``o + r * dir(azimuth, elevation)`` on spheres about the scene centre ``o``.

    Azimuth is measured in the horizontal plane from the direction from ``o`` to the input camera (the reference
    view; positive to its right), elevation from that plane (positive up), ``r`` in units of ``d0`` (the input
    camera's distance to ``o``). The default, azimuth +-90 deg, elevation +-30 deg, r in 0.6-1.0 d0, is
    ViewCrafter's quarter sphere facing the reference view (a quarter of the sphere's area), with the radius
    allowed to shrink towards ``o`` (ViewCrafter moves by ``d_r``, -0.2 by default). Every candidate looks at ``o``.
    """

    radius: tuple[float, float] = (0.6, 1.0)
    azimuth_deg: tuple[float, float] = (-90.0, 90.0)
    elevation_deg: tuple[float, float] = (-30.0, 30.0)


def level_forward(pose: np.ndarray) -> np.ndarray:
    """The camera's viewing axis with its vertical part removed, unit length (the "forward" that
    ``look_at_centre`` keeps when the axis is vertical)."""
    forward = pose[:3, 2] - (pose[:3, 2] @ WORLD_UP) * WORLD_UP
    return forward / max(np.linalg.norm(forward), 1e-9)


def search_space(cfg: PlanConfig) -> SearchSpace:
    """The search space S of a run's planning config."""
    return SearchSpace(cfg.radius_range, cfg.azimuth_range_deg, cfg.elevation_range_deg)


def scene_centre(depth: np.ndarray, confidence: np.ndarray, quantile: float) -> np.ndarray:
    """The scene centre ``o``: the point on the input camera's optical axis at the given quantile of the input
    view's valid depth (``plan.centre_depth_quantile``)."""
    d = depth[(confidence > 0) & (depth > 0)]
    if d.size == 0:
        raise ValueError("no valid depth to place the scene centre")
    return np.array([0.0, 0.0, float(np.quantile(d, quantile))])


def search_frame(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (back, right, up) of S: ``back`` is the horizontal direction from ``o`` to the input camera
    (the world origin; the input camera's own horizontal viewing direction reversed if ``o`` is straight above or
    below it), ``right`` the input camera's right."""
    up = WORLD_UP
    f = np.asarray(centre, dtype=np.float64)
    f = f - (f @ up) * up  # horizontal direction from the camera to o
    if np.linalg.norm(f) < 1e-9:
        f = np.array([0.0, 0.0, 1.0]) - (np.array([0.0, 0.0, 1.0]) @ up) * up
    f = f / np.linalg.norm(f)
    right = np.cross(-up, f)  # OpenCV: x = y x z with y = down
    return -f, right, up


def space_positions(centre: np.ndarray, azimuth: np.ndarray, elevation: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Positions ``[..., 3]`` of S at ``radius`` (world units) from ``o`` in the directions (radians) of the
    search frame (see ``SearchSpace``)."""
    back, right, up = search_frame(centre)
    dirs = (np.cos(elevation) * np.cos(azimuth))[..., None] * back + \
        (np.cos(elevation) * np.sin(azimuth))[..., None] * right + np.sin(elevation)[..., None] * up
    return np.asarray(centre, dtype=np.float64) + np.asarray(radius)[..., None] * dirs


def look_at_centre(position: np.ndarray, centre: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Pose at ``position`` looking at ``centre``; horizontally along ``forward`` when ``centre`` is
    within 5 deg of straight above or below (where look-at has no stable roll)."""
    view = centre - position
    n = np.linalg.norm(view)
    if n < 1e-9 or abs(view @ WORLD_UP) > np.cos(np.deg2rad(90.0 - MAX_ELEVATION_DEG)) * n:
        return look_at(position, position + forward, up=WORLD_UP)
    return look_at(position, centre, up=WORLD_UP)


def sample_candidates(centre: np.ndarray, d0: float, space: SearchSpace, count: int,
                      rng: np.random.Generator) -> np.ndarray:
    """``count`` candidate poses ``[count, 4, 4]`` in the search space, all looking at ``centre``.

    Stratified: a Halton sequence over (azimuth, sin elevation, radius) with a seeded random shift.
    """
    shift = rng.random(3)
    u = (np.stack([_halton(count, 2), _halton(count, 3), _halton(count, 5)], 1) + shift) % 1.0
    az = np.deg2rad(space.azimuth_deg[0] + u[:, 0] * (space.azimuth_deg[1] - space.azimuth_deg[0]))
    s0, s1 = np.sin(np.deg2rad(space.elevation_deg))  # uniform in area: sample sin(elevation)
    el = np.arcsin(np.clip(s0 + u[:, 1] * (s1 - s0), -1, 1))
    r = d0 * (space.radius[0] + u[:, 2] * (space.radius[1] - space.radius[0]))
    forward = -search_frame(centre)[0]
    return np.stack([look_at_centre(p, centre, forward) for p in space_positions(centre, az, el, r)])


def repair_candidate(candidate: np.ndarray, current: np.ndarray, centre: np.ndarray, d0: float, space: SearchSpace,
                     detector: CollisionDetector, grid_deg: float = 10.0, radii: int = 3) -> np.ndarray | None:
    """A colliding candidate moved to the nearest position of S that ``G`` passes (a grid over S every
    ``grid_deg`` in azimuth and elevation at ``radii`` radii, and the arc from the current camera to the
    candidate, whose start was seen free), still looking at ``o``; None if none passes."""
    c = np.asarray(centre, dtype=np.float64)
    az = np.deg2rad(np.arange(space.azimuth_deg[0], space.azimuth_deg[1] + 1e-9, grid_deg))
    el = np.deg2rad(np.arange(space.elevation_deg[0], space.elevation_deg[1] + 1e-9, grid_deg))
    r = d0 * np.linspace(space.radius[0], space.radius[1], radii)
    A, E, R = np.meshgrid(az, el, r, indexing="ij")
    tries = np.concatenate([space_positions(c, A, E, R).reshape(-1, 3),
                            interpolate_poses(current, candidate, 21, centre=c)[1:-1, :3, 3]])
    free = ~detector.collides(tries)
    if not free.any():
        return None
    tries = tries[free]
    best = tries[int(np.argmin(np.linalg.norm(tries - candidate[:3, 3], axis=1)))]
    return look_at_centre(best, c, level_forward(candidate))


def _halton(n: int, base: int) -> np.ndarray:
    out = np.empty(n)
    for i in range(n):
        fr, x, k = 1.0, 0.0, i + 1
        while k > 0:
            fr /= base
            x += fr * (k % base)
            k //= base
        out[i] = x
    return out


# --------------------------------------------------------------------------------------------------
# Collision detector
# --------------------------------------------------------------------------------------------------
@dataclass
class SeenView:
    """An earlier camera and what it saw: pose, intrinsics and z-depth (0 = unknown)."""

    c2w: np.ndarray
    K: np.ndarray
    depth: np.ndarray
    # [H, W] bool: pixels whose depth copies content known before the view was made (a generated frame's
    # anchored pixels, ``explore.anchored_pixels``); None: every pixel is an observation (the input photo)
    anchored: np.ndarray | None = None


def forgive_escape(clearance: np.ndarray, near: np.ndarray) -> np.ndarray:
    """``near`` (per pose: too near a surface) with an escape forgiven: a clip that starts too near a surface (an
    earlier clip's true camera drifted there) may leave, its clearance rising frame by frame, until it is clear.
    Staying there is no escape (every frame would count as a collision, and G would reject every path, so the camera
    would stay put), nor is a path that never gets clear."""
    if not near[0] or near.all():
        return near
    k = int(np.argmin(near))  # the first clear frame
    rising = np.r_[True, np.diff(clearance[:k + 1]) > 0]
    out = near.copy()
    out[:k] = ~rising[:k]
    return out


class CollisionDetector:
    """G: within ``r_safe`` of an observed surface, or outside the free space seen by earlier cameras
    (see the module docstring, step 2).

    Surfaces: the cloud (a KD-tree on the cloud thinned to voxels of ``r_safe / 8``; ``thin=False``
    when the caller already thinned it at most that coarsely, so distances are exact to within
    0.11 * ``r_safe``), the earlier views' depth maps as meshes (``surfaces``), and an optional ground
    plane. ``unknown_is_free`` selects the ``"free"`` policy for space no camera has seen. ``visibility_views``, when
    given, are the views whose seen free space G trusts (``_visibility``) in place of ``views`` (e.g. the explorer's
    views with the input photo's sky opened); the surfaces stay those of ``views``' depth maps.
    """

    def __init__(self, cloud_points: np.ndarray, r_safe: float, views: list[SeenView], thin: bool = True,
                 unknown_is_free: bool = False, surfaces: bool = True,
                 ground: tuple[np.ndarray, float] | None = None, follow_error: float = 0.0,
                 visibility_views: list[SeenView] | None = None) -> None:
        if r_safe <= 0:
            raise ValueError("r_safe must be positive")
        self.r_safe = float(r_safe)
        self.follow_error = float(follow_error)
        self.unknown_is_free = unknown_is_free
        pts = thin_points(cloud_points, r_safe / 8) if thin else np.asarray(cloud_points, dtype=np.float64)
        self.points = pts
        self.tree = cKDTree(pts, balanced_tree=False, compact_nodes=False) if len(pts) else None
        self.views = views if visibility_views is None else visibility_views
        self.centres = np.array([v.c2w[:3, 3] for v in views]).reshape(-1, 3)
        self.surfaces = view_surfaces(views) if surfaces else None
        self.ground = ground  # (unit normal pointing up, offset): height above ground = n . x + offset

    def cloud_clearance(self, x: np.ndarray) -> np.ndarray:
        """Distance from positions ``[M, 3]`` to the nearest cloud point (KD-tree)."""
        if self.tree is None:
            return np.full(len(x), np.inf)
        d, _ = self.tree.query(np.asarray(x, dtype=np.float64), k=1)
        return d

    def clearance(self, x: np.ndarray) -> np.ndarray:
        """Distance from positions ``[M, 3]`` to the nearest observed surface: the cloud's points, and
        the surfaces of the earlier views' depth maps (which have no holes where a view saw a surface
        at a grazing angle, e.g. a floor far away)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        d = self.cloud_clearance(x)
        if self.surfaces is not None and len(x):
            import open3d as o3d

            d = np.minimum(d, self.surfaces.compute_distance(o3d.core.Tensor(x.astype(np.float32))).numpy())
        if self.ground is not None:
            d = np.minimum(d, np.maximum(x @ self.ground[0] + self.ground[1], 0.0))
        return d

    def seen_free(self, x: np.ndarray) -> np.ndarray:
        """Free as far as the earlier views tell: seen in front of a surface by some view, or next to
        an earlier camera; with ``unknown_is_free``, also any position no view saw behind a surface."""
        free, occluded = self._visibility(x)
        return free | (~occluded if self.unknown_is_free else False)

    def _visibility(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per position: seen free by some view (or near an earlier camera); behind a surface in some view (any
        pixel). A view with ``anchored`` pixels (a generated frame: ``explore.anchored_pixels``) carves free space
        only where it copied known content: its invented depth is no evidence that the space in front is free."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        free = np.zeros(len(x), dtype=bool)
        occluded = np.zeros(len(x), dtype=bool)
        if len(self.centres):
            free |= np.linalg.norm(x[:, None] - self.centres[None], axis=-1).min(1) < self.r_safe
        for v in self.views:
            uv, z = project(x, v.c2w, v.K)
            H, W = v.depth.shape
            u, w = np.floor(uv[:, 0]), np.floor(uv[:, 1])
            ok = (z > 0) & (u >= 0) & (u < W) & (w >= 0) & (w < H)
            if not ok.any():
                continue
            d = np.zeros(len(x))
            trusted = np.zeros(len(x), dtype=bool)
            ui, wi = u[ok].astype(int), w[ok].astype(int)
            d[ok] = v.depth[wi, ui]
            trusted[ok] = True if v.anchored is None else v.anchored[wi, ui]
            occluded |= ok & (d > 0) & (z >= d)
            free |= ok & trusted & (d > 0) & (z < d)
        return free, occluded

    def collides(self, x: np.ndarray) -> np.ndarray:
        """Per position: within ``r_safe`` of an observed surface, or not in seen free space."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        return (self.clearance(x) < self.r_safe) | ~self.seen_free(x)

    def path_clearance(self, positions: np.ndarray, follow_error: float | None = None) -> np.ndarray:
        """The clearance each sample of a path needs: ``r_safe`` plus ``follow_error`` (default: the detector's)
        times the distance travelled from the path's start (a video model follows the requested cameras with an
        error that grows along the clip)."""
        x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(x, axis=0), axis=1))])
        return self.r_safe + (self.follow_error if follow_error is None else follow_error) * travelled

    def path_flags(self, trajectory: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per pose of ``trajectory`` [T, 4, 4]: closer to a surface than the path's clearance (an escape from a
        start that is already too near forgiven: ``forgive_escape``), outside the seen free space; and the clearance
        itself."""
        x = trajectory[:, :3, 3]
        clearance = self.clearance(x)
        return forgive_escape(clearance, clearance < self.path_clearance(x)), ~self.seen_free(x), clearance

    def trajectory_collides(self, trajectory: np.ndarray) -> bool:
        near, unseen, _ = self.path_flags(trajectory)
        return bool((near | unseen).any())


def estimate_ground(points: np.ndarray, camera: np.ndarray, rng: np.random.Generator, tolerance: float,
                    max_tilt_deg: float = 35.0, iterations: int = 300,
                    min_inliers: float = 0.05) -> tuple[np.ndarray, float] | None:
    """The dominant plane below ``camera`` whose normal is within ``max_tilt_deg`` of world up
    (RANSAC, seeded), as ``(n, c)`` with ``n`` pointing up, so ``n . x + c`` is the height above it;
    ``None`` if no such plane holds at least ``min_inliers`` of the points."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 3:
        return None
    sample = pts[rng.choice(len(pts), min(len(pts), 20000), replace=False)]
    cos_tilt = np.cos(np.deg2rad(max_tilt_deg))
    best, best_count = None, int(min_inliers * len(sample))
    for _ in range(iterations):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n = n / norm
        if n @ WORLD_UP < 0:
            n = -n
        if n @ WORLD_UP < cos_tilt:
            continue
        off = -n @ a
        if camera @ n + off <= 0:  # must be below the camera
            continue
        count = int((np.abs(sample @ n + off) < tolerance).sum())
        if count > best_count:
            best, best_count = (n, float(off)), count
    if best is None:
        return None
    n, off = best  # refine on the inliers (least squares with the normal fixed in orientation)
    inl = sample[np.abs(sample @ n + off) < tolerance]
    centroid = inl.mean(0)
    _, _, vt = np.linalg.svd(inl - centroid, full_matrices=False)
    n2 = vt[2] if vt[2] @ WORLD_UP > 0 else -vt[2]
    if n2 @ WORLD_UP >= cos_tilt:
        n = n2
    return n, float(-n @ centroid)


def _smooth_steps(q: np.ndarray, axis: int, factor: float = 3.0, noise: float = 0.02) -> np.ndarray:
    """For each pair of neighbours along ``axis`` of an inverse-depth grid: True where the step is
    consistent with its neighbouring steps (a surface, however steep), False at a depth edge."""
    dq = np.abs(np.diff(q, axis=axis))
    pad = [(0, 0), (0, 0)]
    pad[axis] = (1, 1)
    padded = np.pad(dq, pad, constant_values=np.inf)
    prev = np.take(padded, range(0, dq.shape[axis]), axis=axis)
    nxt = np.take(padded, range(2, dq.shape[axis] + 2), axis=axis)
    ref = np.minimum(prev, nxt)
    ref = np.where(np.isfinite(ref), ref, dq)  # a lone step (grid border) is judged by itself
    n = q.shape[axis]
    qmin = np.minimum(np.take(q, range(0, n - 1), axis=axis), np.take(q, range(1, n), axis=axis))
    return dq <= factor * ref + noise * qmin


def view_surfaces(views: list[SeenView], step: int = 4, max_jump: float = 1.0):
    """An Open3D raycasting scene of the views' depth maps as triangle meshes (every ``step``-th pixel),
    or ``None``.

    Neighbours are joined unless a depth edge separates them: on a plane, inverse depth is affine in
    the pixel coordinates, so its steps along a row or column stay constant however steep the plane
    (a floor seen at a grazing angle stays closed); at an occlusion edge one step stands out from its
    neighbours and the triangles across it are dropped (as are those spanning depths more than a
    factor ``1 + max_jump`` apart), so no phantom surface blocks space that other views saw free."""
    import open3d as o3d

    verts, tris, offset = [], [], 0
    for v in views:
        H, W = v.depth.shape
        rows, cols = np.arange(0, H, step), np.arange(0, W, step)
        d = v.depth[np.ix_(rows, cols)].astype(np.float64)
        rays = camera_directions(v.K, H, W)[np.ix_(rows, cols)]
        pts = (rays * d[..., None]) @ v.c2w[:3, :3].T + v.c2w[:3, 3]
        h, w = d.shape
        valid = d > 0
        q = np.where(valid, 1.0 / np.where(valid, d, 1.0), 0.0)
        ok_x = _smooth_steps(q, 1) & valid[:, :-1] & valid[:, 1:]  # (h, w-1): pixel (i,j)-(i,j+1)
        ok_y = _smooth_steps(q, 0) & valid[:-1, :] & valid[1:, :]  # (h-1, w): pixel (i,j)-(i+1,j)
        idx = np.arange(h * w).reshape(h, w)
        a, b, c, e = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        first = ok_x[:-1, :] & ok_y[:, :-1]  # triangle (a, c, b): edges a-b and a-c
        second = ok_x[1:, :] & ok_y[:, 1:]  # triangle (b, c, e): edges c-e and b-e
        flat = d.reshape(-1)
        for tri, keep in ((np.stack([a, c, b], -1), first), (np.stack([b, c, e], -1), second)):
            tri = tri[keep]
            z = flat[tri]
            tris.append(tri[z.max(1) <= (1 + max_jump) * z.min(1)] + offset)
        verts.append(pts.reshape(-1, 3))
        offset += h * w
    tris_a = np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)
    if len(tris_a) == 0:
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.concatenate(verts).astype(np.float32)),
                        o3d.core.Tensor(tris_a.astype(np.uint32)))
    return scene


# --------------------------------------------------------------------------------------------------
# Scoring, interpolation, optimisation
# --------------------------------------------------------------------------------------------------
def visibility_score(mask: np.ndarray, anchor_fraction: float) -> float:
    """F(M) = (1 - m) * min(1, m / m0), m = covered fraction of the mask."""
    m = float(np.mean(mask))
    return (1.0 - m) * min(1.0, m / anchor_fraction)


def spherical_interpolate(current: np.ndarray, target: np.ndarray, num: int, centre: np.ndarray) -> np.ndarray:
    return interpolate_poses(current, target, num, centre=centre)


def poses_looking_at(positions: np.ndarray, centre: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Poses at ``positions`` looking at ``centre``; the first and last are ``start`` and ``end`` exactly."""
    forward = level_forward(end)
    out = np.stack([look_at_centre(p, centre, forward) for p in positions])
    out[0], out[-1] = start, end
    return out


@dataclass
class OptimisationResult:
    trajectory: np.ndarray
    collision_free: bool
    optimised: bool  # False when the input was already collision-free (returned unchanged)
    starts: int = 0
    iterations: int = 0
    cost: float = 0.0


def trajectory_cost(x: np.ndarray, detector: CollisionDetector, smoothness: float) -> float:
    d = detector.clearance(x)
    return float(np.maximum(0.0, detector.path_clearance(x) - d).sum() + smoothness * (np.diff(x, axis=0) ** 2).sum())


def _spline_basis(num_out: int, num_knots: int) -> np.ndarray:
    """``[num_out, num_knots]`` matrix evaluating a natural cubic spline through ``num_knots`` values at
    uniform parameters, at ``num_out`` uniform parameters (both including the ends)."""
    from scipy.interpolate import CubicSpline

    s_k, s_o = np.linspace(0, 1, num_knots), np.linspace(0, 1, num_out)
    return np.stack([CubicSpline(s_k, e, bc_type="natural")(s_o) for e in np.eye(num_knots)], axis=1)


def optimise_trajectory(trajectory: np.ndarray, detector: CollisionDetector, centre: np.ndarray,
                        smoothness: float = 1.0, margin: float = 0.2, knots: int = 17, samples: int = 33,
                        max_iter: int = 100) -> OptimisationResult:
    """CollisionOptimization: collision-free path with the same end poses, or a report that none was
    found. A path that is already collision-free is returned unchanged.

    The path is a natural cubic spline through ``knots`` positions (the ends fixed); the hinge is
    evaluated at ``samples`` points along it (weighted to stand for all T), the smoothness term on all
    T positions, exactly as in ``L``. The hinge pushes towards ``(1 + margin) * r_safe`` while ``G``
    accepts ``r_safe``: the cloud is an estimate (noisy, thinned), so a path planned exactly at
    ``r_safe`` would graze the true surfaces. Starts are tried by increasing detour amplitude; the
    cheapest collision-free result of the first amplitude that has one wins.
    """
    if not detector.trajectory_collides(trajectory):
        return OptimisationResult(trajectory, True, False)
    if detector.collides(trajectory[[0, -1], :3, 3]).any():  # fixed end points: nothing can fix that
        return OptimisationResult(trajectory, False, False)
    x0 = trajectory[:, :3, 3].copy()
    T = len(x0)
    M, S = min(knots, T), min(samples, T)
    A = _spline_basis(T, M)  # dense positions from knots
    B = _spline_basis(S, M)  # hinge samples from knots
    D = np.diff(np.eye(T), axis=0) @ A  # differences of dense positions
    DtD = D.T @ D
    weight = T / S
    # the hinge's radius at each sample: the clearance G demands there (growing with the distance travelled along
    # the initial path), plus the margin
    r = (1.0 + margin) * np.interp(np.linspace(0, 1, S), np.linspace(0, 1, T), detector.path_clearance(x0))
    tree, pts = detector.tree, detector.points
    ends = np.zeros((M, 3))
    ends[0], ends[-1] = x0[0], x0[-1]

    def knots_of(y: np.ndarray) -> np.ndarray:
        out = ends.copy()
        out[1:-1] = y.reshape(-1, 3)
        return out

    def fun(y: np.ndarray) -> tuple[float, np.ndarray]:
        k = knots_of(y)
        g = 2 * smoothness * (DtD @ k)
        cost = smoothness * float(np.sum((D @ k) ** 2))
        xs = B @ k
        gx = np.zeros_like(xs)
        if tree is not None:
            d, idx = tree.query(xs, k=1, distance_upper_bound=float(r.max()))
            close = np.isfinite(d) & (d < r)
            if close.any():
                cost += weight * float((r[close] - d[close]).sum())
                gx[close] -= (xs[close] - pts[idx[close]]) / np.maximum(d[close], 1e-9)[:, None]
        if detector.ground is not None:  # the ground plane: height h = n . x + c, hinge on r - h
            n, c = detector.ground
            h = xs @ n + c
            low = h < r
            cost += weight * float((r[low] - h[low]).sum())
            gx[low] -= n
        return cost, (g + weight * (B.T @ gx))[1:-1].ravel()

    s_k = np.linspace(0, 1, M)
    base = np.stack([np.interp(s_k, np.linspace(0, 1, T), x0[:, i]) for i in range(3)], 1)
    chord = x0[-1] - x0[0]
    along = chord / max(np.linalg.norm(chord), 1e-9)
    side = np.cross(along, WORLD_UP)
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0, 0])
    up = np.cross(side, along)
    bump = np.sin(np.pi * s_k)[:, None]
    scale = max(np.linalg.norm(chord) / 2, 2 * float(r.max()))
    ring = [np.cos(a) * up + np.sin(a) * side for a in np.deg2rad(np.arange(0, 360, 45))]
    levels = [[base]] + [[base + a * scale * bump * n for n in ring] for a in (0.25, 0.5, 1.0, 2.0)]
    least_bad: OptimisationResult | None = None
    tried = 0
    # One BLAS thread for the starts: every array here is tiny (45 unknowns, 33 samples), and with OpenBLAS's two
    # threads L-BFGS-B's own BLAS calls and the products in ``fun`` waited on each other: on one plan (66 starts
    # that all failed) the explorer's iteration took 17.4 s, with one thread 4.2 s, the same plan bit for bit
    # (benchmarks/results/planning-explore8-speed). The collection flows already run the
    # whole scene so (models/threads.py); a planner called outside them (the benchmark, a scene deployment) did not.
    with one_blas_thread():
        for level in levels:
            best: OptimisationResult | None = None
            for start in level:
                tried += 1
                res = minimize(fun, start[1:-1].ravel(), jac=True, method="L-BFGS-B",
                               options={"maxiter": max_iter})
                x = A @ knots_of(res.x)
                x[0], x[-1] = x0[0], x0[-1]
                traj = poses_looking_at(x, centre, trajectory[0], trajectory[-1])
                ok = not detector.trajectory_collides(traj)
                cand = OptimisationResult(traj, ok, True, 0, int(res.nit), float(res.fun))
                if ok and (best is None or cand.cost < best.cost):
                    best = cand
                if least_bad is None or cand.cost < least_bad.cost:
                    least_bad = cand
            if best is not None:
                best.starts = tried
                return best
    assert least_bad is not None
    least_bad.collision_free = False
    least_bad.starts = tried
    return least_bad


def _directions26() -> np.ndarray:
    grid = np.stack(np.meshgrid(*[np.array([-1.0, 0.0, 1.0])] * 3, indexing="ij"), -1).reshape(-1, 3)
    grid = grid[np.abs(grid).sum(1) > 0]
    return grid / np.linalg.norm(grid, axis=1)[:, None]


def free_depth(x: np.ndarray, detector: CollisionDetector, reach: float, rings: int = 6) -> np.ndarray:
    """Per position ``[M, 3]``: the distance (up to ``reach``) to the nearest space no earlier view saw free
    (``detector.seen_free``), probed in 26 directions at ``rings`` distances; ``reach`` if every probe is free."""
    radii = reach * np.arange(1, rings + 1) / rings
    probes = x[:, None, None] + radii[None, :, None, None] * _directions26()[None, None]  # [M, rings, 26, 3]
    free = detector.seen_free(probes.reshape(-1, 3)).reshape(len(x), rings, -1).all(2)  # [M, rings]
    blocked = ~free
    return np.where(blocked.any(1), radii[np.argmax(blocked, axis=1)] - reach / rings, reach)


def retrace_trajectory(current: np.ndarray, centre: np.ndarray, d0: float, detector: CollisionDetector, num: int,
                       length: float = 0.3) -> np.ndarray | None:
    """Back the way the camera came: ``num`` poses along the earlier cameras' positions (the views' centres, latest
    first, starting from the one nearest the current camera) for an arc length of ``length`` x d0 (at least
    2 r_safe; less if the earlier path is shorter), rotations by SLERP to a pose there looking at ``o``. None if
    the earlier cameras are within r_safe of the current one, or a pose would go below the ground plane.

    The path is held neither to the clearance from the cloud nor to the seen free space: the camera passed there in
    truth (a clip that G had passed, the explorer's through unknown space it had looked at first), and what the
    cloud puts on that path comes from the lifted frames of the same clip (the demo room: its estimated cloud lies
    0.03 m from the clip's estimated cameras, whose true clearance was 0.42 m)."""
    x0 = np.asarray(current[:3, 3], dtype=np.float64)
    cams = detector.centres[::-1]
    if len(cams) == 0:
        return None
    start = int(np.argmin(np.linalg.norm(cams - x0, axis=1)))
    poly = np.concatenate([x0[None], cams[start:]])
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    total = min(arc[-1], max(length * d0, 2 * detector.r_safe))
    if total < detector.r_safe:
        return None
    s = np.linspace(0.0, total, num)
    pos = np.stack([np.interp(s, arc, poly[:, i]) for i in range(3)], 1)
    forward = level_forward(current)
    end = look_at_centre(pos[-1], np.asarray(centre, dtype=np.float64), forward)
    traj = interpolate_poses(current, end, num)
    traj[:, :3, 3] = pos
    traj[-1] = end
    if detector.ground is not None and (pos @ detector.ground[0] + detector.ground[1] < 0).any():
        return None
    return traj


def fallback_move(current: np.ndarray, centre: np.ndarray, d0: float, detector: CollisionDetector,
                  num: int) -> tuple[np.ndarray, str]:
    """What a planner does when no planned path passes G: back the way the camera came (``retrace_trajectory``);
    with no earlier path to retrace (the first clip), a retreat G passes (``retreat_trajectory``); else the camera
    stays put. Returns the path and its name ("retrace", "retreat", "static").

    Retrace first: planning fails where the last clip's drift left the camera somewhere the estimate gets wrong
    (the demo room: 0.26 m from a ceiling nobody had seen; development street 0: 0.04 m from a surface the cloud
    lacked, after a 13 m dolly), and the way it came is the one stretch of space it is known to have passed; a
    retreat there chose a 0.25 m move, as the estimate showed nothing near, and 24 of the clip's 25 frames stayed
    within r_safe."""
    retrace = retrace_trajectory(current, centre, d0, detector, num)
    if retrace is not None:
        return retrace, "retrace"
    retreat = retreat_trajectory(current, centre, d0, detector, num)
    if retreat is not None:
        return retreat, "retreat"
    return np.repeat(current[None], num, axis=0), "static"


def retreat_trajectory(current: np.ndarray, centre: np.ndarray, d0: float, detector: CollisionDetector,
                       num: int, steps: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0, 4.0),
                       target: float = 3.0) -> np.ndarray | None:
    """The fallback when no planned path passes G: a short straight move (``num`` poses, rotations by SLERP) to
    the position deepest inside the space known to be safe, among positions ``steps`` x r_safe from the current
    camera (at most 0.3 d0) in 26 directions, towards ``o`` and away from the nearest cloud point; every end looks
    at ``o``. An end's depth is the smaller of its clearance from every observed surface and its distance to the
    nearest space that no view saw free (probes in 26 directions out to ``target`` x r_safe): unseen space may hold
    a surface nobody observed. Only paths that pass G whole count (the follow error included, the escape from a
    start too near a surface forgiven). Depth counts up to ``target`` x r_safe; among ends that reach it (or tie) the
    shortest move wins (less drift). None when no move passes G.

    Why: standing still is not safe when an earlier clip's true camera drifted next to a surface (the demo room:
    0.26 m from its ceiling, r_safe 0.28 m; two static clips put all 162 of their frames within r_safe). Maximising
    the clearance from observed surfaces alone took that camera further up, into the ceiling no view had shown
    (true clearance 0.01 m); counting unseen space as a possible surface takes it back into the room."""
    x0 = np.asarray(current[:3, 3], dtype=np.float64)
    c = np.asarray(centre, dtype=np.float64)
    dirs = list(_directions26())
    if np.linalg.norm(c - x0) > 1e-9:
        dirs.append((c - x0) / np.linalg.norm(c - x0))
    if detector.tree is not None:
        _, i = detector.tree.query(x0)
        away = x0 - detector.points[i]
        if np.linalg.norm(away) > 1e-9:
            dirs.append(away / np.linalg.norm(away))
    dirs_a = np.stack(dirs)
    lengths = np.minimum(np.asarray(steps, dtype=np.float64) * detector.r_safe, 0.3 * d0)
    ends = (x0[None, None] + lengths[None, :, None] * dirs_a[:, None]).reshape(-1, 3)
    length = np.broadcast_to(lengths[None], (len(dirs_a), len(lengths))).reshape(-1)
    cap = target * detector.r_safe
    value = np.minimum(detector.clearance(ends), free_depth(ends, detector, cap))
    value[detector.collides(ends)] = -np.inf  # an end G rejects on its own
    forward = level_forward(current)
    for j in np.lexsort((length, -value)):  # most clearance first, then the shortest move
        if not np.isfinite(value[j]):
            break
        end = look_at_centre(ends[j], c, forward)
        traj = interpolate_poses(current, end, num)
        if not detector.trajectory_collides(traj):
            return traj
    return None


# --------------------------------------------------------------------------------------------------
# Planners
# --------------------------------------------------------------------------------------------------
@dataclass
class PlanningState:
    current: np.ndarray  # [4, 4] current camera pose (world)
    centre: np.ndarray  # [3] scene centre o
    d0: float  # distance from the input camera to o (scales the search space)
    K: np.ndarray  # [3, 3] intrinsics of masks and frames
    height: int
    width: int
    cloud_points: np.ndarray  # [N, 3]
    views: list[SeenView]
    num_frames: int
    point_size: float  # world size of a cloud point (for splatting)


@dataclass
class PlanResult:
    trajectory: np.ndarray  # [T, 4, 4] final
    initial_trajectory: np.ndarray  # [T, 4, 4] before collision optimisation
    candidates: np.ndarray  # [C, 4, 4]
    scores: np.ndarray  # [C]
    collides: np.ndarray  # [C] bool (all False for planners without a detector)
    masks: np.ndarray | None  # [C, H, W] bool; None: scored without masks (the explorer's voxel map)
    chosen: int  # index into candidates, -1 when the camera stays put
    optimised: bool = False
    collision_free: bool | None = None  # None: the planner does not check
    # "", "next-candidate" (the best one had no safe path), "shortened-<f>" (explorer), or, when no candidate had a
    # safe path, ``fallback_move``'s "retrace", "retreat" or "static"
    fallback: str = ""
    rounds: int = 1
    timings: dict[str, float] = field(default_factory=dict)


def planning_cloud(state: PlanningState, r_safe: float | None = None) -> np.ndarray:
    """The cloud thinned once per planning call, to the splat size (and at most ``r_safe / 8``, so the
    collision detector can use it as is): masks and clearances need no finer detail."""
    voxel = state.point_size if r_safe is None else min(state.point_size, r_safe / 8)
    return thin_points(state.cloud_points, voxel)


def _masks_and_scores(state: PlanningState, points: np.ndarray, cands: np.ndarray, skip: np.ndarray,
                      score) -> tuple[np.ndarray, np.ndarray]:
    """Visibility masks of the candidates not skipped (the cloud splatted into them) and ``score(mask)`` of each
    (skipped ones: an empty mask, score 0)."""
    masks = np.zeros((len(cands), state.height, state.width), dtype=bool)
    scores = np.zeros(len(cands))
    for i, c2w in enumerate(cands):
        if skip[i]:
            continue
        masks[i] = render_points(points, c2w, state.K, state.height, state.width, state.point_size).mask
        scores[i] = score(masks[i])
    return masks, scores


def planning_detector(state: PlanningState, cfg: PlanConfig, rng: np.random.Generator
                      ) -> tuple[np.ndarray, CollisionDetector]:
    """The thinned cloud and the collision detector G of a planning call (ground plane estimated from the cloud)."""
    points = planning_cloud(state, cfg.safe_radius)
    ground = estimate_ground(points, state.current[:3, 3], rng, tolerance=cfg.safe_radius / 4)
    return points, CollisionDetector(points, cfg.safe_radius, state.views, thin=False,
                                     unknown_is_free=cfg.unknown_space == "free", ground=ground,
                                     follow_error=cfg.follow_error)


class CollisionAwarePlanner:
    """The paper's Algorithm 1 (one iteration per call)."""

    name = "collision_aware"

    def __init__(self, config: PlanConfig) -> None:
        self.config = config

    def plan(self, state: PlanningState, rng: np.random.Generator) -> PlanResult:
        cfg = self.config
        t0 = time.perf_counter()
        points, detector = planning_detector(state, cfg, rng)
        t_tree = time.perf_counter()
        # draw K candidates at a time (the baseline draws the same), a colliding one pulled towards o until G
        # passes it; again, at most max_resample times, until K pass (those that still collide keep an empty mask)
        cands, collides = [], []
        while len(cands) <= cfg.max_resample:
            c = candidate_rounds(state, cfg, rng, 1)
            hit = detector.collides(c[:, :3, 3])
            for j in np.flatnonzero(hit):
                moved = repair_candidate(c[j], state.current, state.centre, state.d0, search_space(cfg), detector)
                if moved is not None:
                    c[j], hit[j] = moved, False
            cands.append(c)
            collides.append(hit)
            if sum(int((~x).sum()) for x in collides) >= cfg.num_candidates:
                break
        rounds = len(cands)
        cands_a, collides_a = np.concatenate(cands), np.concatenate(collides)
        masks_a, scores_a = _masks_and_scores(state, points, cands_a, collides_a,
                                              lambda m: visibility_score(m, cfg.anchor_fraction))
        t_score = time.perf_counter() - t_tree
        T = state.num_frames
        first_initial = None
        for rank, i in enumerate(np.argsort(-scores_a, kind="stable")):
            if collides_a[i] or scores_a[i] <= 0:
                break
            initial = spherical_interpolate(state.current, cands_a[i], T, state.centre)
            first_initial = initial if first_initial is None else first_initial
            opt = optimise_trajectory(initial, detector, state.centre, cfg.smoothness)
            if opt.collision_free:
                return self._result(opt.trajectory, initial, cands_a, scores_a, collides_a, masks_a, int(i),
                                    opt.optimised, "" if rank == 0 else "next-candidate", rounds, t0, t_tree,
                                    t_score)
        # no candidate has a path G passes: move away (``fallback_move``) rather than stand where an earlier clip's
        # drift left the camera
        final, how = fallback_move(state.current, state.centre, state.d0, detector, T)
        return self._result(final, first_initial if first_initial is not None else final, cands_a, scores_a,
                            collides_a, masks_a, -1, False, how, rounds, t0, t_tree, t_score)

    @staticmethod
    def _result(traj, initial, cands, scores, collides, masks, chosen, optimised, fallback, rounds, t0, t_tree,
                t_score) -> PlanResult:
        t_end = time.perf_counter()
        timings = {"detector_s": t_tree - t0, "candidates_s": t_score,
                   "trajectory_s": t_end - t_tree - t_score, "total_s": t_end - t0}
        return PlanResult(traj, initial, cands, scores, collides, masks, chosen, optimised=optimised,
                          collision_free=True, fallback=fallback, rounds=rounds, timings=timings)


def candidate_rounds(state: PlanningState, cfg: PlanConfig, rng: np.random.Generator, rounds: int) -> np.ndarray:
    """``rounds`` draws of K candidates in S (``sample_candidates``), concatenated."""
    return np.concatenate([sample_candidates(state.centre, state.d0, search_space(cfg), cfg.num_candidates, rng)
                           for _ in range(rounds)])


def occlusion_utility(mask: np.ndarray) -> float:
    """ViewCrafter's utility of a candidate: the area its point-cloud render leaves empty (the occlusion mask)."""
    return 1.0 - float(np.mean(mask))


class ViewCrafterPlanner:
    """Baseline: ViewCrafter's next-best view as its paper and code describe it: K candidates drawn from the same
    search space S (the quarter sphere about ``o``) by the same sampler and seed as ours (with the default
    ``max_resample = 0`` both score exactly K), the one whose render leaves the largest area empty
    (``occlusion_utility``; ViewCrafter takes the candidate of smallest rendered mask), a spherical interpolation
    about ``o`` (ViewCrafter's ``generate_traj_specified``), no collision check and no optimisation."""

    name = "viewcrafter"

    def __init__(self, config: PlanConfig) -> None:
        self.config = config

    def plan(self, state: PlanningState, rng: np.random.Generator) -> PlanResult:
        cfg = self.config
        t0 = time.perf_counter()
        cands = candidate_rounds(state, cfg, rng, 1)
        none = np.zeros(len(cands), dtype=bool)
        masks, scores = _masks_and_scores(state, planning_cloud(state), cands, none, occlusion_utility)
        t_score = time.perf_counter()
        i = int(np.argmax(scores))
        traj = spherical_interpolate(state.current, cands[i], state.num_frames, state.centre)
        t_end = time.perf_counter()
        timings = {"detector_s": 0.0, "candidates_s": t_score - t0, "trajectory_s": t_end - t_score,
                   "total_s": t_end - t0}
        return PlanResult(traj, traj, cands, scores, none, masks, i, timings=timings)


PLANNERS = {CollisionAwarePlanner.name: CollisionAwarePlanner, ViewCrafterPlanner.name: ViewCrafterPlanner}


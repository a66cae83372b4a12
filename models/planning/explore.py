"""A planner that explores safely (``plan.strategy: explorer``, issue 30; the benchmark's "ours").

Algorithm 1's structure stays (candidates, collision detector G, score F, interpolation, collision optimisation),
with three levers:

1. **F is information gain over a voxel map** (``VoxelMap``): a grid about the scene centre ``o`` (side 3 d0,
   ``explore_voxels`` cells along it) whose cells are *occupied* (a cloud point lies in them), *free* (some earlier
   view saw them in front of its depth: every lifted depth map carves free space) or *unknown*. A candidate
   *trajectory* is scored on ``explore_frames`` of its frames at low resolution (``explore_rays`` rays a side):
   each ray marches through the grid and counts the unknown cells it passes before the first occupied one, each
   weighted by the depth accuracy expected at its range z: the probability that a depth error of
   ``explore_depth_error`` x z stays within ``explore_accuracy`` x d0 (erf(a d0 / (sqrt 2 e z))); a cell seen by
   several frames counts once (the union over the clip). The **anchor term**: each frame must keep known content
   (rays ending on an occupied cell) in a share ``m`` of its view: the score is multiplied by the smallest
   min(1, m / ``explore_anchor``) over the scored frames, so the video model always has something to copy.
   **Accuracy of known content** (``explore_revisit``): the first occupied cell each ray meets adds
   ``explore_revisit`` x max(0, erf weight at this range - erf weight at the nearest range any earlier view saw it
   at, ``VoxelMap.zmin``): a view that comes nearer to lifted content re-lifts it with a smaller depth error, and
   that content is anchored, so the video model copies it (issue 30: most of the 5 cm coverage lost on seen surface
   is hallucination and range-grown depth error). Optionally unknown cells count less the farther they lie from
   known content (``explore_anchor_falloff``: what a video model invents far from its cloud is not the truth).
2. **Many more candidate trajectories** for the same synthesis budget (one clip of the same length per
   iteration): end positions on a grid over the search space S (azimuth x elevation x radius), each looking at
   ``o`` or turned by +-``explore_yaw_deg``, joined to the current pose by three shapes (``arc``: the spherical
   interpolation about ``o``; ``dolly``: a straight line; ``orbit``: azimuth, elevation and radius about ``o``
   interpolated linearly); the ends are pre-scored on their last frame alone, the best
   ``explore_candidates`` trajectories on ``explore_frames`` frames.
3. **Optimistic but safe unknown space** (``ExplorerDetector``): besides the seen free space of G, a camera may
   stand in unknown space if it is at least r_safe above the ground plane, never behind a surface an earlier view
   observed, and an earlier frame of the same clip (at least ``lag`` frames before) looks at it through cells that
   are free or unknown (nothing observed in the way): the clip then shows that space before the camera enters it.
   The first ``explore_prefix`` of the clip's frames stay in seen free space, a prefix to fall back on. The clearance
   (r_safe plus the follow error along the path) from every observed surface is G's. With ``explore_ball`` > 0 such a
   frame's clearance ball must have been seen or looked at too (``ExplorerDetector.ball_seen``; with
   ``explore_ball_up`` only the part of it above the frame; with ``explore_ball_open_sky`` false not at all where the
   input photo shows sky: ``under_open_sky``).

The best trajectory that G passes is taken; when none passes, the best few are handed to the collision
optimisation (with their end poses), then the next ones; with no safe path the camera stays put.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import erf

from navcrafter.models.camera.cameras import (
    axis_angle_to_matrix,
    camera_directions,
    interpolate_poses,
    look_at,
)
from navcrafter.models.planning.config import PlanConfig
from navcrafter.models.planning.planners import (
    WORLD_UP,
    CollisionDetector,
    PlanningState,
    PlanResult,
    SeenView,
    _directions26,
    estimate_ground,
    fallback_move,
    forgive_escape,
    level_forward,
    look_at_centre,
    optimise_trajectory,
    planning_cloud,
    search_space,
    space_positions,
)
from navcrafter.models.planning.voxel_kernels import FREE, OCCUPIED, UNKNOWN, carve, march, observe
from navcrafter.models.reconstruction.pointrender import render_points

SHAPES = ("arc", "dolly", "orbit")
# ``plan.explore_ball_open_sky``: the share of the input photo's pixels without depth from which it shows sky (the
# simulated rooms and table-tops have none: closed shells; a street's sky fills a large part of its photo)
SKY_SHARE = 0.01


@dataclass
class VoxelMap:
    """Free / occupied / unknown cells of a cube about ``origin`` (its lowest corner), ``size`` cells of ``voxel``."""

    origin: np.ndarray
    voxel: float
    size: int
    state: np.ndarray  # [size**3] uint8 (UNKNOWN, FREE, OCCUPIED), flat index (i * size + j) * size + k
    occluded: np.ndarray  # [size**3] bool: behind a surface some view observed
    to_free: np.ndarray | None = None  # [size**3] distance (cells) to the nearest free cell
    zmin: np.ndarray | None = None  # [size**3] nearest z-depth any view saw the (occupied) cell at; inf: none

    @classmethod
    def build(cls, state: PlanningState, points: np.ndarray, cells: int, side_d0: float = 3.0,
              free_views: list[SeenView] | None = None) -> VoxelMap:
        """``free_views``: the views that carve free space (``carving_views``), in place of ``state.views``; the
        nearest range each occupied cell was seen at comes from ``state.views`` (their anchored pixels) either way."""
        voxel = side_d0 * state.d0 / cells
        origin = np.asarray(state.centre, dtype=np.float64) - side_d0 * state.d0 / 2
        idx = np.stack(np.meshgrid(*[np.arange(cells)] * 3, indexing="ij"), -1).reshape(-1, 3)
        centres = origin + (idx + 0.5) * voxel
        free = np.zeros(len(centres), dtype=bool)
        behind = np.zeros(len(centres), dtype=bool)
        for v in state.views if free_views is None else free_views:  # depth maps carve free space in front
            carve(centres, *cls._view_args(v), voxel, free, behind)
        grid = np.full(len(centres), UNKNOWN, dtype=np.uint8)
        grid[free] = FREE
        occ = cls._cells(origin, voxel, cells, points)
        grid[occ] = OCCUPIED
        from scipy.ndimage import distance_transform_edt

        to_free = distance_transform_edt(grid.reshape(cells, cells, cells) != FREE).reshape(-1)
        zmin = np.full(len(centres), np.inf)
        if len(occ):
            zo = np.full(len(occ), np.inf)
            for v in state.views:  # the nearest range each occupied cell was seen at (copied content only)
                observe(centres, occ.astype(np.int64), *cls._view_args(v), voxel, zo)
            zmin[occ] = zo
        return cls(origin, voxel, cells, grid, behind & (grid != FREE), to_free, zmin)

    @staticmethod
    def _view_args(v) -> tuple:
        """A view as the voxel kernels take it: rotation, position, fx, fy, cx, cy, depth, anchored mask, whether
        the mask applies."""
        anchored = np.ones((1, 1), dtype=bool) if v.anchored is None else np.ascontiguousarray(v.anchored, bool)
        return (np.ascontiguousarray(v.c2w[:3, :3], dtype=np.float64),
                np.ascontiguousarray(v.c2w[:3, 3], dtype=np.float64), float(v.K[0, 0]), float(v.K[1, 1]),
                float(v.K[0, 2]), float(v.K[1, 2]), np.ascontiguousarray(v.depth, dtype=np.float64), anchored,
                v.anchored is not None)

    def to_occupied(self) -> np.ndarray:
        """[size**3] distance (cells) to the nearest occupied cell (only ``explore_anchor_falloff`` needs it)."""
        from scipy.ndimage import distance_transform_edt

        n = self.size
        return distance_transform_edt(self.state.reshape(n, n, n) != OCCUPIED).reshape(-1)

    def reach(self, x: np.ndarray) -> np.ndarray:
        """Distance (world units) from positions to the nearest free cell (0 inside free space; inf outside)."""
        idx = self.index(x)
        return np.where(idx >= 0, self.to_free[np.maximum(idx, 0)] * self.voxel, np.inf)

    @staticmethod
    def _cells(origin: np.ndarray, voxel: float, cells: int, points: np.ndarray) -> np.ndarray:
        ijk = np.floor((np.asarray(points, dtype=np.float64).reshape(-1, 3) - origin) / voxel).astype(int)
        ok = ((ijk >= 0) & (ijk < cells)).all(1)
        ijk = ijk[ok]
        return np.unique((ijk[:, 0] * cells + ijk[:, 1]) * cells + ijk[:, 2])

    def index(self, x: np.ndarray) -> np.ndarray:
        """Flat cell index of positions ``[..., 3]`` (-1 outside the grid)."""
        ijk = np.floor((x - self.origin) / self.voxel).astype(np.int64)
        ok = ((ijk >= 0) & (ijk < self.size)).all(-1)
        flat = (ijk[..., 0] * self.size + ijk[..., 1]) * self.size + ijk[..., 2]
        return np.where(ok, flat, -1)

    def lookup(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(cell index, state) of positions; outside the grid: (-1, FREE) (nothing known blocks a ray there)."""
        idx = self.index(x)
        st = np.where(idx >= 0, self.state[np.maximum(idx, 0)], FREE)
        return idx, st


class ExplorerDetector(CollisionDetector):
    """G with optimistic-but-safe unknown space (module docstring, lever 3) for whole trajectories."""

    def __init__(self, *args, vmap: VoxelMap, prefix: float = 0.1, lag: int = 2, reach: float = 1.0,
                 ball: float = 0.0, ball_follow_error: float | None = None, ball_up: bool = False,
                 ball_seen_free: bool = False, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.vmap, self.prefix, self.lag = vmap, float(prefix), int(lag)
        self.ball = float(ball)  # ``plan.explore_ball``: share of the clearance whose ball must be seen (0: off)
        # ``plan.explore_ball_follow_error``: what the ball grows with along the path (None: G's follow error)
        self.ball_follow_error = self.follow_error if ball_follow_error is None else float(ball_follow_error)
        self.ball_up = bool(ball_up)  # ``plan.explore_ball_up``: the ball's probes only above the frame
        self.ball_seen_free = bool(ball_seen_free)  # ``plan.explore_ball_seen_free``: asked in seen free space too
        self.max_reach = float(reach) * vmap.voxel  # unknown space is entered at most this far from free space

    def start_radius(self) -> float:
        """How far from the clip's start its first frames may stand outside the seen free space: 2 r_safe, or one
        map cell (3 d0 / ``explore_voxels``) where that is more. The start camera stands at the apex of its own
        view, so any sideways or rising move leaves the space it saw; a street's clip moves ~0.5 m a frame (d0 is
        ~10 m), more than 2 r_safe (development street 0: every trajectory's second frame fell outside, and the
        first clip retreated by 1 unit instead of exploring)."""
        return max(2 * self.r_safe, self.vmap.voxel)

    def _above_ground(self, x: np.ndarray) -> np.ndarray:
        if self.ground is None:
            return np.ones(len(x), dtype=bool)
        return x @ self.ground[0] + self.ground[1] >= self.r_safe

    def _line_of_sight(self, a: np.ndarray, b: np.ndarray) -> bool:
        """No occupied cell between ``a`` and ``b`` (nor within r_safe of ``b``'s cell on the way)."""
        return bool(self._sight_many(a[None], b[None])[0])

    @staticmethod
    def _in_frustum(p: np.ndarray) -> np.ndarray:
        """Per point in a camera's frame (``p[:, 2]`` along its view): in front and within its looking cone."""
        z = np.maximum(p[:, 2], 1e-12)
        return (p[:, 2] > 1e-6) & (np.abs(p[:, 0] / z) < 0.9) & (np.abs(p[:, 1] / z) < 0.9)

    def _sight_many(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Per pair of positions ``a[i]``, ``b[i]``: no occupied cell between them (``_line_of_sight`` for many)."""
        if len(a) == 0:
            return np.zeros(0, dtype=bool)
        n = max(2, int(np.ceil(np.linalg.norm(b - a, axis=1).max() / (self.vmap.voxel / 2))))
        s = np.linspace(0.0, 1.0, n)[1:]
        _, st = self.vmap.lookup(a[:, None] + s[None, :, None] * (b - a)[:, None])
        return ~(st == OCCUPIED).any(1)

    def ball_seen(self, trajectory: np.ndarray, t: int, radius: float) -> bool:
        """Whether frame ``t``'s clearance ball (probes at 0.5 and 1 x ``radius`` in 26 directions) was seen: each
        probe seen free by an earlier view, below the ground plane (a known surface: G's clearance keeps the camera
        off it), within r_safe of an earlier frame's position in this clip (the camera passed there: G treats earlier
        cameras' surroundings so; without it the ball behind a moving camera, which no frame looks at, refused
        nearly every move: explore11's first version), or looked at by an earlier frame of the clip (at least ``lag``
        frames before) with no occupied cell in the way (a probe in an observed surface's shadow too: G's clearance
        already keeps every observed surface out of the ball; refusing shadow probes outright refused nearly every
        move in explore11's second version). Cameras look at ``o``, so
        the space above a frame high in S (a ceiling) lies outside every frustum of its clip though the position
        itself was in view (explore10: room 0, an unseen ceiling 0.30 m above a dolly's end)."""
        x = trajectory[t, :3, 3]
        dirs = _directions26()
        if self.ball_up:  # only the directions rising from the ground plane (from the clip's first camera without one)
            up = self.ground[0] if self.ground is not None else -trajectory[0, :3, 1]
            dirs = dirs[dirs @ (up / np.linalg.norm(up)) > 0.5]
        probes = (x[None, None] + np.array([0.5, 1.0])[:, None, None] * radius * dirs[None]).reshape(-1, 3)
        free, occluded = self._visibility(probes)
        idx, _ = self.vmap.lookup(probes)
        occluded = occluded | np.where(idx >= 0, self.vmap.occluded[np.maximum(idx, 0)], False)
        if self.ground is not None:
            free |= probes @ self.ground[0] + self.ground[1] < 0
        if t > 0:  # the clip's own camera passed there (G counts space within r_safe of an earlier camera so)
            passed = trajectory[:t, :3, 3]
            free |= np.linalg.norm(probes[:, None] - passed[None], axis=-1).min(1) < self.r_safe
        pending = np.flatnonzero(~free)  # unknown or in an observed surface's shadow: an earlier frame must look
        earlier = trajectory[:max(t - self.lag + 1, 0)]
        for s in range(len(earlier) - 1, -1, -1):  # the latest first
            if len(pending) == 0:
                break
            look = self._in_frustum((probes[pending] - earlier[s, :3, 3]) @ earlier[s, :3, :3])
            if look.any():
                j = pending[look]
                ok = self._sight_many(np.repeat(earlier[s, None, :3, 3], len(j), 0), probes[j])
                pending = np.setdiff1d(pending, j[ok], assume_unique=True)
        return len(pending) == 0

    def path_flags(self, trajectory: np.ndarray, first_only: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per pose: too near an observed surface; not admissible (outside seen free space and not entered the safe
        way: see the module docstring); the clearance. ``first_only``: stop at the first flagged pose."""
        x = trajectory[:, :3, 3]
        clearance, needed = self.clearance(x), self.path_clearance(x)
        near = forgive_escape(clearance, clearance < needed)
        if first_only and near.any():
            return near, np.zeros(len(x), dtype=bool), clearance
        free, occluded = self._visibility(x)
        idx, _ = self.vmap.lookup(x)
        occluded = occluded | np.where(idx >= 0, self.vmap.occluded[np.maximum(idx, 0)], False)
        start = x[0]
        fixed = int(np.ceil(self.prefix * len(x)))
        # the prefix: seen free, or next to where the camera stands (the clip's first frames barely move)
        unseen = ~(free | (np.linalg.norm(x - start, axis=1) < self.start_radius()))
        ok_ground = self._above_ground(x)
        reach = self.vmap.reach(x)
        ball_need = self.path_clearance(x, self.ball_follow_error) if self.ball > 0 else needed
        # ``explore_ball_seen_free``: the ball of a frame past the prefix in seen free space is asked too (seen free
        # vouches for the position, not for the space about it: collide14, room 7 of CRN base seed 4)
        ball_free = ((np.arange(len(x)) >= fixed) & ~unseen if self.ball > 0 and self.ball_seen_free
                     else np.zeros_like(unseen))
        for t in np.flatnonzero(unseen | ball_free):
            if ball_free[t]:
                unseen[t] = not self.ball_seen(trajectory, t, self.ball * ball_need[t])
            elif t >= fixed and not occluded[t] and ok_ground[t] and reach[t] <= self.max_reach:
                # an earlier frame of this clip (the latest first) looks at it, nothing in the way
                earlier = trajectory[:max(t - self.lag + 1, 0)]
                look = self._in_frustum(np.einsum("sji,sj->si", earlier[:, :3, :3], x[t] - earlier[:, :3, 3]))
                for s in np.flatnonzero(look)[::-1]:
                    if self._line_of_sight(earlier[s, :3, 3], x[t]):
                        unseen[t] = False
                        break
                if not unseen[t] and self.ball > 0:  # its clearance ball must have been seen too
                    unseen[t] = not self.ball_seen(trajectory, t, self.ball * ball_need[t])
            if first_only and unseen[t]:
                unseen[t + 1:] = False
                break
        return near, unseen, clearance

    def trajectory_collides(self, trajectory: np.ndarray) -> bool:
        near, unseen, _ = self.path_flags(trajectory, first_only=True)
        return bool((near | unseen).any())


def under_open_sky(views: list[SeenView]) -> bool:
    """Whether the observations (views without ``anchored`` pixels: the input photo) show sky, i.e. at least
    ``SKY_SHARE`` of their pixels have no depth: the geometry found no surface on those rays, and nothing caps the
    scene (``plan.explore_ball_open_sky``)."""
    seen = [v.depth for v in views if v.anchored is None]
    return bool(seen) and float(np.mean(np.concatenate([(d <= 0).ravel() for d in seen]))) >= SKY_SHARE


def open_sky(views: list[SeenView]) -> list[SeenView]:
    """The views with every pixel of no depth (0: the geometry found no surface, i.e. sky) of an *observation* (a view
    without ``anchored`` pixels: the input photo) seeing free space without end (depth +inf): its ray met nothing.
    A generated frame's empty pixels stay unknown (the video model may have drawn sky where a building stands)."""
    out = []
    for v in views:
        if v.anchored is None and (v.depth <= 0).any():
            v = SeenView(v.c2w, v.K, np.where(v.depth > 0, v.depth, np.inf), None)
        out.append(v)
    return out


def carving_views(views: list[SeenView], free_space: str, share: float) -> list[SeenView]:
    """The views as they carve free space under ``plan.explore_free_space``: ``anchored`` and ``all`` as given (the
    plan step computed the anchored pixels, or none for ``all``); ``share``: a generated frame at least ``share`` of
    whose pixels are anchored carves free space with every pixel that has a depth (its empty pixels stay unknown, not
    sky: ``open_sky``), a frame below it with its anchored pixels only. Why: under ``all`` the room collisions on
    development seeds came from frames that were almost wholly invented (room 3's third clip entered free space carved
    by a frame 1 % anchored, whose invented depth 11.2 units lay past a true surface at 1.25) and from generated
    frames' empty pixels opened as sky (room 3's second clip: with them unknown, G refuses that path)."""
    if free_space != "share":
        return views
    out = []
    for v in views:
        if v.anchored is not None and float(np.mean(v.anchored)) >= share:
            v = SeenView(v.c2w, v.K, v.depth, np.ones_like(v.anchored, dtype=bool))  # still generated: no sky
        out.append(v)
    return out


def repairable(det: ExplorerDetector, trajectory: np.ndarray) -> bool:
    """Whether the collision optimisation could repair ``trajectory`` at all. It moves the interior positions away
    from observed surfaces with both ends fixed, and has no term for admissibility (seen free space, or unknown space
    entered the safe way): a path with an inadmissible frame, or whose end pose stands nearer a surface than even the
    straight path's clearance (r_safe + the follow error times the chord; every path is at least that long) demands,
    cannot pass G after it. Measured on development room 0 (seed 0, quick sizes, iteration 3): all three hopeless
    optimisations (33 L-BFGS starts each) failed and took 7.5 of the planner's 8.5 s."""
    near, unseen, clearance = det.path_flags(trajectory)
    if unseen.any():
        return False
    x = trajectory[:, :3, 3]
    return bool(clearance[-1] >= det.r_safe + det.follow_error * np.linalg.norm(x[-1] - x[0]))


def anchored_pixels(depth: np.ndarray, c2w: np.ndarray, K: np.ndarray, prior_points: np.ndarray,
                    point_size: float, rel_tol: float) -> np.ndarray:
    """Pixels of a generated frame (lifted ``depth`` ``[H, W]`` at its estimated camera ``c2w``, intrinsics ``K``)
    whose depth agrees, within ``rel_tol`` of the depth, with the point cloud the video model was conditioned on
    (``prior_points``, rendered from the same camera): there the model copied content it was shown. Elsewhere it
    invented the content, and its depth is no evidence that the space in front is free: an object nobody saw may
    stand there, drawn elsewhere or not at all (a video model's hallucinations move objects and walls; the honest
    simulation's variants do the same)."""
    H, W = depth.shape
    if len(prior_points) == 0:
        return np.zeros((H, W), dtype=bool)
    dc = render_points(prior_points, c2w, K, H, W, float(point_size)).depth.astype(np.float64)
    d = np.asarray(depth, dtype=np.float64)
    return (d > 0) & (dc > 0) & (np.abs(d - dc) <= rel_tol * dc)


class _Scorer:
    """Information gain (union over frames) and anchoring of candidate trajectories: each ray of a frame (``dirs``,
    camera frame, z = 1) is sampled one cell apart through the map up to its first occupied cell
    (``voxel_kernels.march``); an unknown cell it passes counts with the accuracy weight of its range z."""

    def __init__(self, vmap: VoxelMap, state: PlanningState, cfg: PlanConfig) -> None:
        self.vmap, self.cfg, self.d0 = vmap, cfg, state.d0
        n = cfg.explore_rays
        scale = n / max(state.height, state.width)
        h, w = max(2, round(state.height * scale)), max(2, round(state.width * scale))
        K = np.asarray(state.K, dtype=np.float64).copy()
        K[0] *= w / state.width
        K[1] *= h / state.height
        dirs = camera_directions(K, h, w).reshape(-1, 3)
        max_range = np.sqrt(3) * vmap.size * vmap.voxel / 2
        step = vmap.voxel
        self.dist = (np.arange(int(np.ceil(max_range / step))) + 0.5) * step  # distance along the unit ray
        norm = np.linalg.norm(dirs, axis=1)
        self.unit = np.ascontiguousarray(dirs / norm[:, None])
        z = self.dist[None, :] / norm[:, None]  # z-depth of each sample [R, S]
        self.weight = np.ascontiguousarray(self.accuracy(z))
        n_cells = vmap.size ** 3
        if cfg.explore_anchor_falloff > 0:
            s = np.maximum(0.0, vmap.to_occupied() - 1.0) * vmap.voxel
            self.prox = np.ascontiguousarray(np.exp(-s / (cfg.explore_anchor_falloff * state.d0)))
        else:
            self.prox = np.ones(n_cells)
        self.revisit = float(cfg.explore_revisit)
        if self.revisit > 0 and vmap.zmin is not None:
            self.acc = np.ascontiguousarray(np.where(np.isfinite(vmap.zmin), self.accuracy(vmap.zmin), 0.0))
        else:
            self.acc = np.zeros(n_cells)

    def accuracy(self, z: np.ndarray) -> np.ndarray:
        """The chance that a depth measured at z-depth ``z`` lands within ``explore_accuracy`` x d0."""
        cfg = self.cfg
        return erf(cfg.explore_accuracy * self.d0 / (np.sqrt(2.0) * cfg.explore_depth_error * np.maximum(z, 1e-6)))

    def _march(self, poses: np.ndarray, group: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
        v = self.vmap
        return march(v.state, v.size, np.asarray(v.origin, dtype=np.float64), float(v.voxel),
                     np.ascontiguousarray(poses[:, :3, :3], dtype=np.float64),
                     np.ascontiguousarray(poses[:, :3, 3], dtype=np.float64), self.unit, self.dist, self.weight,
                     group.astype(np.int64), n_groups, self.prox, self.acc, self.revisit)

    def last_frames(self, ends: np.ndarray) -> np.ndarray:
        """Score of each end pose ``[E, 4, 4]`` on its own (one frame each; cells counted once per frame)."""
        if len(ends) == 0:
            return np.zeros(0)
        gain, anchor = self._march(ends, np.arange(len(ends)), len(ends))
        return gain * np.minimum(1.0, anchor / self.cfg.explore_anchor)

    def score(self, poses: np.ndarray) -> tuple[float, float]:
        """(information gain of the union over ``poses`` times the anchor term, the least anchored share)."""
        gain, anchor = self._march(poses, np.zeros(len(poses), dtype=np.int64), 1)
        if not len(anchor):
            return 0.0, 0.0
        factor = float(np.min(np.minimum(1.0, anchor / self.cfg.explore_anchor)))
        return float(gain[0]) * factor, float(anchor.min())


def end_yaws(yaw_deg: float, turns: int = 1) -> tuple[float, ...]:
    """The turns (degrees about world up) of each end pose from looking at o: 0, then +-k ``yaw_deg`` for
    k = 1 .. ``turns``."""
    if yaw_deg <= 0:
        return (0.0,)
    return (0.0, *(s * k * float(yaw_deg) for k in range(1, int(turns) + 1) for s in (1.0, -1.0)))


def _end_pose(position: np.ndarray, centre: np.ndarray, yaw_deg: float, forward: np.ndarray) -> np.ndarray:
    """At ``position`` looking at ``centre``, then turned by ``yaw_deg`` about world up."""
    base = look_at_centre(position, centre, forward)
    if yaw_deg == 0.0:
        return base
    out = base.copy()
    out[:3, :3] = axis_angle_to_matrix(WORLD_UP, np.deg2rad(yaw_deg)) @ base[:3, :3]
    return out


def shaped_trajectory(current: np.ndarray, end: np.ndarray, centre: np.ndarray, num: int, shape: str) -> np.ndarray:
    """``num`` poses from ``current`` to ``end``: ``arc`` (spherical interpolation about ``centre``), ``dolly``
    (straight line), ``orbit`` (azimuth, elevation, radius about ``centre`` linear); rotations by SLERP; the end
    poses are exact."""
    if shape == "arc":
        return interpolate_poses(current, end, num, centre=centre)
    if shape == "dolly":
        return interpolate_poses(current, end, num)
    if shape != "orbit":
        raise ValueError(f"unknown trajectory shape {shape!r}; choose from {SHAPES}")
    out = interpolate_poses(current, end, num, centre=centre)  # rotations
    c = np.asarray(centre, dtype=np.float64)
    up = WORLD_UP

    def sph(p):
        v = p - c
        r = np.linalg.norm(v)
        el = np.arcsin(np.clip(v @ up / max(r, 1e-12), -1, 1))
        h = v - (v @ up) * up
        return r, el, h

    r0, e0, h0 = sph(current[:3, 3])
    r1, e1, h1 = sph(end[:3, 3])
    a = np.linalg.norm(h0) > 1e-9 and np.linalg.norm(h1) > 1e-9
    if not a:
        return out
    h0n, h1n = h0 / np.linalg.norm(h0), h1 / np.linalg.norm(h1)
    ang = np.arctan2(np.cross(h0n, h1n) @ up, h0n @ h1n)
    for i, f in enumerate(np.linspace(0.0, 1.0, num)):
        hd = axis_angle_to_matrix(up, f * ang) @ h0n
        r, e = (1 - f) * r0 + f * r1, (1 - f) * e0 + f * e1
        out[i, :3, 3] = c + r * (np.cos(e) * hd + np.sin(e) * up)
    out[0], out[-1] = current, end
    return out


class ExplorerPlanner:
    """The safe explorer (module docstring)."""

    name = "explorer"
    # trajectories G checks, best first, before the shortened ones: every one scored (it was 20; on development
    # street 0 the 21 best all rose out of the input view's frustum, and the camera retreated though safe ones scored)
    max_checked = 60

    def __init__(self, config: PlanConfig) -> None:
        self.config = config

    def plan(self, state: PlanningState, rng: np.random.Generator) -> PlanResult:
        cfg = self.config
        t0 = time.perf_counter()
        points = planning_cloud(state, cfg.safe_radius)
        ground = estimate_ground(points, state.current[:3, 3], rng, tolerance=cfg.safe_radius / 4)
        seen = replace(state, views=open_sky(state.views)) if cfg.explore_sky == "free" else state
        free_views = carving_views(seen.views, cfg.explore_free_space, cfg.explore_invented_share)
        vmap = VoxelMap.build(seen, points, cfg.explore_voxels, free_views=free_views)
        det = ExplorerDetector(points, cfg.safe_radius, state.views, thin=False, ground=ground,
                               follow_error=cfg.follow_error if cfg.explore_follow_error is None
                               else cfg.explore_follow_error, vmap=vmap, prefix=cfg.explore_prefix,
                               reach=cfg.explore_reach, visibility_views=free_views,
                               ball=cfg.explore_ball if cfg.explore_ball_open_sky or not under_open_sky(state.views)
                               else 0.0,
                               ball_follow_error=cfg.explore_ball_follow_error, ball_up=cfg.explore_ball_up,
                               ball_seen_free=cfg.explore_ball_seen_free)
        t_map = time.perf_counter()
        scorer = _Scorer(vmap, state, cfg)
        # end positions: a grid over S
        space = search_space(cfg)
        az = np.deg2rad(np.linspace(*space.azimuth_deg, 13))
        el = np.deg2rad(np.linspace(*space.elevation_deg, 3))
        r = state.d0 * np.linspace(space.radius[0], space.radius[1], 3)
        A, E, R = np.meshgrid(az, el, r, indexing="ij")
        pos = space_positions(state.centre, A, E, R).reshape(-1, 3)
        ok = det.clearance(pos) >= cfg.safe_radius
        ok &= det._above_ground(pos)
        _, occluded = det._visibility(pos)
        idx, _ = vmap.lookup(pos)
        ok &= ~occluded & ~np.where(idx >= 0, vmap.occluded[np.maximum(idx, 0)], False)
        ok &= vmap.reach(pos) <= det.max_reach
        pos = pos[ok]
        forward = level_forward(state.current)
        yaws = end_yaws(cfg.explore_yaw_deg, cfg.explore_yaw_turns)
        ends = [_end_pose(p, state.centre, y, forward) for p in pos for y in yaws]
        # pre-score every end on its last frame alone; the best go on as trajectories of every shape
        T = state.num_frames
        pre = scorer.last_frames(np.stack(ends)) if ends else np.zeros(0)
        n_ends = max(1, cfg.explore_candidates // len(SHAPES))
        top = np.argsort(-pre, kind="stable")[:n_ends]
        frames = np.unique(np.linspace(0, T - 1, cfg.explore_frames + 1).round().astype(int))[1:]
        trajs, scores, anchors, names = [], [], [], []
        for i in top:
            for shape in SHAPES:
                traj = shaped_trajectory(state.current, ends[i], state.centre, T, shape)
                s, a = scorer.score(traj[frames])
                trajs.append(traj)
                scores.append(s)
                anchors.append(a)
                names.append(shape)
        t_score = time.perf_counter()
        scores_a = np.asarray(scores)
        order = np.argsort(-scores_a, kind="stable")
        collides = np.zeros(len(trajs), dtype=bool)
        chosen, final, initial, optimised, fallback = -1, None, None, False, "static"
        checked = 0
        for rank, i in enumerate(order):
            if scores_a[i] <= 0:
                break
            checked += 1
            if not det.trajectory_collides(trajs[i]):
                chosen, final, initial, fallback = int(i), trajs[i], trajs[i], "" if rank == 0 else "next-candidate"
                break
            collides[i] = True
            if checked <= 3 and repairable(det, trajs[i]):  # the best few may be repaired (same end poses)
                opt = optimise_trajectory(trajs[i], det, state.centre, cfg.smoothness)
                if opt.collision_free:
                    chosen, final, initial, optimised = int(i), opt.trajectory, trajs[i], True
                    fallback = "" if rank == 0 else "next-candidate"
                    collides[i] = False
                    break
            if checked >= self.max_checked:
                break
        if final is None:  # none passes whole: the best ones cut short (a smaller step the same way), same length
            for i in order[:10]:
                for frac in (0.6, 0.35, 0.15):
                    end = shaped_trajectory(state.current, trajs[i][-1], state.centre, 11, names[i])[
                        int(round(frac * 10))]
                    short = shaped_trajectory(state.current, end, state.centre, T, names[i])
                    if not det.trajectory_collides(short):
                        chosen, final, initial, fallback = int(i), short, short, f"shortened-{frac:g}"
                        break
                if final is not None:
                    break
        if final is None:  # move away rather than stand still (``planners.fallback_move``)
            final, fallback = fallback_move(state.current, state.centre, state.d0, det, T)
            initial = trajs[int(order[0])] if len(trajs) else final
        t_end = time.perf_counter()
        cands = np.stack([t[-1] for t in trajs]) if trajs else state.current[None]
        timings = {"map_s": t_map - t0, "candidates_s": t_score - t_map, "trajectory_s": t_end - t_score,
                   "total_s": t_end - t0, "trajectories": float(len(trajs)), "ends": float(len(ends))}
        res = PlanResult(final, initial, cands, scores_a if len(trajs) else np.zeros(1), collides
                         if len(trajs) else np.zeros(1, bool), None, chosen, optimised=optimised,
                         collision_free=True, fallback=fallback, timings=timings)
        res.shape = names[chosen] if chosen >= 0 else ""  # type: ignore[attr-defined]
        return res


__all__ = ["ExplorerDetector", "ExplorerPlanner", "VoxelMap", "anchored_pixels", "carving_views", "repairable",
           "shaped_trajectory", "look_at", "under_open_sky"]

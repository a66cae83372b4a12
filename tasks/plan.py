"""Plan: the camera trajectory of iteration k (strategies in ``plan.strategy``).

* ``explorer`` (default: ``models.planning.explore``), ``collision_aware`` (the paper's Algorithm 1),
  ``viewcrafter`` and ``viewcrafter_nbv`` (baselines) run the planners of ``navcrafter.models.planning`` on the
  state read from the store: the current pose (the last pose of the previous iteration), the scene centre ``o``,
  the cloud after iteration k-1, and every earlier camera with its depth (the input view and the lifted views),
  which bounds the seen free space. The step stores the candidates (the explorer: its scored trajectories' end
  poses), their scores, collision flags and visibility masks (not the explorer's), the trajectory
  before and after collision optimisation, and a top-down plot (``topdown.png``).
* ``orbit`` (the foundation's simple planner, ``models.planning.orbit``) does not look at obstacles.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.planning.explore import anchored_pixels
from navcrafter.models.planning.orbit import orbit_azimuth_deg, orbit_radius, orbit_trajectory
from navcrafter.models.planning.planners import (
    PlanningState,
    PlanResult,
    SeenView,
    optimise_trajectory,
    planning_detector,
    scene_centre,
)
from navcrafter.models.planning.plots import topdown_png
from navcrafter.models.planning.registry import PLANNERS
from navcrafter.models.planning.user import trajectory_spec, user_path
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import GEOMETRY, LIFT
from navcrafter.schemas.store import SceneStore
from navcrafter.tasks.common import load_cloud, logger
from navcrafter.tasks.readers import current_pose, stored_scene_centre
from navcrafter.tasks.steps import StepContext


def planning_state(scene: SceneStore, k: int, config: RunConfig) -> PlanningState:
    """What the planner knows before iteration k."""
    geo = scene.read_all(GEOMETRY)
    centre = scene_centre(geo["depth"], geo["confidence"], config.plan.centre_depth_quantile)
    views = [SeenView(np.eye(4), geo["K"], geo["depth"])]
    cfg = config.plan
    point_size = 1.5 * config.lift.voxel_size
    for j in range(1, k):
        lifted = scene.read_all(LIFT, j)
        anchored = [None] * len(lifted["c2w"])
        if cfg.strategy == "explorer" and cfg.explore_free_space != "all":  # what clip j copied from the cloud
            prior = load_cloud(scene, j - 1).points
            anchored = [anchored_pixels(d, c, K, prior, point_size, cfg.explore_anchor_tolerance)
                        for c, K, d in zip(lifted["c2w"], lifted["K"], lifted["depth"])]
        views += [SeenView(c, K, d, a) for c, K, d, a in zip(lifted["c2w"], lifted["K"], lifted["depth"], anchored)]
    return PlanningState(
        current=current_pose(scene, k), centre=centre, d0=float(np.linalg.norm(centre)), K=geo["K"],
        height=config.synthesis.height, width=config.synthesis.width,
        cloud_points=load_cloud(scene, k - 1).points, views=views, num_frames=config.synthesis.num_frames,
        point_size=point_size)


def plan(ctx: StepContext) -> dict:
    cfg, scene, k = ctx.config.plan, ctx.scene, ctx.k
    if cfg.trajectory is not None:
        return user_plan(ctx)
    if cfg.strategy == "orbit":
        centre = stored_scene_centre(scene, ctx.config)
        traj, target = orbit_trajectory(k, current_pose(scene, k), centre, cfg, ctx.config.synthesis.num_frames)
        ctx.write_all(trajectory=traj, K=scene.read(GEOMETRY, None, "K"), centre=centre, candidates=target[None])
        return {"strategy": cfg.strategy, "chosen": 0,
                "azimuth_deg": orbit_azimuth_deg(k, cfg, orbit_radius(centre, cfg))}
    state = planning_state(scene, k, ctx.config)
    res = PLANNERS[cfg.strategy](cfg).plan(state, np.random.default_rng(ctx.seed))
    arrays = {"candidate_masks": res.masks} if res.masks is not None else {}
    ctx.write_all(trajectory=res.trajectory, K=state.K, centre=state.centre, candidates=res.candidates,
                  candidate_scores=res.scores, candidate_collides=res.collides,
                  initial_trajectory=res.initial_trajectory, **arrays)
    cloud = ctx.cloud(k - 1)
    ctx.write_file("topdown.png", topdown_png(cloud.points, cloud.colors, state, res, cfg.strategy, k))
    attrs = {"strategy": cfg.strategy, "chosen": res.chosen, "optimised": res.optimised, "fallback": res.fallback,
             "rounds": res.rounds, "r_safe": cfg.safe_radius, "d0": state.d0, "timings": res.timings}
    if getattr(res, "shape", ""):
        attrs["shape"] = res.shape
    if res.collision_free is not None:
        attrs["collision_free"] = res.collision_free
    return attrs


def user_plan(ctx: StepContext) -> dict:
    """A user's path (``plan.trajectory``, ``models/planning/user.py``) in place of the planner, checked by G."""

    cfg, scene, k = ctx.config.plan, ctx.scene, ctx.k
    state = planning_state(scene, k, ctx.config)
    spec = trajectory_spec(cfg.trajectory, k)
    path = user_path(spec, state.current, state.centre, state.num_frames, extent=cfg.trajectory_extent,
                     convention=cfg.trajectory_convention)
    _, detector = planning_detector(state, cfg, np.random.default_rng(ctx.seed))
    initial = path.trajectory
    near, unseen, clearance = detector.path_flags(initial)
    bad = near | unseen
    traj, optimised, warning = initial, False, ""
    if bad.any():
        frames = np.flatnonzero(bad)
        what = (f"iteration {k}: collision detector G flags the trajectory {spec.text!r} at {len(frames)} of "
                f"{len(initial)} frames (first {frames[:5].tolist()}): {int(near.sum())} closer to a surface than "
                f"r_safe {cfg.safe_radius} (+ the follow error; least clearance {float(clearance.min()):.3f}), "
                f"{int(unseen.sum())} outside the space the cameras saw free")
        if cfg.trajectory_repair:
            opt = optimise_trajectory(initial, detector, state.centre, cfg.smoothness)
            if opt.collision_free:
                traj, optimised = opt.trajectory, opt.optimised
                what += "; repaired by the collision optimisation"
            else:
                what += "; the collision optimisation found no safe path: kept as given"
        else:
            what += "; kept as given (plan.trajectory_repair=true repairs it)"
        warning = what
        logger().warning("scene %s: %s", ctx.scene_id[:12], warning)
    ctx.write_all(trajectory=traj, K=state.K, centre=state.centre, candidates=traj[-1:],
                  candidate_collides=np.array([bool(bad.any())]), initial_trajectory=initial)
    cloud = ctx.cloud(k - 1)

    shown = PlanResult(traj, initial, traj[-1:], np.zeros(1), np.array([bool(bad.any())]),
                       np.zeros((1, state.height, state.width), dtype=bool), 0, optimised=optimised)
    ctx.write_file("topdown.png", topdown_png(cloud.points, cloud.colors, state, shown, "trajectory", k))
    return {"strategy": "trajectory", "chosen": 0, "trajectory": spec.text, "source": path.source,
            "collision_free": not bool(bad.any()) or optimised, "colliding_frames": int(bad.sum()),
            "optimised": optimised, "warning": warning, "r_safe": cfg.safe_radius, "d0": state.d0}

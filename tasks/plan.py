"""Plan: the camera trajectory of iteration k (strategies in ``plan.strategy``).

* ``collision_aware`` (default) and ``viewcrafter`` (baseline) run the planners of
  ``navcrafter.models.planning.planners`` on the state read from the store: the current pose (the last pose of
  the previous iteration), the scene centre ``o``, the cloud after iteration k-1, and every earlier
  camera with its depth (the input view and the lifted views), which bounds the seen free space.
  The step stores the candidates, their scores, collision flags and visibility masks, the trajectory
  before and after collision optimisation, and a top-down plot (``topdown.png``).
* ``orbit`` (the foundation's simple planner): iteration k targets the input camera position rotated
  about the world up axis through ``o`` by azimuth ``+s, -s, +2s, -2s, ...``
  (``s = plan.orbit_step_deg``, reduced so that one step moves the camera by at most
  ``plan.orbit_max_shift``), pulled towards ``o`` by ``plan.orbit_radius_scale``, looking at ``o``.
  It does not look at obstacles.
"""

from __future__ import annotations

import math

import numpy as np

from navcrafter.models.camera.cameras import axis_angle_to_matrix, interpolate_poses, look_at
from navcrafter.models.planning.planners import PLANNERS, PlannerConfig, PlanningState, SearchSpace, SeenView
from navcrafter.models.planning.plots import topdown_png
from navcrafter.schemas.config import PlanConfig, RunConfig
from navcrafter.schemas.layout import GEOMETRY, LIFT, PLAN
from navcrafter.schemas.store import SceneStore
from navcrafter.tasks.common import StepRef, load_cloud, open_store, run_step

WORLD_UP = np.array([0.0, -1.0, 0.0])  # the input camera's "up" (OpenCV: y points down)


def scene_centre(depth: np.ndarray, confidence: np.ndarray, quantile: float) -> np.ndarray:
    """The point on the input camera's optical axis at the given quantile of the input view's depth."""
    d = depth[(confidence > 0) & (depth > 0)]
    if d.size == 0:
        raise ValueError("no valid depth to place the scene centre")
    return np.array([0.0, 0.0, float(np.quantile(d, quantile))])


def orbit_azimuth_deg(k: int, cfg: PlanConfig, radius: float) -> float:
    """+s, -s, +2s, -2s, ... for k = 1, 2, 3, 4, ...; ``s`` is ``orbit_step_deg``, reduced so that one
    step moves the camera by at most ``orbit_max_shift`` on a circle of ``radius``."""
    step = cfg.orbit_step_deg
    if radius > 0 and cfg.orbit_max_shift < 2 * radius:
        step = min(step, float(np.rad2deg(2 * np.arcsin(cfg.orbit_max_shift / (2 * radius)))))
    return step * math.ceil(k / 2) * (1 if k % 2 else -1)


def orbit_target(k: int, centre: np.ndarray, cfg: PlanConfig) -> np.ndarray:
    radius = float(np.linalg.norm(centre)) * cfg.orbit_radius_scale
    R = axis_angle_to_matrix(WORLD_UP, np.deg2rad(orbit_azimuth_deg(k, cfg, radius)))
    eye = centre + cfg.orbit_radius_scale * (R @ (np.zeros(3) - centre))
    return look_at(eye, centre, up=WORLD_UP)


def planner_config(cfg: PlanConfig) -> PlannerConfig:
    return PlannerConfig(num_candidates=cfg.num_candidates,
                         space=SearchSpace(cfg.radius_range, cfg.azimuth_range_deg, cfg.elevation_range_deg),
                         safe_radius=cfg.safe_radius, anchor_fraction=cfg.anchor_fraction,
                         smoothness=cfg.smoothness, max_resample=cfg.max_resample,
                         unknown_space=cfg.unknown_space)


def planning_state(scene: SceneStore, k: int, config: RunConfig) -> PlanningState:
    """What the planner knows before iteration k."""
    geo = scene.read_all(GEOMETRY)
    centre = scene_centre(geo["depth"], geo["confidence"], config.plan.centre_depth_quantile)
    views = [SeenView(np.eye(4), geo["K"], geo["depth"])]
    for j in range(1, k):
        lifted = scene.read_all(LIFT, j)
        views += [SeenView(c, K, d) for c, K, d in zip(lifted["c2w"], lifted["K"], lifted["depth"])]
    return PlanningState(
        current=np.eye(4) if k == 1 else scene.read(PLAN, k - 1, "trajectory")[-1],
        centre=centre, d0=float(np.linalg.norm(centre)), K=geo["K"],
        height=config.synthesis.height, width=config.synthesis.width,
        cloud_points=load_cloud(scene, k - 1).points, views=views, num_frames=config.synthesis.num_frames,
        point_size=1.5 * config.lift.voxel_size)


def plan(store_uri: str, scene_id: str, k: int, config: RunConfig, run_id: str) -> StepRef:
    cfg = config.plan

    def orbit_body(writer, seed: int, _) -> dict:
        scene = open_store(store_uri).scene(scene_id)
        geo = scene.read_all(GEOMETRY)
        centre = scene_centre(geo["depth"], geo["confidence"], cfg.centre_depth_quantile)
        current = np.eye(4) if k == 1 else scene.read(PLAN, k - 1, "trajectory")[-1]
        target = orbit_target(k, centre, cfg)
        traj = interpolate_poses(current, target, config.synthesis.num_frames, centre=centre)
        writer.write("trajectory", traj)
        writer.write("K", geo["K"])
        writer.write("centre", centre)
        writer.write("candidates", target[None])
        return {"strategy": cfg.strategy, "chosen": 0,
                "azimuth_deg": orbit_azimuth_deg(k, cfg, float(np.linalg.norm(centre)) * cfg.orbit_radius_scale)}

    def planner_body(writer, seed: int, _) -> dict:
        scene = open_store(store_uri).scene(scene_id)
        state = planning_state(scene, k, config)
        planner = PLANNERS[cfg.strategy](planner_config(cfg))
        res = planner.plan(state, np.random.default_rng(seed))
        writer.write("trajectory", res.trajectory)
        writer.write("K", state.K)
        writer.write("centre", state.centre)
        writer.write("candidates", res.candidates)
        writer.write("candidate_scores", res.scores)
        writer.write("candidate_collides", res.collides)
        writer.write("candidate_masks", res.masks)
        writer.write("initial_trajectory", res.initial_trajectory)
        cloud = load_cloud(scene, k - 1)
        writer.write_file("topdown.png", topdown_png(cloud.points, cloud.colors, state, res, cfg.strategy, k))
        attrs = {"strategy": cfg.strategy, "chosen": res.chosen, "optimised": res.optimised,
                 "fallback": res.fallback, "rounds": res.rounds, "r_safe": cfg.safe_radius,
                 "d0": state.d0, "timings": res.timings}
        if res.collision_free is not None:
            attrs["collision_free"] = res.collision_free
        return attrs

    return run_step(store_uri, scene_id, PLAN, k, config, run_id,
                    orbit_body if cfg.strategy == "orbit" else planner_body)

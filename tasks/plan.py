"""Plan: the camera trajectory of iteration k.

Strategies (``plan.strategy``):

* ``orbit`` (the foundation's simple planner): the scene centre ``o`` is the point on the input
  camera's optical axis at the median depth of the central image region; iteration k targets the
  input camera position rotated about the world up axis through ``o`` by azimuth
  ``+s, -s, +2s, -2s, ...`` (``s = plan.orbit_step_deg``, reduced so that one step moves the camera
  by at most ``plan.orbit_max_shift``), pulled towards ``o`` by
  ``plan.orbit_radius_scale``, looking at ``o``. The trajectory from the current pose (the last pose
  of the previous iteration) interpolates rotation by SLERP and position on the arc around ``o``.
  It does not look at obstacles.
* ``collision_aware`` is the paper's Algorithm 1 (candidates, collision detector, visibility score,
  collision optimisation); it is not built yet and raises ``NotImplementedError``.
"""

from __future__ import annotations

import math

import numpy as np

from navcrafter.models.cameras import axis_angle_to_matrix, interpolate_poses, look_at
from navcrafter.schemas.config import PlanConfig, RunConfig
from navcrafter.schemas.layout import GEOMETRY, PLAN
from navcrafter.tasks.common import StepRef, open_store, run_step

WORLD_UP = np.array([0.0, -1.0, 0.0])  # the input camera's "up" (OpenCV: y points down)
COLLISION_AWARE_NOT_BUILT = ("plan.strategy 'collision_aware' (the paper's Algorithm 1) is not built yet; "
                             "it is tracked as its own issue. Use plan.strategy 'orbit'.")


def scene_centre(depth: np.ndarray, confidence: np.ndarray, quantile: float) -> np.ndarray:
    """Point on the input camera's optical axis at the given depth quantile of the central region."""
    H, W = depth.shape
    win = (slice(H // 4, H - H // 4), slice(W // 4, W - W // 4))
    d = depth[win][(confidence[win] > 0) & (depth[win] > 0)]
    if d.size == 0:
        d = depth[depth > 0]
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


def plan(store_uri: str, scene_id: str, k: int, config: RunConfig, run_id: str) -> StepRef:
    cfg = config.plan
    if cfg.strategy == "collision_aware":
        raise NotImplementedError(COLLISION_AWARE_NOT_BUILT)

    def body(writer, seed: int, _) -> dict:
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

    return run_step(store_uri, scene_id, PLAN, k, config, run_id, body)

"""The foundation's simple orbit planner (``plan.strategy: orbit``): no scoring, no obstacles.

Iteration k targets the input camera position rotated about the world up axis through the scene centre ``o``
by azimuth ``+s, -s, +2s, -2s, ...`` (``s = plan.orbit_step_deg``, reduced so that one step moves the camera
by at most ``plan.orbit_max_shift``), pulled towards ``o`` by ``plan.orbit_radius_scale``, looking at ``o``.
"""

from __future__ import annotations

import math

import numpy as np

from navcrafter.models.camera.cameras import axis_angle_to_matrix, interpolate_poses, look_at
from navcrafter.models.planning.config import PlanConfig
from navcrafter.models.planning.planners import WORLD_UP


def orbit_azimuth_deg(k: int, cfg: PlanConfig, radius: float) -> float:
    """+s, -s, +2s, -2s, ... for k = 1, 2, 3, 4, ...; ``s`` is ``orbit_step_deg``, reduced so that one
    step moves the camera by at most ``orbit_max_shift`` on a circle of ``radius``."""
    step = cfg.orbit_step_deg
    if radius > 0 and cfg.orbit_max_shift < 2 * radius:
        step = min(step, float(np.rad2deg(2 * np.arcsin(cfg.orbit_max_shift / (2 * radius)))))
    return step * math.ceil(k / 2) * (1 if k % 2 else -1)


def orbit_radius(centre: np.ndarray, cfg: PlanConfig) -> float:
    return float(np.linalg.norm(centre)) * cfg.orbit_radius_scale


def orbit_target(k: int, centre: np.ndarray, cfg: PlanConfig) -> np.ndarray:
    """The c2w that iteration ``k`` of the orbit moves to."""
    R = axis_angle_to_matrix(WORLD_UP, np.deg2rad(orbit_azimuth_deg(k, cfg, orbit_radius(centre, cfg))))
    eye = centre + cfg.orbit_radius_scale * (R @ (np.zeros(3) - centre))
    return look_at(eye, centre, up=WORLD_UP)


def orbit_trajectory(k: int, current: np.ndarray, centre: np.ndarray, cfg: PlanConfig,
                     num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(trajectory [T, 4, 4] from ``current`` to iteration k's target around ``centre``, the target)."""
    target = orbit_target(k, centre, cfg)
    return interpolate_poses(current, target, num_frames, centre=centre), target

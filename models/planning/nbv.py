"""ViewCrafter's next-best view as its code does it (``plan.strategy: viewcrafter_nbv``, the benchmark's
"baseline"; read in ViewCrafter's ``utils/pvd_utils.py`` ``generate_candidate_poses`` / ``generate_traj_specified``
and ``viewcrafter.py``'s ``single_view_nbv`` mode, for facts only).

* **Candidates relative to the current pose**, 2 or 3 of them (ViewCrafter refuses other counts; so do we):
  (d_theta, d_phi) = (0, phi), (-theta, phi) and, with 3, (theta/2, phi): the current camera rotated rigidly about
  the scene centre ``o`` (ViewCrafter's world origin: the point at the reference view's centre depth) by d_phi in
  azimuth and d_theta in elevation (ViewCrafter: a positive d_theta moves the camera down), ``phi`` and ``theta``
  its grid spacings (``plan.nbv_step_deg``, ViewCrafter's documented defaults d_theta 10, d_phi 30 degrees). The
  sign of d_phi is the exploration direction, which ViewCrafter's user sets once: here it is drawn (seeded) at the
  input view and kept from then on (the side of ``o`` the camera has moved to). Angles about ``o`` scale with the
  scene by construction; the radius step d_r (``plan.nbv_radius_step``, ViewCrafter's -0.2) multiplies the
  distance to ``o`` by ``1 + d_r`` over the clip.
* **Utility**: the candidate whose point-cloud render covers the least (``argmin`` of the rendered mask sum: the
  largest hole).
* **Trajectory**: d_theta, d_phi (and the radius) interpolated linearly from 0 over the clip's frames, each pose
  the current pose rotated rigidly about ``o`` (``generate_traj_specified``); no collision check, no optimisation.
"""

from __future__ import annotations

import time

import numpy as np

from navcrafter.models.camera.cameras import axis_angle_to_matrix
from navcrafter.models.planning.config import PlanConfig
from navcrafter.models.planning.planners import (
    WORLD_UP,
    PlanningState,
    PlanResult,
    _masks_and_scores,
    occlusion_utility,
    planning_cloud,
    search_frame,
)


def nbv_offsets(theta_deg: float, phi_deg: float, count: int) -> list[tuple[float, float]]:
    """ViewCrafter's (d_theta, d_phi) candidates (degrees): 2 -> (0, phi), (-theta, phi); 3 adds (theta/2, phi)."""
    if count == 2:
        return [(0.0, phi_deg), (-theta_deg, phi_deg)]
    if count == 3:
        return [(0.0, phi_deg), (-theta_deg, phi_deg), (theta_deg / 2, phi_deg)]
    raise ValueError(f"plan.num_candidates={count}: ViewCrafter's next-best view takes 2 or 3 candidates per "
                     "iteration (set plan.num_candidates to 2 or 3, or use another plan.strategy)")


def rotate_about(c2w: np.ndarray, centre: np.ndarray, d_theta_deg: float, d_phi_deg: float,
                 radius_factor: float = 1.0) -> np.ndarray:
    """``c2w`` moved rigidly about ``centre``: by ``d_phi`` in azimuth (about world up; positive: to the input
    camera's right as seen from ``o``), ``d_theta`` in elevation (positive: down, ViewCrafter's sign), then its
    distance to ``centre`` scaled by ``radius_factor``; the orientation turns with it."""
    c = np.asarray(centre, dtype=np.float64)
    p = c2w[:3, 3] - c
    R_az = axis_angle_to_matrix(WORLD_UP, np.deg2rad(d_phi_deg))
    p1 = R_az @ p
    horiz = p1 - (p1 @ WORLD_UP) * WORLD_UP
    axis = np.cross(WORLD_UP, horiz)  # rotating p about it by +a lowers the camera (d_theta > 0: down)
    R_el = axis_angle_to_matrix(axis, np.deg2rad(d_theta_deg)) if np.linalg.norm(axis) > 1e-9 else np.eye(3)
    R = R_el @ R_az
    out = np.eye(4)
    out[:3, :3] = R @ c2w[:3, :3]
    out[:3, 3] = c + radius_factor * (R @ p)
    return out


def nbv_direction(state: PlanningState, rng: np.random.Generator, tol_deg: float = 1.0) -> float:
    """The sign of d_phi: the side of ``o`` the camera has already moved to; at the input view, drawn."""
    back, right, _ = search_frame(state.centre)
    p = state.current[:3, 3] - state.centre
    az = np.degrees(np.arctan2(p @ right, p @ back))
    draw = 1.0 if rng.random() < 0.5 else -1.0
    return draw if abs(az) < tol_deg else float(np.sign(az))


class ViewCrafterNBVPlanner:
    """ViewCrafter's next-best view from the current pose (module docstring)."""

    name = "viewcrafter_nbv"

    def __init__(self, config: PlanConfig) -> None:
        self.config = config

    def plan(self, state: PlanningState, rng: np.random.Generator) -> PlanResult:
        cfg = self.config
        t0 = time.perf_counter()
        theta, phi = cfg.nbv_step_deg
        sign = nbv_direction(state, rng)
        offsets = nbv_offsets(theta, phi, cfg.num_candidates)
        cands = np.stack([rotate_about(state.current, state.centre, dt, sign * dp, 1.0 + cfg.nbv_radius_step)
                          for dt, dp in offsets])
        none = np.zeros(len(cands), dtype=bool)
        masks, scores = _masks_and_scores(state, planning_cloud(state), cands, none, occlusion_utility)
        t_score = time.perf_counter()
        i = int(np.argmax(scores))  # argmin of the mask sum
        dt, dp = offsets[i]
        s = np.linspace(0.0, 1.0, state.num_frames)
        traj = np.stack([rotate_about(state.current, state.centre, f * dt, f * sign * dp,
                                      1.0 + f * cfg.nbv_radius_step) for f in s])
        traj[0], traj[-1] = state.current, cands[i]
        t_end = time.perf_counter()
        timings = {"detector_s": 0.0, "candidates_s": t_score - t0, "trajectory_s": t_end - t_score,
                   "total_s": t_end - t0}
        return PlanResult(traj, traj, cands, scores, none, masks, i, timings=timings)

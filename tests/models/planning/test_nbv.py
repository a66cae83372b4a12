"""ViewCrafter's next-best view from the current pose (models/planning/nbv.py)."""

from __future__ import annotations

import numpy as np
import pytest
from test_planning import room_state

from navcrafter.models.camera.cameras import look_at
from navcrafter.models.planning.nbv import ViewCrafterNBVPlanner, nbv_offsets, rotate_about
from navcrafter.models.planning.planners import WORLD_UP, search_frame
from navcrafter.models.planning.registry import PLANNERS
from navcrafter.schemas.config import PlanConfig


def _angles(p: np.ndarray, centre: np.ndarray) -> tuple[float, float, float]:
    back, right, up = search_frame(centre)
    v = p - centre
    r = float(np.linalg.norm(v))
    return float(np.degrees(np.arctan2(v @ right, v @ back))), float(np.degrees(np.arcsin(v @ up / r))), r


def test_candidates_are_viewcrafters_offsets_from_the_current_pose():
    assert nbv_offsets(10, 30, 3) == [(0.0, 30), (-10, 30), (5.0, 30)]
    assert nbv_offsets(10, 30, 2) == [(0.0, 30), (-10, 30)]
    with pytest.raises(ValueError, match="2 or 3 candidates"):
        nbv_offsets(10, 30, 5)
    centre = np.array([0.0, 0.0, 4.0])
    start = look_at(np.array([0.0, 0.0, 0.0]), centre)
    moved = rotate_about(start, centre, -10.0, 30.0, 0.8)  # up by 10 deg, right by 30 deg, 20 % closer
    az, el, r = _angles(moved[:3, 3], centre)
    assert az == pytest.approx(30.0) and el == pytest.approx(10.0) and r == pytest.approx(3.2)
    # a rigid motion about o: still looking at o, no roll against world up
    fwd = moved[:3, 2]
    np.testing.assert_allclose(fwd, (centre - moved[:3, 3]) / 3.2, atol=1e-9)
    assert abs(moved[:3, 0] @ WORLD_UP) < 1e-9


def test_planner_steps_from_the_current_pose_to_the_largest_hole():
    _, state = room_state()
    assert PLANNERS["viewcrafter_nbv"] is ViewCrafterNBVPlanner
    res = ViewCrafterNBVPlanner(PlanConfig(num_candidates=3)).plan(state, np.random.default_rng(0))
    assert len(res.candidates) == 3 and not res.collides.any() and res.collision_free is None
    np.testing.assert_allclose(res.scores, [1 - m.mean() for m in res.masks])
    assert res.chosen == int(np.argmax(res.scores))  # argmin of the rendered mask sum
    azs = [_angles(c[:3, 3], state.centre) for c in res.candidates]
    assert all(abs(abs(a) - 30.0) < 1e-6 for a, _, _ in azs) and len({np.sign(a) for a, _, _ in azs}) == 1
    assert sorted(round(e, 6) for _, e, _ in azs) == [-5.0, 0.0, 10.0]
    assert np.array_equal(res.trajectory[0], state.current)
    assert np.array_equal(res.trajectory[-1], res.candidates[res.chosen])
    r = np.linalg.norm(res.trajectory[:, :3, 3] - state.centre, axis=1)  # radius 1 -> 0.8 linearly
    np.testing.assert_allclose(r, np.linspace(r[0], 0.8 * r[0], len(r)), atol=1e-9)
    # the direction, once chosen, is kept: from the end of this clip the next step goes the same way
    state.current = res.trajectory[-1]
    nxt = ViewCrafterNBVPlanner(PlanConfig(num_candidates=3)).plan(state, np.random.default_rng(1))
    a0, a1 = _angles(res.trajectory[-1][:3, 3], state.centre)[0], _angles(nxt.trajectory[-1][:3, 3], state.centre)[0]
    assert abs(a1) == pytest.approx(abs(a0) + 30.0, abs=1e-6)

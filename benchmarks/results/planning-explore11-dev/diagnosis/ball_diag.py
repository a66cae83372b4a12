"""Why the explorer refuses paths at one plan step of a kept store (explore11): python ball_diag.py STORE_DIR K
[KEY=VALUE ...]. For the best trajectories (rebuilt as the planner builds them): the first flagged frame and why
(near an observed surface, unseen position, or the clearance ball's probes: how many unseen, in which directions)."""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
from benchmarks import planning
from navcrafter.models.planning import explore as ex
from navcrafter.models.planning.planners import _directions26, estimate_ground, planning_cloud
from navcrafter.schemas.layout import PLAN
from navcrafter.schemas.store import Store
from navcrafter.tasks.plan import planning_state

path, k = sys.argv[1], int(sys.argv[2])
variant = dict(a.split("=", 1) for a in sys.argv[3:])
config = planning.bench_config("explorer", True, None, variant or None)
cfg = config.plan
store = Store(path)
scene = store.scene(store.scene_ids()[0])
state = planning_state(scene, k, config)
print("stored fallback", scene.attrs(PLAN, k).get("fallback") if hasattr(scene, "attrs") else "?")
cands = np.asarray(scene.read(PLAN, k, "candidates"))
scores = np.asarray(scene.read(PLAN, k, "candidate_scores"))
rng = np.random.default_rng(0)
points = planning_cloud(state, cfg.safe_radius)
ground = estimate_ground(points, state.current[:3, 3], rng, tolerance=cfg.safe_radius / 4)
seen = replace(state, views=ex.open_sky(state.views))
free_views = ex.carving_views(seen.views, cfg.explore_free_space, cfg.explore_invented_share)
vmap = ex.VoxelMap.build(seen, points, cfg.explore_voxels, free_views=free_views)
det = ex.ExplorerDetector(points, cfg.safe_radius, state.views, thin=False, ground=ground,
                          follow_error=cfg.explore_follow_error, vmap=vmap, prefix=cfg.explore_prefix,
                          reach=cfg.explore_reach, visibility_views=free_views, ball=1.0)
det0 = ex.ExplorerDetector(points, cfg.safe_radius, state.views, thin=False, ground=ground,
                           follow_error=cfg.explore_follow_error, vmap=vmap, prefix=cfg.explore_prefix,
                           reach=cfg.explore_reach, visibility_views=free_views, ball=0.0)
T = state.num_frames
names = np.array(ex.SHAPES * (len(cands) // 3))
dirs = _directions26()
for i in np.argsort(-scores)[:12]:
    traj = ex.shaped_trajectory(state.current, cands[i], state.centre, T, names[i])
    n0, u0, _ = det0.path_flags(traj)
    n1, u1, _ = det.path_flags(traj)
    first = int(np.argmax(n1 | u1)) if (n1 | u1).any() else -1
    line = f"cand {i} {names[i]} score {scores[i]:.3f} ball0 {'ok' if not (n0 | u0).any() else 'refused'}"
    line += f" ball1 first flagged {first}"
    if first >= 0 and not (n0 | u0)[first]:
        x = traj[first, :3, 3]
        need = det.path_clearance(traj[:, :3, 3])[first]
        probes = (x[None, None] + np.array([0.5, 1.0])[:, None, None] * need * dirs[None]).reshape(-1, 3)
        free, occ = det._visibility(probes)
        line += f" (ball r {need:.2f}; probes not seen-free {int((~free).sum())}/52, up-ish unseen " \
                f"{int((~free.reshape(2, 26)[:, dirs[:, 1] < -0.5]).sum())})"
    print(line)

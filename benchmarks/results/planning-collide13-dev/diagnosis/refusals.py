"""Why a clearance-ball variant refuses the plan a kept CRN store chose (collide13): python refusals.py STORE_DIR
BASE_SEED KEY=VALUE ... (the variant's plan settings). Per iteration: the stored plan's frames the variant's G does
not admit, and at the first of them the ball's radius (G's clearance x explore_ball) and its probes that were neither
seen free nor looked at, by direction (up: rising more than 30 deg from the ground plane, level, down)."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from analyse import detector, setup  # noqa: E402

from navcrafter.models.planning.planners import _directions26  # noqa: E402
from navcrafter.schemas.layout import PLAN  # noqa: E402

path, base = sys.argv[1], int(sys.argv[2])
config, sid, scene = setup(path, base, dict(a.split("=", 1) for a in sys.argv[3:]))
for k in range(1, config.iterations + 1):
    plan = np.asarray(scene.read(PLAN, k, "trajectory"), dtype=np.float64)
    state, det = detector(scene, sid, config, k)
    near, unseen, _ = det.path_flags(plan)
    a = scene.status(PLAN, k).attrs
    travelled = float(np.linalg.norm(np.diff(plan[:, :3, 3], axis=0), axis=1).sum())
    print(f"clip {k} ({a.get('fallback') or 'best'}/{a.get('shape')}, path {travelled:.2f} u, d0 {state.d0:.2f} u): "
          f"near {np.flatnonzero(near).tolist()}, unadmitted {np.flatnonzero(unseen).tolist()}")
    if not unseen.any():
        continue
    t = int(np.flatnonzero(unseen)[0])
    x = plan[t, :3, 3]
    radius = det.ball * det.path_clearance(plan[:, :3, 3], det.ball_follow_error)[t]
    dirs = _directions26()
    up = det.ground[0] if det.ground is not None else -plan[0, :3, 1]
    rise = dirs @ (up / np.linalg.norm(up))
    probes = (x[None, None] + np.array([0.5, 1.0])[:, None, None] * radius * dirs[None]).reshape(-1, 3)
    free, _ = det._visibility(probes)
    pending = ~free.reshape(2, 26)
    looked = np.zeros_like(pending)
    for s in range(max(t - det.lag + 1, 0)):
        q = (probes - plan[s, :3, 3]) @ plan[s, :3, :3]
        looked |= det._in_frustum(q).reshape(2, 26)
    groups = {"up": rise > 0.5, "level": np.abs(rise) <= 0.5, "down": rise < -0.5}
    print(f"   frame {t}: ball radius {radius:.2f} u; probes not seen free (of 2 x n) / of those in no earlier "
          f"frame's view: " + ", ".join(f"{n} {int(pending[:, g].sum())}/{int((pending & ~looked)[:, g].sum())} "
                                         f"of {2 * int(g.sum())}" for n, g in groups.items()))

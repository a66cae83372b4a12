"""diag.py (explore9) on a kept store: python diag_store.py STORE_DIR KEY=VALUE..."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
from benchmarks import planning
from navcrafter.schemas.layout import PLAN, SYNTHESIZE
from navcrafter.schemas.store import Store
from navcrafter.tasks.common import simulation_truth

path = sys.argv[1]
variant = dict(a.split("=", 1) for a in sys.argv[2:])
cfg = planning.bench_config("explorer", True, None, variant or None)
store = Store(path)
scene = store.scene(store.scene_ids()[0])
truth = simulation_truth(scene)
ws = truth.world_scale
r_safe_m = cfg.plan.safe_radius / ws
print(f"r_safe {cfg.plan.safe_radius:.3f} units = {r_safe_m:.3f} m; world_scale {ws:.4f}")
for k in range(1, cfg.iterations + 1):
    plan = np.asarray(scene.read(PLAN, k, "trajectory"), dtype=np.float64)
    true = np.asarray(scene.read(SYNTHESIZE, k, "true_c2w"), dtype=np.float64)
    xp, xt = plan[:, :3, 3], true[:, :3, 3]
    L = float(np.linalg.norm(np.diff(xp, axis=0), axis=1).sum())
    moved = true[0] @ np.linalg.inv(plan[0]) @ plan
    drift = np.linalg.norm(xt - moved[:, :3, 3], axis=1)
    start_off = float(np.linalg.norm(xt[0] - xp[0]))
    cp = truth.scene.distance(truth.gt_points(xp))
    ct = truth.scene.distance(truth.gt_points(xt))
    cm = truth.scene.distance(truth.gt_points(moved[:, :3, 3]))
    a = scene.status(PLAN, k).attrs
    print(f"clip {k} ({a.get('fallback')}/{a.get('shape')}): path {L:.2f} u, start offset {start_off:.3f} u, "
          f"end drift {drift[-1]:.3f} u ({drift[-1] / max(L, 1e-9):.1%} of path), min clearance planned "
          f"{cp.min():.3f} m / moved {cm.min():.3f} m / true {ct.min():.3f} m")
    for i in np.flatnonzero(ct < r_safe_m):
        print(f"   frame {i}: planned clr {cp[i]:.3f} m, moved {cm[i]:.3f} m, true {ct[i]:.3f} m, "
              f"drift {drift[i]:.3f} u")

"""Rebuild one development scene with an explorer variant (python diag.py KIND SEED OUTDIR [KEY=VALUE ...]), keep
its store, and print per clip: planned path length, the true end drift as a fraction of it, and per colliding frame
the planned pose's true clearance against the true camera's."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))  # the repository root, for `benchmarks`
from benchmarks import planning  # noqa: E402
from navcrafter.models.simulation.demo import write_demo_collection  # noqa: E402
from navcrafter.schemas.layout import PLAN, SYNTHESIZE  # noqa: E402
from navcrafter.schemas.store import Store  # noqa: E402
from navcrafter.tasks.common import simulation_truth  # noqa: E402

kind, seed, out = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
variant = dict(a.split("=", 1) for a in sys.argv[4:])
photo = write_demo_collection(out / "photos", (kind,), 1, seed)[0]
cfg = planning.bench_config("explorer", True, None, variant or None)
row, _ = planning.run_one(photo, out / "store", cfg)
print({k: round(row[k], 3) for k in ("seen", "coverage_at_0.05", "collisions")})
store = Store(str(out / "store"))

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
    # the requested path moved rigidly onto the true start (what the simulation does before the drift)
    moved = true[0] @ np.linalg.inv(plan[0]) @ plan
    drift = np.linalg.norm(xt - moved[:, :3, 3], axis=1)
    start_off = float(np.linalg.norm(xt[0] - xp[0]))
    offset_total = np.linalg.norm(xt - xp, axis=1)
    cp = truth.scene.distance(truth.gt_points(xp))
    ct = truth.scene.distance(truth.gt_points(xt))
    cm = truth.scene.distance(truth.gt_points(moved[:, :3, 3]))
    print(f"clip {k}: path {L:.2f} u, start offset {start_off:.3f} u, end drift {drift[-1]:.3f} u "
          f"({drift[-1] / max(L, 1e-9):.1%} of path), end offset planned->true {offset_total[-1]:.3f} u, "
          f"min true clearance planned {cp.min():.3f} m / moved {cm.min():.3f} m / true {ct.min():.3f} m")
    hit = np.flatnonzero(ct < r_safe_m)
    for i in hit:
        print(f"   frame {i}: planned clr {cp[i]:.3f} m, moved-to-true-start clr {cm[i]:.3f} m, "
              f"true clr {ct[i]:.3f} m, "
              f"drift {drift[i]:.3f} u, total offset {offset_total[i]:.3f} u")

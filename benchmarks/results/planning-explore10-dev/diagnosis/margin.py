"""Per development room and clip of kept stores: the planned path's smallest true clearance over the clearance G
demands (r_safe + explore_follow_error x distance travelled). python margin.py STORE_ROOT [KEY=VALUE ...]"""
import glob
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
from benchmarks import planning
from navcrafter.schemas.layout import PLAN
from navcrafter.schemas.store import Store
from navcrafter.tasks.common import simulation_truth

root = sys.argv[1]
variant = dict(a.split("=", 1) for a in sys.argv[2:])
cfg = planning.bench_config("explorer", True, None, variant or None)
res = {}
for s in range(10):
    path = glob.glob(f"{root}/*/ours/room-{s}")[0]
    st = Store(path)
    sc = st.scene(st.scene_ids()[0])
    tr = simulation_truth(sc)
    mins = []
    for k in range(1, 4):
        p = np.asarray(sc.read(PLAN, k, "trajectory"))[:, :3, 3]
        L = np.r_[0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
        need = (cfg.plan.safe_radius + cfg.plan.explore_follow_error * L) / tr.world_scale
        c = tr.scene.distance(tr.gt_points(p))
        mins.append(round(float((c / np.maximum(need, 1e-9)).min()), 2))
    res[s] = mins
print(json.dumps(res))

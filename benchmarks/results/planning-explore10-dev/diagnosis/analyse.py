"""Per clip of a stored benchmark scene: cumulative seen after the clip, the true path length (d0 units),
frames that add seen, the median true depth, heading change; plan attrs.
Usage: analyse.py STORE_ROOT METHOD KIND-SEED [plan k=v ...]"""
import glob
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "benchmarks"))
from planning import bench_config

from navcrafter.models.metrics.cloud import seen_mask
from navcrafter.models.planning.planners import search_space
from navcrafter.models.simulation.reference import reference_points
from navcrafter.models.simulation.render import render_many
from navcrafter.schemas.layout import PLAN
from navcrafter.schemas.store import Store
from navcrafter.tasks.common import simulation_truth
from navcrafter.tasks.readers import stored_scene_centre, true_cameras
from navcrafter.tasks.scene_metrics import SEEN_SAMPLE, SEEN_SIDE

root, method, ks = sys.argv[1], sys.argv[2], sys.argv[3]
plan = dict(a.split("=", 1) for a in sys.argv[4:])
strategy = {"ours": "explorer", "baseline": "viewcrafter_nbv", "baseline_global": "viewcrafter"}[method]
cfg = bench_config(strategy, True, None, plan or None)
path = glob.glob(f"{root}/*/{method}/{ks}")[0]
st = Store(path)
sid = [p.split("/")[-2] for p in glob.glob(path + "/scenes/*/")][0]
scene = st.scene(sid)
truth = simulation_truth(scene)
centre = stored_scene_centre(scene, cfg)
d0 = float(np.linalg.norm(centre))
ref = reference_points(truth, centre, d0, search_space(cfg.plan), cfg.plan.safe_radius / truth.world_scale)
K = truth.intrinsics_for(cfg.synthesis.height, cfg.synthesis.width)
s = min(1.0, SEEN_SIDE / max(K.width, K.height))
Ks = K.resize(max(1, round(K.width * s)), max(1, round(K.height * s))) if s < 1.0 else K
sample = np.arange(0, len(ref), max(1, -(-len(ref) // SEEN_SAMPLE)))
R = ref[sample]
depth0 = list(render_many(truth.scene, truth.photo_c2w[None], Ks, colour=False).depth)
seen = seen_mask(R, truth.photo_c2w[None], Ks.K, depth0)
out = {"seen0": float(seen.mean()), "clips": []}
for k in range(1, cfg.iterations + 1):
    tc = truth.gt_pose(true_cameras(scene, k))
    depths = list(render_many(truth.scene, tc, Ks, colour=False).depth)
    adds = []
    for c, d in zip(tc, depths):
        m = seen_mask(R, c[None], Ks.K, [d])
        adds.append(int((m & ~seen).sum()))
        seen |= m
    pos = tc[:, :3, 3]
    L = float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()) / (d0 / truth.world_scale)
    fw = tc[:, :3, 2]
    head = np.degrees(np.arccos(np.clip((fw[0] * fw[-1]).sum(), -1, 1)))
    med = [float(np.median(d[d > 0])) if (d > 0).any() else 0 for d in depths]
    attrs = scene.status(PLAN, k).attrs
    out["clips"].append({"k": k, "seen": round(float(seen.mean()), 4), "gain": round(sum(adds) / len(R), 4),
                         "frames_adding>0.2%": int(sum(a > 0.002 * len(R) for a in adds)),
                         "path_d0": round(L, 3), "turn_deg": round(float(head), 1),
                         "median_depth_first_last": [round(med[0], 2), round(med[-1], 2)],
                         "fallback": attrs.get("fallback"), "shape": attrs.get("shape"),
                         "end_xyz_d0": np.round((pos[-1] - truth.photo_c2w[:3, 3]) / (d0 / truth.world_scale),
                                                 2).tolist()})
print(json.dumps(out))

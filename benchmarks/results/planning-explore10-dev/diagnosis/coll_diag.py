"""The surface nearest a planned pose of a kept store: python coll_diag.py STORE_DIR CLIP FRAME (explore_accuracy 0.03's
config): was it seen by earlier true frames, is the planning cloud near it."""
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
from benchmarks import planning
from navcrafter.models.metrics.cloud import seen_mask
from navcrafter.models.simulation.render import render_many
from navcrafter.schemas.layout import PLAN
from navcrafter.schemas.store import Store
from navcrafter.tasks.common import load_cloud, simulation_truth
from navcrafter.tasks.readers import true_cameras

path, k, frame = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
cfg = planning.bench_config("explorer", True, None, {"explore_accuracy": "0.03"})
store = Store(path)
scene = store.scene(store.scene_ids()[0])
truth = simulation_truth(scene)
plan = np.asarray(scene.read(PLAN, k, "trajectory"), dtype=np.float64)
xp = truth.gt_points(plan[frame, :3, 3])[None]
rc, _ = truth.scene.raycasting()
ans = rc.compute_closest_points(o3d.core.Tensor(xp.astype(np.float32)))
P = ans["points"].numpy()[0]
gid = int(ans["geometry_ids"].numpy()[0])
names = [o.name for o in truth.scene.objects] if hasattr(truth.scene.objects[0], "name") else None
name = names[gid] if names and gid < len(names) else ""
print("planned end (gt m)", np.round(xp[0], 2), "closest true surface", np.round(P, 2),
      "dist", round(float(np.linalg.norm(P - xp[0])), 3), "geometry id", gid, name)
# lifted cloud available to the plan of clip k (after iteration k-1)
cl = truth.gt_points(load_cloud(scene, k - 1).points)
d, _ = cKDTree(cl).query(P)
print("nearest point of the planning cloud to that surface point:", round(float(d), 3), "m; cloud size", len(cl))
# within a 0.3 m ball around P: true surface points seen by earlier true frames?
cams = [truth.photo_c2w[None]] + [truth.gt_pose(true_cameras(scene, j)) for j in range(1, k)]
cams = np.concatenate(cams)
K = truth.intrinsics_for(128, 128)
depths = list(render_many(truth.scene, cams, K, colour=False).depth)
# sample the true surface near P by casting: use the closest-point of a grid around P
g = P + (np.stack(np.meshgrid(*[np.linspace(-0.3, 0.3, 13)] * 3, indexing="ij"), -1).reshape(-1, 3))
cp = rc.compute_closest_points(o3d.core.Tensor(g.astype(np.float32)))["points"].numpy()
cp = cp[np.linalg.norm(cp - P, axis=1) < 0.3]
cp = np.unique(np.round(cp, 3), axis=0)
s = seen_mask(cp, cams, K.K, depths)
print("true surface within 0.3 m of it:", len(cp), "points, seen by earlier true frames:", round(float(s.mean()), 3))
dd, _ = cKDTree(cl).query(cp)
print("  of those, share with a cloud point within 0.1 m:", round(float((dd < 0.1).mean()), 3),
      "within 0.3 m:", round(float((dd < 0.3).mean()), 3))

"""Which earlier views made planned frames of a kept CRN store 'seen free' (collide13): python which_view.py
STORE_DIR BASE_SEED K FRAME[,FRAME...]. Per frame and view: the pixel, the view's (lifted) depth there, the frame's
range along it, and where the true ray from that (estimated) camera through the pixel meets the true scene."""
import sys
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from analyse import detector, setup  # noqa: E402

from navcrafter.models.planning.planners import project  # noqa: E402
from navcrafter.schemas.layout import PLAN  # noqa: E402
from navcrafter.tasks.common import simulation_truth  # noqa: E402

path, base, k = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
frames = [int(f) for f in sys.argv[4].split(",")]
config, sid, scene = setup(path, base, {})
truth = simulation_truth(scene)
rc, _ = truth.scene.raycasting()
names = [o.name for o in truth.scene.objects]
_, det = detector(scene, sid, config, k)
x = np.asarray(scene.read(PLAN, k, "trajectory"), dtype=np.float64)[frames, :3, 3]
for j, v in enumerate(det.views):
    uv, z = project(x, v.c2w, v.K)
    H, W = v.depth.shape
    for f, p, zz in zip(frames, uv, z):
        u, w = int(np.floor(p[0])), int(np.floor(p[1]))
        if not (zz > 0 and 0 <= u < W and 0 <= w < H):
            continue
        d = float(v.depth[w, u])
        if d > 0 and zz < d and (v.anchored is None or v.anchored[w, u]):
            ray = v.c2w[:3, :3] @ (np.linalg.inv(v.K) @ np.array([u + 0.5, w + 0.5, 1.0]))
            og, pg = truth.gt_points(np.stack([v.c2w[:3, 3], v.c2w[:3, 3] + ray * d]))
            scale = np.linalg.norm(pg - og) / d
            hit = rc.cast_rays(o3d.core.Tensor(np.r_[og, (pg - og) / np.linalg.norm(pg - og)][None]
                                               .astype(np.float32)))
            print(f"frame {f}: seen free by view {j} ({'observed' if v.anchored is None else 'generated'}), pixel "
                  f"({u}, {w}), its depth {d:.2f} u, the frame's range {zz:.2f} u; the true ray meets "
                  f"'{names[int(hit['geometry_ids'].numpy()[0])]}' at {float(hit['t_hit'].numpy()[0]) / scale:.2f} u")

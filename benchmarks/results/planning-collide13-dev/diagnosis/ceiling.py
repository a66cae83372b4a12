"""How much of room 2's ceiling the planning cloud held before each clip, and how far below it clip 3 was
planned (collide13): python ceiling.py (the store of rebuild.py room 2 1 /tmp/collide13/room-2)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np
from analyse import setup

from navcrafter.schemas.layout import PLAN
from navcrafter.tasks.common import load_cloud, simulation_truth

config, sid, scene = setup("/tmp/collide13/room-2/store", 1, {})
truth = simulation_truth(scene)
obj = [o for o in truth.scene.objects if o.name == "ceiling"][0]
zc = np.asarray(obj.mesh.vertices)[:, 2].min()
for k in (1, 2, 3):
    cl = truth.gt_points(load_cloud(scene, k - 1).points)
    print(f"cloud before clip {k}: {len(cl)} pts, max z {cl[:, 2].max():.2f} m, ceiling z {zc:.2f} m, "
          f"pts within 0.1 m of the ceiling plane {(np.abs(cl[:, 2] - zc) < 0.1).sum()}")
p = truth.gt_points(np.asarray(scene.read(PLAN, 3, "trajectory"))[:, :3, 3])
print("clip 3 planned height below the ceiling, frames 0, 4, 12, 20, 24:", np.round(zc - p[[0, 4, 12, 20, 24], 2], 2))

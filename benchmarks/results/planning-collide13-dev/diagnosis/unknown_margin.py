"""What a clearance test against unknown space would refuse (collide13, not a rule in the planner): python
unknown_margin.py STORE_DIR BASE_SEED. Per clip of a kept CRN store: each planned frame's distance to the nearest
unknown cell of the explorer's voxel map (cell centres; a cell is ~3 d0 / explore_voxels wide) over the clearance G
demands there (r_safe + the follow error x distance travelled); the frames below 1."""
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import distance_transform_edt

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from analyse import detector, setup  # noqa: E402

from navcrafter.models.planning.voxel_kernels import UNKNOWN  # noqa: E402
from navcrafter.schemas.layout import PLAN  # noqa: E402

config, sid, scene = setup(sys.argv[1], int(sys.argv[2]), {})
for k in range(1, config.iterations + 1):
    plan = np.asarray(scene.read(PLAN, k, "trajectory"), dtype=np.float64)
    _, det = detector(scene, sid, config, k)
    vm = det.vmap
    grid = vm.state.reshape(vm.size, vm.size, vm.size)
    to_unknown = distance_transform_edt(grid != UNKNOWN).reshape(-1) * vm.voxel
    x = plan[:, :3, 3]
    idx = vm.index(x)
    d = np.where(idx >= 0, to_unknown[np.maximum(idx, 0)], np.inf)
    ratio = d / det.path_clearance(x)
    print(f"clip {k}: cell {vm.voxel:.2f} u; distance to unknown / demanded clearance, min {ratio.min():.2f}; "
          f"frames below 1: {np.flatnonzero(ratio < 1).tolist()}")

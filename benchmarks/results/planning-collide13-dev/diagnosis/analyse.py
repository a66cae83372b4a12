"""Why a kept CRN store's true camera collides (collide13): python analyse.py STORE_DIR BASE_SEED [KEY=VALUE ...]
(KEY=VALUE: the plan settings the store was made with, or others, e.g. explore_ball=0.5, to see whether their G would
have refused the stored plan).
Per clip: shape / fallback, planned path length, end drift (share of the path), the planned path's smallest true
clearance over the clearance G demands (r_safe + follow error x distance travelled: the margin), and per colliding
true frame: its true clearance, the nearest true surface (object name, offset from the camera in the ground-truth
frame, z up), the drift there against G's follow-error allowance, how G admitted the planned pose (seen free /
start neighbourhood / rule 3: looked at by an earlier frame of the clip), and whether earlier true frames saw that
surface (share of true surface within 0.3 m of it seen; nearest planning-cloud point). The detector is rebuilt as
the explorer built it (CRN: the plan step's seed from the base seed, scene, step and iteration)."""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
from benchmarks import planning  # noqa: E402
from navcrafter.models.metrics.cloud import seen_mask  # noqa: E402
from navcrafter.models.planning import explore as ex  # noqa: E402
from navcrafter.models.planning.planners import estimate_ground, planning_cloud  # noqa: E402
from navcrafter.models.simulation.render import render_many  # noqa: E402
from navcrafter.schemas.layout import PLAN, SYNTHESIZE  # noqa: E402
from navcrafter.schemas.store import Store  # noqa: E402
from navcrafter.tasks.common import load_cloud, simulation_truth  # noqa: E402
from navcrafter.tasks.plan import planning_state  # noqa: E402
from navcrafter.tasks.readers import true_cameras  # noqa: E402
from navcrafter.tasks.steps import step_seed  # noqa: E402


def setup(path: str, base: int, variant: dict):
    """The store's scene, its truth and the run's config (the CRN bench config with ``variant``)."""
    config = planning.bench_config("explorer", True, None, variant or None, crn=True, base_seed=base)
    store = Store(path)
    sid = store.scene_ids()[0]
    return config, sid, store.scene(sid)


def detector(scene, sid: str, config, k: int):
    """G as the explorer built it at iteration ``k`` (CRN: the plan step's seed from base seed, scene, step, k)."""
    cfg = config.plan
    state = planning_state(scene, k, config)
    rng = np.random.default_rng(step_seed(sid, PLAN, k, config, ""))
    points = planning_cloud(state, cfg.safe_radius)
    ground = estimate_ground(points, state.current[:3, 3], rng, tolerance=cfg.safe_radius / 4)
    seen = replace(state, views=ex.open_sky(state.views)) if cfg.explore_sky == "free" else state
    free_views = ex.carving_views(seen.views, cfg.explore_free_space, cfg.explore_invented_share)
    vmap = ex.VoxelMap.build(seen, points, cfg.explore_voxels, free_views=free_views)
    e = cfg.follow_error if cfg.explore_follow_error is None else cfg.explore_follow_error
    return state, ex.ExplorerDetector(points, cfg.safe_radius, state.views, thin=False, ground=ground,
                                      follow_error=e, vmap=vmap, prefix=cfg.explore_prefix, reach=cfg.explore_reach,
                                      visibility_views=free_views, ball=cfg.explore_ball,
                                      ball_follow_error=cfg.explore_ball_follow_error, ball_up=cfg.explore_ball_up)


def main() -> None:
    path, base = sys.argv[1], int(sys.argv[2])
    config, sid, scene = setup(path, base, dict(a.split("=", 1) for a in sys.argv[3:]))
    cfg = config.plan
    e = cfg.follow_error if cfg.explore_follow_error is None else cfg.explore_follow_error
    truth = simulation_truth(scene)
    ws = truth.world_scale
    r_m = cfg.safe_radius / ws
    rc, _ = truth.scene.raycasting()
    names = [o.name for o in truth.scene.objects]
    Kt = truth.intrinsics_for(128, 128)
    print(f"r_safe {cfg.safe_radius:.3f} u = {r_m:.3f} m; follow error {e}; world_scale {ws:.4f}")
    for k in range(1, config.iterations + 1):
        plan = np.asarray(scene.read(PLAN, k, "trajectory"), dtype=np.float64)
        true = np.asarray(scene.read(SYNTHESIZE, k, "true_c2w"), dtype=np.float64)
        xp, xt = plan[:, :3, 3], true[:, :3, 3]
        travelled = np.r_[0, np.cumsum(np.linalg.norm(np.diff(xp, axis=0), axis=1))]
        L = float(travelled[-1])
        moved = true[0] @ np.linalg.inv(plan[0]) @ plan
        drift = np.linalg.norm(xt - moved[:, :3, 3], axis=1)
        need_m = (cfg.safe_radius + e * travelled) / ws
        cp = truth.scene.distance(truth.gt_points(xp))
        ct = truth.scene.distance(truth.gt_points(xt))
        a = scene.status(PLAN, k).attrs
        print(f"clip {k} ({a.get('fallback') or 'best'}/{a.get('shape')}): path {L:.2f} u, end drift {drift[-1]:.3f} u "
              f"({drift[-1] / max(L, 1e-9):.1%} of path; G allows {e:.0%}), margin (planned true clearance / demanded) "
              f"{(cp / need_m).min():.2f}, min true clearance planned {cp.min():.3f} m / true {ct.min():.3f} m")
        hit = np.flatnonzero(ct < r_m)
        if len(hit) == 0:
            continue
        _, det = detector(scene, sid, config, k)
        near, unseen, _ = det.path_flags(plan)
        free, _ = det._visibility(xp)
        start_nb = np.linalg.norm(xp - xp[0], axis=1) < det.start_radius()
        cams = np.concatenate([truth.photo_c2w[None]] + [truth.gt_pose(true_cameras(scene, j)) for j in range(1, k)]
                              + [truth.gt_pose(true[:i]) for i in [int(hit[0])] if i > 0])
        depths = list(render_many(truth.scene, cams, Kt, colour=False).depth)
        cloud = truth.gt_points(load_cloud(scene, k - 1).points)
        tree = cKDTree(cloud)
        print(f"   G of these settings on the stored plan: near flags {np.flatnonzero(near).tolist()}, unadmitted "
              f"{np.flatnonzero(unseen).tolist()} (the default planned it: [] [] under the default's settings)")
        for i in hit:
            x_gt = truth.gt_points(xt[i][None])
            ans = rc.compute_closest_points(o3d.core.Tensor(x_gt.astype(np.float32)))
            P = ans["points"].numpy()[0]
            gid = int(ans["geometry_ids"].numpy()[0])
            how = "seen free" if free[i] else ("start neighbourhood" if start_nb[i] else "rule 3 (looked at)")
            g = P + np.stack(np.meshgrid(*[np.linspace(-0.3, 0.3, 13)] * 3, indexing="ij"), -1).reshape(-1, 3)
            sp = rc.compute_closest_points(o3d.core.Tensor(g.astype(np.float32)))["points"].numpy()
            sp = np.unique(np.round(sp[np.linalg.norm(sp - P, axis=1) < 0.3], 3), axis=0)
            s = seen_mask(sp, cams, Kt.K, depths)
            dcl, _ = tree.query(P)
            print(f"   frame {i}: true clr {ct[i]:.3f} m (planned {cp[i]:.3f} m, demanded {need_m[i]:.3f} m); "
                  f"drift {drift[i]:.3f} u = {drift[i] / max(travelled[i], 1e-9):.1%} of distance travelled "
                  f"{travelled[i]:.2f} u; nearest surface '{names[gid]}' offset {np.round(P - x_gt[0], 2)} m; "
                  f"planned pose admitted: {how}; surface seen by earlier true frames {s.mean():.2f} "
                  f"({len(sp)} pts), nearest cloud point {dcl:.2f} m")


if __name__ == "__main__":
    main()

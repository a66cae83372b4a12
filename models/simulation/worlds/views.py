"""Start cameras in a world: in free space, at least ``r_safe`` from every surface, at eye height above the
floor, looking at a well-scanned region.

Candidates: positions on a horizontal grid at ``eye_height`` (spacing ``extent / grid``), kept where the
conservative occupancy calls them free (``scene.ScanRaycaster``) and the clearance is >= ``START_CLEARANCE`` x
``r_safe`` (>= ``r_safe`` in a scan too narrow for that); at each,
``yaws`` headings with a small downward pitch. Each candidate is rendered (depth only, 48 x 64) and scored by
its valid-pixel fraction (rays that hit the scan) plus half its depth variety (standard deviation of log depth,
capped at 1) plus half its reach (median depth over ``REACH_M``, capped at 1: a view across the room, not at
the wall in front of it, the close frames the exploration metrics penalise). Candidates seeing less than
``min_valid`` valid pixels are dropped; the best are taken greedily, each at least ``min_separation_m`` or 60
degrees of heading from those already taken.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics, look_at
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.worlds import WorldError
from navcrafter.models.simulation.worlds.scene import ScanScene

EYE_HEIGHT_M = 1.5  # standing eye height (the generated rooms use 1.4-1.65 m)
PITCH_DEG = -10.0
REACH_M = 2.5  # a view whose median depth reaches this looks across the room (not at a wall in front of it)
# start positions keep this many r_safe from every surface where the scan has room (else r_safe): the collision
# metric converts r_safe to metres through the geometry's estimated scale, so a start at exactly r_safe counts every
# frame of a camera standing still as a collision whenever that scale comes out below 1 (collide15: a test room's
# start 0.2501 m from a wall, scale 0.93, 18 of 18 frames); 2 absorbs scale errors up to 50 %
START_CLEARANCE = 2.0


def score_view(scene: ScanScene, c2w: np.ndarray, fov_x_deg: float) -> tuple[float, float]:
    """(valid-pixel fraction, score) of a candidate camera."""
    K = Intrinsics.from_fov(fov_x_deg, 64, 48)
    r = render(scene, c2w, K, colour=False)
    valid = float(r.hit.mean())
    if r.hit.sum() <= 10:
        return valid, valid
    variety = float(min(1.0, np.std(np.log(r.depth[r.hit]))))
    reach = float(min(1.0, np.median(r.depth[r.hit]) / REACH_M))
    return valid, valid + 0.5 * variety + 0.5 * reach


def start_views(scene: ScanScene, n: int, r_safe_m: float, fov_x_deg: float = 65.0, *, grid: int = 14,
                yaws: int = 8, eye_height_m: float = EYE_HEIGHT_M, min_valid: float = 0.8,
                min_separation_m: float = 1.0, source: str = "") -> list[np.ndarray]:
    """``n`` OpenCV camera-to-world poses (ground-truth frame) of start views (see the module docstring)."""
    lo, hi = scene.world.bounds()
    z = eye_height_m if scene.world.floor else (lo[2] + hi[2]) / 2
    z = float(min(z, hi[2] - r_safe_m)) if hi[2] - lo[2] > 2 * r_safe_m else float((lo[2] + hi[2]) / 2)
    step = max(float(max(hi[0] - lo[0], hi[1] - lo[1])) / grid, r_safe_m / 2)
    xs, ys = np.arange(lo[0] + step / 2, hi[0], step), np.arange(lo[1] + step / 2, hi[1], step)
    P = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    P = np.concatenate([P, np.full((len(P), 1), z)], axis=1)
    where = source or scene.world.name
    if len(P) == 0:
        raise WorldError(f"{where}: the scan has no horizontal extent to place a camera in")
    clear, occupied = scene.distance(P), scene.occupied(P)
    free = (clear >= START_CLEARANCE * r_safe_m) & ~occupied
    if not free.any():  # a narrow scan: r_safe itself
        free = (clear >= r_safe_m) & ~occupied
    if not free.any():
        raise WorldError(f"{where}: no free space to start in: no point at {z:.2f} m height is >= r_safe "
                         f"({r_safe_m} m) from every surface and inside the scanned space (enclosed by scanned "
                         f"surfaces); check --scale and --up, or give start cameras with --start")
    pitch = np.deg2rad(PITCH_DEG)
    cands = []
    for p in P[free]:
        for a in np.arange(yaws) * 2 * np.pi / yaws:
            d = np.array([np.cos(a) * np.cos(pitch), np.sin(a) * np.cos(pitch), np.sin(pitch)])
            c2w = look_at(p, p + d, up=np.array([0.0, 0.0, 1.0]))
            valid, score = score_view(scene, c2w, fov_x_deg)
            if valid >= min_valid:
                cands.append((score, a, p, c2w))
    if not cands:
        raise WorldError(f"{where}: no free camera position sees at least {min_valid:.0%} scanned surface; the scan "
                         f"may be too incomplete, or give start cameras with --start")
    cands.sort(key=lambda c: -c[0])
    chosen: list[tuple[float, float, np.ndarray, np.ndarray]] = []
    for c in cands:
        if all(np.linalg.norm(c[2] - q[2]) >= min_separation_m or abs(np.angle(np.exp(1j * (c[1] - q[1]))))
               >= np.deg2rad(60) for q in chosen):
            chosen.append(c)
        if len(chosen) == n:
            break
    if len(chosen) < n:
        raise WorldError(f"{where}: only {len(chosen)} distinct start views found in the free space, {n} asked; "
                         f"ask for fewer with --views")
    return [c[3] for c in chosen]


def check_start(scene: ScanScene, c2w: np.ndarray, r_safe_m: float, where: str) -> None:
    """A given start camera must stand in free space, >= r_safe from every surface."""
    p = np.asarray(c2w, dtype=np.float64)[:3, 3][None]
    clear = float(scene.distance(p)[0])
    if clear < r_safe_m or scene.occupied(p)[0]:
        raise WorldError(f"{where}: the start camera at {np.round(p[0], 3).tolist()} (world frame) is "
                         f"{clear:.2f} m from a surface (r_safe {r_safe_m} m) or outside the scanned free space; "
                         f"give cameras in the scan's own coordinates and units (before --scale)")

"""Hallucinated variants of a world: what a video model draws where it has nothing to copy, on a scan.

The generated scenes' variant (``backend.procedural_variant``) moves the objects (grouped where they touch)
horizontally by up to ``variant_shift_m``, moves the structure (``backend._structure_moves``: a room's walls so
each horizontal extent changes by ``extent_change``, its ceiling by ``extent_change`` x the height; a street's
facades along their normal by ``structure_shift_m``; floors and ground stay) and re-draws every material (colours
within 0.2). A scan has no object list, so ``segments.segment`` splits it into surface patches:

* **structure** (anchored to the scan, but not to the clip): the triangles on large bounding planes (RANSAC
  planes with >= 95 % of the scan on one side: floor, walls, ceiling), and any connected patch more than
  ``MAX_OBJECT_M`` across (built-ins, a fused shell);
* **objects** (movable): the connected components of the rest (vertices welded at 0.1 mm), i.e. furniture
  once the floor and walls under and behind it are taken away; touching parts stay one patch, as the generated
  scenes group touching objects.

``variant_world`` then, with the generated scenes' settings:

* moves each object patch horizontally by a shift drawn exactly as for generated scenes (uniform direction,
  radius ``shift_m * sqrt(U)``);
* moves the planar structure patches (``structure_moves``) with the generated *rooms'* semantics wherever the
  scan is a room (it has a ceiling patch): the walls (structure planes whose normal is within ``WALL_MAX_NZ`` of
  horizontal) are grouped into horizontal axes (normals within ``AXIS_TOLERANCE_DEG`` of each other up to sign);
  along each axis the room's extent (the scan's span along it) changes by a signed fraction drawn from
  ``extent_change``, split at random between the walls on its two sides, each wall moving along its own normal;
  the ceiling (horizontal structure planes above mid-height) moves up or down by ``extent_change`` x the
  floor-to-ceiling height. Room semantics rather than an independent ``structure_shift_m`` draw per wall
  because that is what a generated room does (its walls keep facing each other: the room gets wider or
  narrower, it does not shear), and the extent follows the scan's own size. A scan without a ceiling patch
  (outdoors, or a room scanned without its ceiling) has no height to change; its walls are treated like the
  generated streets' facades: each moves along its normal by a signed draw from ``structure_shift_m``, whose
  source (single-image layout error, walls 0.3-1 m off) describes room walls too;
* keeps the floor (the lowest horizontal structure plane, which carries the camera), sloped or non-planar
  structure (a fused shell, a ramp) in place;
* re-textures every patch (structure included): its captured colour offset by a per-patch colour within 0.2 per
  channel, the generated scenes' re-draw range.

What a moved patch uncovers (where an object stood, the gap beside a wall that moved out, the strip above a
wall under a raised ceiling) was never scanned: it renders as no data. The structure draws come from their own
random stream, so with zero ``structure_shift_m`` / ``extent_change`` the variant is exactly the object-only one.
Door openings (``opening_probability`` on generated rooms) are not cut into scans: what lies behind a scanned wall
is unknown, so an opening would only be another hole.
"""

from __future__ import annotations

import functools

import numpy as np

from navcrafter.models.simulation.worlds.scene import ScanScene
from navcrafter.models.simulation.worlds.world import World

COLOUR_JITTER = 0.2  # backend.procedural_variant's colour re-draw range
WALL_MAX_NZ = 0.3  # a structure plane whose unit normal has |z| below this is a wall (within ~17 deg of vertical)
LEVEL_MIN_NZ = 0.9  # ... and above this a floor or ceiling (within ~26 deg of level)
PLANAR = 0.9  # share of a patch's normal scatter along its main normal for it to count as one plane
AXIS_TOLERANCE_DEG = 15.0  # walls whose normals agree this well (up to sign) share one horizontal axis


def _signed(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    """A draw from ``lo_hi`` with a random sign (``backend._signed``)."""
    return float(rng.uniform(*lo_hi) * (1 if rng.random() < 0.5 else -1))


def _planes_of(corners: np.ndarray, label: np.ndarray,
               patches: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray, float]]:
    """``(patch, unit normal, area-weighted centroid, area)`` of each planar patch among ``patches``."""
    C = corners.astype(np.float64)
    fn = np.cross(C[:, 1] - C[:, 0], C[:, 2] - C[:, 0])
    area = np.linalg.norm(fn, axis=1)
    fn = fn / np.maximum(area, 1e-12)[:, None]
    out = []
    for p in patches:
        sel = label == p
        a = area[sel]
        if a.sum() <= 0:
            continue
        scatter = (fn[sel] * a[:, None]).T @ fn[sel]  # sign-free: windings may disagree
        evals, evecs = np.linalg.eigh(scatter)
        if evals[-1] < PLANAR * evals.sum():
            continue
        centroid = (C[sel].mean(1) * a[:, None]).sum(0) / a.sum()
        out.append((int(p), evecs[:, -1], centroid, float(a.sum())))
    return out


def structure_moves(world: World, label: np.ndarray, movable: np.ndarray, rng: np.random.Generator,
                    structure_shift_m: tuple[float, float], extent_change: tuple[float, float]) -> np.ndarray:
    """Translation ``[P, 3]`` of each patch's structure move (zero for objects, the floor and non-planar or sloped
    structure): see the module docstring."""
    moves = np.zeros((len(movable), 3))
    planes = _planes_of(world.corners, label, np.flatnonzero(~movable))
    area = {p: a for p, _, _, a in planes}
    walls = sorted(((p, n, c) for p, n, c, a in planes if abs(n[2]) < WALL_MAX_NZ), key=lambda w: -area[w[0]])
    lo, hi = world.bounds()
    level = [(p, c) for p, n, c, _ in planes if abs(n[2]) > LEVEL_MIN_NZ]
    ceilings = [(p, c) for p, c in level if c[2] > (lo[2] + hi[2]) / 2]
    floor_z = min((c[2] for _, c in level if c[2] <= (lo[2] + hi[2]) / 2), default=lo[2])
    pts = world.corners.reshape(-1, 3).astype(np.float64)
    if ceilings and extent_change[1] > 0:  # a room: extents change
        axes: list[tuple[np.ndarray, list[tuple[int, np.ndarray, np.ndarray]]]] = []
        for p, n, c in walls:  # largest first
            h = np.array([n[0], n[1], 0.0]) / max(float(np.hypot(n[0], n[1])), 1e-12)
            for axis, members in axes:
                if abs(float(h @ axis)) >= np.cos(np.deg2rad(AXIS_TOLERANCE_DEG)):
                    members.append((p, h if h @ axis > 0 else -h, c))
                    break
            else:
                axes.append((h, [(p, h, c)]))
        for axis, members in axes:
            s = pts @ axis
            mid = (s.min() + s.max()) / 2
            change = _signed(rng, extent_change) * float(s.max() - s.min())
            a = float(rng.random())
            for p, h, c in members:  # h: the wall's normal, oriented along the axis
                moves[p] = h * (a * change if c @ axis > mid else -(1 - a) * change)
        dz = _signed(rng, extent_change) * float(np.mean([c[2] for _, c in ceilings]) - floor_z)
        for p, _ in ceilings:
            moves[p] = (0.0, 0.0, dz)
    elif not ceilings and structure_shift_m[1] > 0:  # facades: each wall along its normal
        for p, n, _ in walls:
            h = np.array([n[0], n[1], 0.0]) / max(float(np.hypot(n[0], n[1])), 1e-12)
            moves[p] = h * _signed(rng, structure_shift_m)
    return moves


@functools.lru_cache(maxsize=6)
def variant_world(scene: ScanScene, variant: int, shift_m: float, *, structure_shift_m: tuple[float, float],
                  extent_change: tuple[float, float]) -> ScanScene:
    """A plausible but different version of a world (see the module docstring); seeded by ``variant``.
    ``shift_m``, ``structure_shift_m`` and ``extent_change``: the simulation settings of the same names
    (``SimulationConfig.variant_shift_m`` ...), as for generated scenes."""
    label, movable = scene.patches()
    rng = np.random.default_rng([int(variant), 17, 34])
    P = len(movable)
    ang, rad = rng.uniform(0, 2 * np.pi, P), shift_m * np.sqrt(rng.random(P))
    shift = np.stack([np.cos(ang) * rad, np.sin(ang) * rad, np.zeros(P)], axis=1) * movable[:, None]
    offsets = rng.uniform(-COLOUR_JITTER, COLOUR_JITTER, (P, 3))
    w = scene.world
    shift = shift + structure_moves(w, label, movable, np.random.default_rng([int(variant), 17, 35]),
                                    tuple(structure_shift_m), tuple(extent_change))
    corners = w.corners + shift[label][:, None, :].astype(np.float32)
    moved = World(w.name, corners, w.colour, w.corner_rgb, w.uvs, w.texture_id, w.textures, w.floor, w.info)
    return ScanScene(moved, offsets=offsets[label], source=f"{scene.source}#variant{variant}")

"""Hallucinated variants of a world: what a video model draws where it has nothing to copy, on a scan.

The generated scenes' variant (``backend.variant_scene``) keeps walls, floors and buildings, moves the other
objects (grouped where they touch) horizontally by up to ``shift_m`` and re-draws every material (colours within
0.2). A scan has no object list, so ``segments.segment`` splits it into surface patches:

* **structure** (anchored): the triangles on large bounding planes (RANSAC planes with >= 95 % of the scan on one
  side: floor, walls, ceiling), and any connected patch more than ``MAX_OBJECT_M`` across (built-ins, a fused
  shell);
* **objects** (movable): the connected components of the rest (vertices welded at 0.1 mm), i.e. furniture
  once the floor and walls under and behind it are taken away; touching parts stay one patch, as the generated
  scenes group touching objects.

``variant_world`` then moves each object patch horizontally by a shift drawn exactly as for generated scenes
(uniform direction, radius ``shift_m * sqrt(U)``) and re-textures every patch (structure included): its
captured colour offset by a per-patch colour within 0.2 per channel, the generated scenes' re-draw range. The
moved patch leaves a hole where it stood (the scan never saw behind it): that renders as no data.
"""

from __future__ import annotations

import functools

import numpy as np

from navcrafter.models.simulation.worlds.scene import ScanScene
from navcrafter.models.simulation.worlds.world import World

COLOUR_JITTER = 0.2  # backend.variant_scene's colour re-draw range


@functools.lru_cache(maxsize=6)
def variant_world(scene: ScanScene, variant: int, shift_m: float) -> ScanScene:
    """A plausible but different version of a world (see the module docstring); seeded by ``variant``."""
    label, movable = scene.patches()
    rng = np.random.default_rng([int(variant), 17, 34])
    P = len(movable)
    ang, rad = rng.uniform(0, 2 * np.pi, P), shift_m * np.sqrt(rng.random(P))
    shift = np.stack([np.cos(ang) * rad, np.sin(ang) * rad, np.zeros(P)], axis=1) * movable[:, None]
    offsets = rng.uniform(-COLOUR_JITTER, COLOUR_JITTER, (P, 3))
    w = scene.world
    corners = w.corners + shift[label][:, None, :].astype(np.float32)
    moved = World(w.name, corners, w.colour, w.corner_rgb, w.uvs, w.texture_id, w.textures, w.floor, w.info)
    return ScanScene(moved, offsets=offsets[label], source=f"{scene.source}#variant{variant}")


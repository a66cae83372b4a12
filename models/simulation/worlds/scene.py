"""A world as a simulation scene: ``ScanScene`` renders like ``scenes.SimScene`` (``render.render`` calls its
``shade_hits``) and answers distance and occupancy queries through ``ScanRaycaster``.

Colour is the scan's own, as captured (its lighting is baked in, so no light is added): the texture at the
hit's barycentric UV (bilinear, repeating), or the hit triangle's interpolated vertex/face colours; a scan
without colour is drawn in neutral grey with headlight shading (labelled as such in the world's info).
A ray that hits nothing is *no data*: ``NO_DATA_RGB``, depth 0.

Occupancy is conservative (``ScanRaycaster.compute_occupancy``): a point counts as occupied when it lies
outside the scan's bounds, when more than ``ESCAPE_FRACTION`` of the ``OCCUPANCY_DIRECTIONS`` rays from it that
point sideways or down (direction z <= ``ESCAPE_MAX_UP``: open sky or a missing ceiling above is fine) hit no
surface (it is in unscanned space: outside the room's shell, beyond a hole), or when more than
``BACKFACE_FRACTION`` of the rays that hit see the back of a surface (inside an object or behind a wall:
scanned surfaces face the space the scanner was in). That needs the triangles' winding, which meshes and
fused RGB-D carry; a surface meshed from a point cloud without normals has estimated ones, so there the
``parity`` rule replaces it: a ray that hits counts against the point when it crosses the surface an even
number of times (inside a closed object, or outside the room's shell; from a room's free space a ray crosses
its shell once, plus twice per object it passes through). So collision counts treat unknown space as an
obstacle, never as free space.
"""

from __future__ import annotations

import functools
import posixpath
import threading
from pathlib import Path

import numpy as np
import open3d as o3d

from navcrafter.models.simulation.worlds import NO_DATA_RGB, SCAN_KIND, WORLD_VERSION, WorldError
from navcrafter.models.simulation.worlds.segments import segment
from navcrafter.models.simulation.worlds.world import World, texture_lookup

ESCAPE_FRACTION = 0.6
ESCAPE_MAX_UP = 0.2  # escaping rays are counted among directions at most this far up (z of the unit direction)
BACKFACE_FRACTION = 0.5
OCCUPANCY_DIRECTIONS = 48
NEUTRAL_ALBEDO = 0.7
OCCUPANCY_RULES = ("backface", "parity")


def sphere_directions(n: int) -> np.ndarray:
    """``n`` near-uniform unit directions (Fibonacci sphere)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5**0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


class ScanRaycaster:
    """Open3D raycasting of a triangle soup, with the conservative occupancy of the module docstring."""

    def __init__(self, corners: np.ndarray, rule: str = "backface") -> None:
        if rule not in OCCUPANCY_RULES:
            raise ValueError(f"occupancy rule {rule!r} not in {OCCUPANCY_RULES}")
        self.rule = rule
        self.corners = np.asarray(corners, dtype=np.float32)
        self._rc = o3d.t.geometry.RaycastingScene()
        n = len(self.corners)
        self._rc.add_triangles(o3d.core.Tensor(self.corners.reshape(-1, 3)),
                               o3d.core.Tensor(np.arange(3 * n, dtype=np.uint32).reshape(-1, 3)))
        self.lo, self.hi = self.corners.reshape(-1, 3).min(0), self.corners.reshape(-1, 3).max(0)
        self.dirs = sphere_directions(OCCUPANCY_DIRECTIONS).astype(np.float32)

    def cast_rays(self, rays):
        return self._rc.cast_rays(rays)

    def compute_distance(self, points):
        return self._rc.compute_distance(points)

    def unknown_fractions(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point: the fraction of rays that escape, and of hits that see a back face (``parity``: that cross
        the surface an even number of times)."""
        p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0), np.zeros(0)
        D = len(self.dirs)
        rays = np.concatenate([np.repeat(p, D, 0), np.tile(self.dirs, (len(p), 1))], axis=1)
        ans = self._rc.cast_rays(o3d.core.Tensor(rays))
        hit = np.isfinite(ans["t_hit"].numpy()).reshape(len(p), D)
        back = ((ans["primitive_normals"].numpy() * rays[:, 3:]).sum(1) > 0).reshape(len(p), D) & hit
        low = self.dirs[:, 2] <= ESCAPE_MAX_UP  # open sky or a missing ceiling above is not unscanned ground
        escape = 1.0 - hit[:, low].mean(1)
        if self.rule == "parity":
            crossings = self._rc.count_intersections(o3d.core.Tensor(rays)).numpy().reshape(len(p), D)
            back = (crossings % 2 == 0) & hit
        backface = back.sum(1) / np.maximum(hit.sum(1), 1)
        return escape, backface

    def occupied(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        outside = np.any((p < self.lo) | (p > self.hi), axis=1)
        escape, backface = self.unknown_fractions(p)
        return outside | (escape > ESCAPE_FRACTION) | (backface > BACKFACE_FRACTION)

    def compute_occupancy(self, points):
        """1 where a point is inside an object or in unscanned space (conservative), else 0 (Open3D's API)."""
        pts = points.numpy() if hasattr(points, "numpy") else np.asarray(points)
        return o3d.core.Tensor(self.occupied(pts).astype(np.float32))


class ScanScene:
    """A world rendered as a simulation scene (the duck type of ``scenes.SimScene`` that ``render``, the
    simulated roles and the metrics use). ``offsets [F, 3]``: a colour offset per triangle (variants)."""

    kind = SCAN_KIND
    seed = 0
    sky = False
    light = None
    objects: list = []
    materials: list = []
    camera_fov_x_deg = 65.0

    def __init__(self, world: World, offsets: np.ndarray | None = None, source: str = "") -> None:
        self.world = world
        self.offsets = offsets
        self.source = source  # where the world file was read (variants' cache key)
        self.camera_c2w = np.eye(4)
        self._rc: ScanRaycaster | None = None
        self._lock = threading.Lock()
        self._patches = None

    @property
    def spec(self) -> dict:
        return {"kind": SCAN_KIND, "name": self.world.name, "world_version": WORLD_VERSION}

    def raycasting(self) -> tuple[ScanRaycaster, np.ndarray]:
        with self._lock:
            if self._rc is None:
                self._rc = ScanRaycaster(self.world.corners, self.world.info.get("occupancy", "backface"))
            return self._rc, np.zeros(1, dtype=np.int64)

    def distance(self, points: np.ndarray) -> np.ndarray:
        rc, _ = self.raycasting()
        if len(points) == 0:
            return np.zeros(0)
        return rc.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()

    def occupied(self, points: np.ndarray) -> np.ndarray:
        return self.raycasting()[0].occupied(points)

    def merged_mesh(self) -> o3d.geometry.TriangleMesh:
        return self.world.merged_mesh()

    def shade_hits(self, ans: dict, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Colour ``[N, 3]`` in [0, 1] of cast rays (``render._shade``'s hook): the scan's captured colour."""
        t = ans["t_hit"]
        hit = np.isfinite(t)
        colour = np.empty((len(t), 3))
        colour[:] = np.asarray(NO_DATA_RGB, dtype=np.float64) / 255.0
        if not hit.any():
            return colour
        w = self.world
        idx = np.flatnonzero(hit)
        prim = ans["primitive_ids"][idx].astype(np.int64)
        b = ans["primitive_uvs"][idx].astype(np.float64)
        bary = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)[:, :, None]  # [N, 3, 1]
        if w.colour == "neutral":
            n = ans["primitive_normals"][idx].astype(np.float64)
            d = dirs[idx] / np.linalg.norm(dirs[idx], axis=1, keepdims=True)
            lam = np.abs((n * d).sum(1)) / np.maximum(np.linalg.norm(n, axis=1), 1e-12)
            rgb = np.repeat((NEUTRAL_ALBEDO * (0.3 + 0.7 * lam))[:, None], 3, axis=1)
        else:
            rgb = (np.full((len(idx), 3), NEUTRAL_ALBEDO) if w.corner_rgb is None
                   else (w.corner_rgb[prim].astype(np.float64) * bary).sum(1))
            if w.colour == "texture":
                tid = w.texture_id[prim]
                uv = (w.uvs[prim].astype(np.float64) * bary).sum(1)
                for k in np.unique(tid[tid >= 0]):
                    sel = tid == k
                    rgb[sel] = texture_lookup(w.textures[int(k)], uv[sel])
        if self.offsets is not None:
            rgb = rgb + self.offsets[prim]
        colour[idx] = np.clip(rgb, 0.0, 1.0)
        return colour

    def patches(self):
        """The world's surface patches (``segments.segment``), computed once."""
        with self._lock:
            if self._patches is None:
                self._patches = segment(self.world)
            return self._patches


def _join(folder: str, relative: str) -> str:
    if "://" in folder:
        proto, rest = folder.split("://", 1)
        return f"{proto}://{posixpath.normpath(posixpath.join(rest, relative))}"
    return str((Path(folder) / relative).resolve())


@functools.lru_cache(maxsize=4)
def load_scan_scene(location: str, sha256: str) -> ScanScene:
    """The world stored at ``location`` (a path or fsspec URL), checked against its recorded sha256."""
    import hashlib

    import fsspec

    try:
        with fsspec.open(location, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise WorldError(f"{location}: the world file of this demo photo is missing; write the demo again with "
                         f"`navcrafter demo-data --world`") from None
    if hashlib.sha256(data).hexdigest() != sha256:
        raise WorldError(f"{location}: the world file changed since its photos were written; write the demo "
                         f"again with `navcrafter demo-data --world`")
    return ScanScene(World.from_bytes(data, location), source=f"{location}#{sha256}")


def scene_from_record(record: dict) -> ScanScene:
    """The world of a demo photo's ground-truth record (ingest's ``simulation_truth``, with ``groundtruth``:
    the folder of the photo's ``scene.json``)."""
    spec = record["scene"]
    if int(spec.get("world_version", -1)) != WORLD_VERSION:
        raise WorldError(f"ground truth was written for world format v{spec.get('world_version')}, this is "
                         f"v{WORLD_VERSION}; write the demo again with `navcrafter demo-data --world`")
    folder = record.get("groundtruth")
    if not folder:
        raise WorldError("the ground-truth record of a scan world has no 'groundtruth' folder; ingest the photo "
                         "again")
    return load_scan_scene(_join(str(folder), spec["world"]), spec["world_sha256"])

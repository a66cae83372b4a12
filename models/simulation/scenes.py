"""Procedurally generated ground-truth scenes (textured triangle meshes) for simulation mode.

Three kinds, each fully determined by ``(kind, seed)``:

* ``room``     an indoor room (walls, floor, ceiling) with furniture-like obstacles;
* ``street``   an outdoor street/courtyard: ground, building blocks with windows, trees, cars,
               benches and bollards, open sky;
* ``tabletop`` an object-centric scene: a table with small objects in a closed room.

The ground-truth frame is z-up, in metres. Cameras are OpenCV camera-to-world poses
(see ``navcrafter.models.camera.cameras``). Every scene also chooses the pose and field of view of its
"input photo" camera, placed in free space (at least ``MIN_CAMERA_CLEARANCE`` from any surface).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from navcrafter.models.camera.cameras import look_at
from navcrafter.models.simulation.textures import Material

GENERATOR_VERSION = 1
KINDS = ("room", "street", "tabletop")
MIN_CAMERA_CLEARANCE = 0.4
UP = np.array([0.0, 0.0, 1.0])


@dataclass
class SceneObject:
    name: str
    mesh: o3d.geometry.TriangleMesh
    material: int


@dataclass
class Light:
    kind: str  # "point" or "sun"
    vector: tuple[float, float, float]  # position (point) or direction towards the sun (sun)
    ambient: float = 0.35
    strength: float = 0.75


@dataclass
class SimScene:
    """A generated scene: meshes with materials, lighting, sky, and its input-photo camera."""

    kind: str
    seed: int
    objects: list[SceneObject]
    materials: list[Material]
    light: Light
    sky: bool
    camera_c2w: np.ndarray
    camera_fov_x_deg: float
    _rc: o3d.t.geometry.RaycastingScene | None = field(default=None, repr=False)
    _geom_material: np.ndarray | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def spec(self) -> dict:
        return {"kind": self.kind, "seed": self.seed, "generator_version": GENERATOR_VERSION}

    def raycasting(self) -> tuple[o3d.t.geometry.RaycastingScene, np.ndarray]:
        """The Open3D raycasting scene (built once) and the material index of each geometry id."""
        with self._lock:
            if self._rc is None:
                rc = o3d.t.geometry.RaycastingScene()
                mats = []
                for obj in self.objects:
                    gid = rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
                    assert gid == len(mats)
                    mats.append(obj.material)
                self._geom_material = np.asarray(mats, dtype=np.int64)
                self._rc = rc
            return self._rc, self._geom_material

    def merged_mesh(self) -> o3d.geometry.TriangleMesh:
        """All objects in one mesh, vertex-coloured with each material's first colour."""
        out = o3d.geometry.TriangleMesh()
        for obj in self.objects:
            m = o3d.geometry.TriangleMesh(obj.mesh)
            m.paint_uniform_color(self.materials[obj.material].color_a)
            out += m
        return out

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance of points ``[N, 3]`` (ground-truth frame) to the nearest surface."""
        rc, _ = self.raycasting()
        if len(points) == 0:
            return np.zeros(0)
        return rc.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()


# --------------------------------------------------------------------------------------------------
# Mesh helpers (ground-truth frame, z up)
# --------------------------------------------------------------------------------------------------
def _box(x0: float, y0: float, z0: float, sx: float, sy: float, sz: float) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
    m.translate((x0, y0, z0))
    return m


def _cyl(cx: float, cy: float, z0: float, r: float, h: float, res: int = 24) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_cylinder(radius=r, height=h, resolution=res)
    m.translate((cx, cy, z0 + h / 2))
    return m


def _sphere(cx: float, cy: float, cz: float, r: float) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_sphere(radius=r, resolution=16)
    m.translate((cx, cy, cz))
    return m


def _cone(cx: float, cy: float, z0: float, r: float, h: float) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_cone(radius=r, height=h, resolution=24)
    m.translate((cx, cy, z0))
    return m


class _Builder:
    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.objects: list[SceneObject] = []
        self.materials: list[Material] = []
        self.footprints: list[tuple[float, float, float, float]] = []

    def material(self, pattern: str, a, b, scale: float) -> int:
        jitter = self.rng.uniform(-0.06, 0.06, 3)
        ca = tuple(float(x) for x in np.clip(np.asarray(a) + jitter, 0, 1))
        cb = tuple(float(x) for x in np.clip(np.asarray(b) + jitter, 0, 1))
        self.materials.append(Material(pattern, ca, cb, scale, int(self.rng.integers(1 << 30))))
        return len(self.materials) - 1

    def add(self, name: str, mesh: o3d.geometry.TriangleMesh, material: int) -> None:
        mesh.compute_triangle_normals()
        self.objects.append(SceneObject(name, mesh, material))

    def place(self, w: float, d: float, xlim, ylim, margin: float, tries: int = 200):
        """A free axis-aligned footprint ``w x d`` inside limits, or ``None``."""
        for _ in range(tries):
            x = self.rng.uniform(xlim[0], xlim[1] - w)
            y = self.rng.uniform(ylim[0], ylim[1] - d)
            if all(x + w + margin < fx0 or fx1 + margin < x or y + d + margin < fy0 or fy1 + margin < y
                   for fx0, fy0, fx1, fy1 in self.footprints):
                self.footprints.append((x, y, x + w, y + d))
                return x, y
        return None


PALETTE_WOOD = ((0.55, 0.36, 0.2), (0.38, 0.22, 0.1))
PALETTE_FABRIC = [((0.25, 0.35, 0.55), (0.15, 0.22, 0.38)), ((0.6, 0.25, 0.2), (0.4, 0.15, 0.12)),
                  ((0.35, 0.5, 0.3), (0.2, 0.32, 0.18)), ((0.7, 0.62, 0.45), (0.5, 0.42, 0.3))]


def _furniture(b: _Builder, kind: str, x: float, y: float, w: float, d: float, room_h: float) -> None:
    rng = b.rng
    if kind == "table":
        top = b.material("wood", *PALETTE_WOOD, 0.3)
        h = rng.uniform(0.7, 0.78)
        b.add("table_top", _box(x, y, h - 0.04, w, d, 0.04), top)
        leg = b.material("plain", (0.2, 0.2, 0.22), (0.1, 0.1, 0.1), 0.3)
        for lx, ly in ((x, y), (x + w - 0.05, y), (x, y + d - 0.05), (x + w - 0.05, y + d - 0.05)):
            b.add("table_leg", _box(lx, ly, 0.0, 0.05, 0.05, h - 0.04), leg)
    elif kind == "sofa":
        fab = b.material("noise", *PALETTE_FABRIC[int(rng.integers(len(PALETTE_FABRIC)))], 0.2)
        b.add("sofa_seat", _box(x, y, 0.0, w, d, 0.45), fab)
        b.add("sofa_back", _box(x, y + d - 0.2, 0.45, w, 0.2, 0.4), fab)
    elif kind == "cabinet":
        mat = b.material("stripes", (0.8, 0.78, 0.72), (0.6, 0.58, 0.52), 0.4)
        b.add("cabinet", _box(x, y, 0.0, w, d, rng.uniform(1.4, min(2.1, room_h - 0.3))), mat)
    elif kind == "pillar":
        mat = b.material("brick", (0.65, 0.3, 0.22), (0.85, 0.82, 0.78), 0.25)
        b.add("pillar", _cyl(x + w / 2, y + d / 2, 0.0, min(w, d) / 2, room_h), mat)
    elif kind == "plant":
        pot = b.material("plain", (0.7, 0.4, 0.25), (0.5, 0.3, 0.2), 0.2)
        b.add("plant_pot", _cyl(x + w / 2, y + d / 2, 0.0, min(w, d) / 2 * 0.7, 0.4), pot)
        leaves = b.material("noise", (0.2, 0.5, 0.2), (0.1, 0.3, 0.1), 0.08)
        b.add("plant", _sphere(x + w / 2, y + d / 2, 0.75, min(w, d) / 2), leaves)
    elif kind == "crate":
        mat = b.material("wood", (0.75, 0.6, 0.4), (0.55, 0.4, 0.25), 0.2)
        b.add("crate", _box(x, y, 0.0, w, d, rng.uniform(0.4, 0.9)), mat)
    else:  # pragma: no cover
        raise AssertionError(kind)


FURNITURE_SIZES = {"table": ((1.0, 1.6), (0.6, 0.9)), "sofa": ((1.6, 2.2), (0.8, 0.95)),
                   "cabinet": ((0.6, 1.2), (0.4, 0.55)), "pillar": ((0.3, 0.45), (0.3, 0.45)),
                   "plant": ((0.4, 0.6), (0.4, 0.6)), "crate": ((0.4, 0.8), (0.4, 0.8))}


def _closed_room(b: _Builder, W: float, D: float, H: float, floor_pattern: str) -> None:
    t = 0.1
    floor = b.material(floor_pattern, *(PALETTE_WOOD if floor_pattern == "wood"
                                        else ((0.75, 0.75, 0.72), (0.35, 0.35, 0.38))), 0.4)
    wall = b.material(str(b.rng.choice(["plain", "stripes", "tiles"])),
                      tuple(b.rng.uniform(0.55, 0.9, 3)), tuple(b.rng.uniform(0.4, 0.75, 3)), 0.35)
    ceiling = b.material("plain", (0.92, 0.92, 0.9), (0.8, 0.8, 0.78), 1.0)
    b.add("floor", _box(-t, -t, -t, W + 2 * t, D + 2 * t, t), floor)
    b.add("ceiling", _box(-t, -t, H, W + 2 * t, D + 2 * t, t), ceiling)
    b.add("wall_south", _box(-t, -t, 0, W + 2 * t, t, H), wall)
    b.add("wall_north", _box(-t, D, 0, W + 2 * t, t, H), wall)
    b.add("wall_west", _box(-t, 0, 0, t, D, H), wall)
    b.add("wall_east", _box(W, 0, 0, t, D, H), wall)
    # pictures on the north and east walls: thin textured panels
    for i in range(int(b.rng.integers(1, 4))):
        pic = b.material(str(b.rng.choice(["checker", "noise", "stripes"])),
                         tuple(b.rng.uniform(0, 1, 3)), tuple(b.rng.uniform(0, 1, 3)), 0.12)
        pw, ph = b.rng.uniform(0.5, 1.1), b.rng.uniform(0.4, 0.8)
        if i % 2 == 0:
            b.add("picture", _box(b.rng.uniform(0.3, W - pw - 0.3), D - 0.02, 1.3, pw, 0.02, ph), pic)
        else:
            b.add("picture", _box(W - 0.02, b.rng.uniform(0.3, D - pw - 0.3), 1.3, 0.02, pw, ph), pic)


def _room(rng: np.random.Generator) -> tuple[_Builder, Light, bool, np.ndarray, np.ndarray, float]:
    b = _Builder(rng)
    W, D, H = rng.uniform(5.0, 7.0), rng.uniform(4.5, 6.0), rng.uniform(2.6, 3.0)
    _closed_room(b, W, D, H, str(rng.choice(["wood", "tiles"])))
    rug = b.material("checker", tuple(rng.uniform(0.3, 0.8, 3)), tuple(rng.uniform(0.1, 0.5, 3)), 0.3)
    b.add("rug", _box(W * 0.3, D * 0.35, 0.0, W * 0.4, D * 0.3, 0.01), rug)
    eye = np.array([rng.uniform(0.35, 0.65) * W, rng.uniform(0.5, 0.8), rng.uniform(1.4, 1.65)])
    b.footprints.append((eye[0] - 1.0, 0.0, eye[0] + 1.0, eye[1] + 1.3))  # keep the camera free
    kinds = ["table", "sofa", "cabinet", "cabinet", "pillar", "plant", "crate", "crate"]
    for kind in rng.permutation(kinds)[: int(rng.integers(5, 8))]:
        (w0, w1), (d0, d1) = FURNITURE_SIZES[str(kind)]
        w, d = rng.uniform(w0, w1), rng.uniform(d0, d1)
        if rng.random() < 0.5 and kind in ("sofa", "cabinet", "table", "crate"):
            w, d = d, w
        spot = b.place(w, d, (0.15, W - 0.15), (0.15, D - 0.15), margin=0.35)
        if spot is not None:
            _furniture(b, str(kind), spot[0], spot[1], w, d, H)
    target = np.array([W * rng.uniform(0.4, 0.6), D * 0.75, rng.uniform(0.8, 1.1)])
    light = Light("point", (W / 2, D / 2, H - 0.3), ambient=0.4, strength=0.8)
    return b, light, False, eye, target, float(rng.uniform(60, 72))


def _street(rng: np.random.Generator) -> tuple[_Builder, Light, bool, np.ndarray, np.ndarray, float]:
    b = _Builder(rng)
    half = rng.uniform(5.0, 7.5)  # half width of the street / courtyard
    L = 40.0
    ground = b.material("noise", (0.32, 0.32, 0.34), (0.2, 0.2, 0.22), 0.5)
    b.add("ground", _box(-L, -L, -0.2, 2 * L, 2 * L, 0.2), ground)
    walk = b.material("tiles", (0.62, 0.6, 0.56), (0.45, 0.43, 0.4), 0.5)
    for side in (-1, 1):
        y0 = half - 2.0 if side > 0 else -half
        b.add("sidewalk", _box(-L / 2, y0, 0.0, L, 2.0, 0.12), walk)
        x = -L / 2
        while x < L / 2:
            w = rng.uniform(6.0, 11.0)
            depth = rng.uniform(6.0, 10.0)
            h = rng.uniform(6.0, 16.0)
            facade = b.material(str(rng.choice(["windows", "brick"])),
                                tuple(rng.uniform(0.5, 0.85, 3)), (0.12, 0.14, 0.18), rng.uniform(1.2, 1.8))
            y = half if side > 0 else -half - depth
            b.add("building", _box(x, y, 0.0, w - 0.3, depth, h), facade)
            x += w
    # a building closing the far end: a courtyard
    end = b.material("windows", tuple(rng.uniform(0.5, 0.85, 3)), (0.12, 0.14, 0.18), 1.5)
    b.add("building_end", _box(rng.uniform(16, 22), -half - 2, 0, 8, 2 * half + 4, rng.uniform(8, 14)), end)
    bark = b.material("noise", (0.35, 0.25, 0.15), (0.2, 0.14, 0.08), 0.1)
    leaves = b.material("noise", (0.2, 0.45, 0.18), (0.08, 0.25, 0.08), 0.3)
    for x in np.arange(-8.0, 16.0, rng.uniform(5.0, 7.0)):
        y = (half - 1.0) * (1 if rng.random() < 0.5 else -1)
        b.add("tree_trunk", _cyl(x, y, 0.0, 0.15, 2.8), bark)
        b.add("tree_crown", _sphere(x, y, 3.6, rng.uniform(1.0, 1.5)), leaves)
    for _ in range(int(rng.integers(2, 5))):
        paint = b.material("plain", tuple(rng.uniform(0.1, 0.9, 3)), (0.1, 0.1, 0.1), 0.5)
        x, y = rng.uniform(2.0, 15.0), rng.uniform(-half + 1.0, half - 3.5)
        b.add("car_body", _box(x, y, 0.3, 4.2, 1.8, 0.75), paint)
        glass = b.material("plain", (0.15, 0.2, 0.25), (0.05, 0.05, 0.08), 0.5)
        b.add("car_cabin", _box(x + 1.0, y + 0.1, 1.05, 2.2, 1.6, 0.55), glass)
    stone = b.material("plain", (0.5, 0.5, 0.5), (0.3, 0.3, 0.3), 0.2)
    for x in np.arange(-4.0, 14.0, 2.0):
        b.add("bollard", _cyl(x, -half + 2.2, 0.0, 0.1, 0.9), stone)
    eye = np.array([-6.0 + rng.uniform(-1, 1), rng.uniform(-1.0, 1.0), rng.uniform(1.5, 1.8)])
    target = np.array([12.0, rng.uniform(-1.5, 1.5), rng.uniform(1.5, 3.0)])
    sun = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.6, 0.6), 1.0])
    light = Light("sun", tuple(float(v) for v in sun / np.linalg.norm(sun)), ambient=0.45, strength=0.7)
    return b, light, True, eye, target, float(rng.uniform(65, 80))


def _tabletop(rng: np.random.Generator) -> tuple[_Builder, Light, bool, np.ndarray, np.ndarray, float]:
    b = _Builder(rng)
    W, D, H = 6.0, 6.0, 2.8
    _closed_room(b, W, D, H, "tiles")
    tx, ty, tw, td, th = 2.2, 2.5, 1.6, 1.0, 0.75
    top = b.material("wood", *PALETTE_WOOD, 0.25)
    b.add("table_top", _box(tx, ty, th - 0.05, tw, td, 0.05), top)
    leg = b.material("plain", (0.25, 0.2, 0.18), (0.1, 0.1, 0.1), 0.3)
    for lx, ly in ((tx, ty), (tx + tw - 0.06, ty), (tx, ty + td - 0.06), (tx + tw - 0.06, ty + td - 0.06)):
        b.add("table_leg", _box(lx, ly, 0.0, 0.06, 0.06, th - 0.05), leg)
    b.footprints.clear()
    for _ in range(int(rng.integers(5, 9))):
        size = rng.uniform(0.08, 0.22)
        spot = b.place(size, size, (tx + 0.05, tx + tw - 0.05), (ty + 0.05, ty + td - 0.05), margin=0.04)
        if spot is None:
            continue
        x, y = spot
        mat = b.material(str(rng.choice(["checker", "stripes", "noise", "plain", "wood"])),
                         tuple(rng.uniform(0.1, 0.95, 3)), tuple(rng.uniform(0.05, 0.9, 3)), size / 2)
        shape = rng.choice(["box", "sphere", "cylinder", "cone"])
        if shape == "box":
            b.add("object_box", _box(x, y, th, size, size, rng.uniform(0.5, 1.5) * size), mat)
        elif shape == "sphere":
            b.add("object_sphere", _sphere(x + size / 2, y + size / 2, th + size / 2, size / 2), mat)
        elif shape == "cylinder":
            b.add("object_cylinder", _cyl(x + size / 2, y + size / 2, th, size / 2, rng.uniform(0.8, 2) * size), mat)
        else:
            b.add("object_cone", _cone(x + size / 2, y + size / 2, th, size / 2, rng.uniform(1, 2) * size), mat)
    centre = np.array([tx + tw / 2, ty + td / 2, th + 0.05])
    ang = rng.uniform(-0.5, 0.5) - np.pi / 2
    dist = rng.uniform(1.1, 1.4)
    eye = centre + np.array([np.cos(ang) * dist, np.sin(ang) * dist, rng.uniform(0.45, 0.65)])
    light = Light("point", (W / 2 - 0.5, D / 2 - 1.0, H - 0.2), ambient=0.4, strength=0.8)
    return b, light, False, eye, centre, float(rng.uniform(50, 60))


_GENERATORS = {"room": _room, "street": _street, "tabletop": _tabletop}


def generate_scene(kind: str, seed: int) -> SimScene:
    """Build the scene ``(kind, seed)``; identical inputs give identical meshes and cameras."""
    if kind not in _GENERATORS:
        raise ValueError(f"unknown scene kind {kind!r}; choose from {KINDS}")
    salt = KINDS.index(kind)
    rng = np.random.default_rng([int(seed), salt, GENERATOR_VERSION])
    b, light, sky, eye, target, fov = _GENERATORS[kind](rng)
    c2w = look_at(eye, target, up=UP)
    scene = SimScene(kind, int(seed), b.objects, b.materials, light, sky, c2w, fov)
    clearance = float(scene.distance(eye[None])[0])
    if clearance < MIN_CAMERA_CLEARANCE:  # generators keep the camera free; this guards regressions
        raise RuntimeError(f"scene {kind}/{seed}: input camera is {clearance:.2f} m from a surface")
    return scene

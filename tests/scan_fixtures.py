"""Small scans built by the tests themselves (nothing downloaded): a textured box room (OBJ + MTL + PNG, y up
as OBJ exports usually are), a coloured point-cloud room (PCD, z up) and a three-frame posed RGB-D sequence.

The room (ground-truth frame: z up, metres): 5 x 4 x 2.6 m, floor at z = 0, x in [0, 5], y in [0, 4], with a
0.8 m crate standing at x in [3.6, 4.4], y in [2.6, 3.4]. Surfaces face into the room."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

W, D, H = 5.0, 4.0, 2.6
CRATE = (3.6, 2.6, 0.0, 0.8, 0.8, 0.8)  # x0, y0, z0, sx, sy, sz
# floor texture: upper half of the image (v > 0.5: far side, y > 2) red, lower half blue
RED, BLUE = (220, 30, 30), (30, 30, 220)
WALL, CRATE_RGB = (200, 190, 150), (40, 160, 60)


def _quad(p0, p1, p2, p3, inward) -> list[np.ndarray]:
    """Two triangles of a quad, wound so their normal is ``inward``."""
    q = [np.asarray(p, dtype=np.float64) for p in (p0, p1, p2, p3)]
    n = np.cross(q[1] - q[0], q[2] - q[0])
    if n @ np.asarray(inward) < 0:
        q = [q[0], q[3], q[2], q[1]]
    return [np.stack([q[0], q[1], q[2]]), np.stack([q[0], q[2], q[3]])]


def room_quads(holes: bool = False) -> list[tuple[str, list[np.ndarray]]]:
    """(surface name, triangles) of the room, ground-truth frame. ``holes``: no ceiling over x > 3."""
    out = [("floor", _quad((0, 0, 0), (W, 0, 0), (W, D, 0), (0, D, 0), (0, 0, 1)))]
    ceil_x = 3.0 if holes else W
    out.append(("ceiling", _quad((0, 0, H), (ceil_x, 0, H), (ceil_x, D, H), (0, D, H), (0, 0, -1))))
    out.append(("wall", _quad((0, 0, 0), (W, 0, 0), (W, 0, H), (0, 0, H), (0, 1, 0))))
    out.append(("wall", _quad((0, D, 0), (W, D, 0), (W, D, H), (0, D, H), (0, -1, 0))))
    out.append(("wall", _quad((0, 0, 0), (0, D, 0), (0, D, H), (0, 0, H), (1, 0, 0))))
    out.append(("wall", _quad((W, 0, 0), (W, D, 0), (W, D, H), (W, 0, H), (-1, 0, 0))))
    x0, y0, z0, sx, sy, sz = CRATE
    x1, y1, z1 = x0 + sx, y0 + sy, z0 + sz
    crate = []
    crate += _quad((x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1), (0, 0, 1))
    crate += _quad((x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1), (0, -1, 0))
    crate += _quad((x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1), (0, 1, 0))
    crate += _quad((x0, y0, z0), (x0, y1, z0), (x0, y1, z1), (x0, y0, z1), (-1, 0, 0))
    crate += _quad((x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1), (1, 0, 0))
    out.append(("crate", crate))
    return out


def _subdivide(tris: list[np.ndarray], max_edge: float = 0.5) -> list[np.ndarray]:
    out = []
    for t in tris:
        stack = [t]
        while stack:
            a = stack.pop()
            e = [np.linalg.norm(a[(i + 1) % 3] - a[i]) for i in range(3)]
            i = int(np.argmax(e))
            if e[i] <= max_edge:
                out.append(a)
                continue
            m = (a[i] + a[(i + 1) % 3]) / 2
            stack.append(np.stack([a[i], m, a[(i + 2) % 3]]))
            stack.append(np.stack([m, a[(i + 1) % 3], a[(i + 2) % 3]]))
    return out


def gt_to_yup(p: np.ndarray) -> np.ndarray:
    """Ground-truth (z up) to the OBJ file's y-up axes."""
    p = np.asarray(p, dtype=np.float64)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def write_obj_room(folder: Path, *, texture: bool = True, nan: bool = False, unit: float = 1.0) -> Path:
    """The textured room as ``room.obj`` + ``room.mtl`` + ``floor.png`` / ``wall.png`` (y up, ``unit``: file
    units per metre). ``texture=False`` writes the MTL but not the PNGs (a missing texture)."""
    folder.mkdir(parents=True, exist_ok=True)
    floor = np.zeros((32, 32, 3), dtype=np.uint8)
    floor[:16] = RED  # image top = v high = far side (y > D / 2)
    floor[16:] = BLUE
    if texture:
        Image.fromarray(floor).save(folder / "floor.png")
        Image.fromarray(np.full((8, 8, 3), WALL, dtype=np.uint8)).save(folder / "wall.png")
        crate = np.full((16, 16, 3), CRATE_RGB, dtype=np.uint8)
        crate[::4] = (20, 80, 30)  # stripes
        Image.fromarray(crate).save(folder / "crate.png")
    (folder / "room.mtl").write_text("newmtl floor\nKd 1 1 1\nmap_Kd floor.png\n\nnewmtl wall\nKd 1 1 1\n"
                                     "map_Kd wall.png\n\nnewmtl crate\nKd 0.16 0.63 0.24\nmap_Kd wall.png\n")
    lines = ["mtllib room.mtl"]
    vi = 1
    for name, tris in room_quads():
        mat = "floor" if name == "floor" else ("crate" if name == "crate" else "wall")
        lines.append(f"o {name}\nusemtl {mat}")
        for t in _subdivide(tris):
            for p in t:
                q = gt_to_yup(p) * unit
                lines.append(f"v {q[0]:.6f} {q[1]:.6f} {q[2]:.6f}")
                lines.append(f"vt {p[0] / W:.6f} {p[1] / D:.6f}")
            lines.append(f"f {vi}/{vi} {vi + 1}/{vi + 1} {vi + 2}/{vi + 2}")
            vi += 3
    if nan:
        lines.insert(1, "v nan 0 0")
        lines.append("f 1 2 3")
    (folder / "room.obj").write_text("\n".join(lines) + "\n")
    return folder / "room.obj"


def room_points(spacing: float = 0.06, holes: bool = True, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (z up) and colours sampled on the room's surfaces: floor red/blue by y, walls beige, crate green."""
    rng = np.random.default_rng(seed)
    pts, cols = [], []
    for name, tris in room_quads(holes=holes):
        for t in tris:
            area = 0.5 * np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0]))
            n = max(3, int(area / spacing**2))
            r1, r2 = rng.random(n), rng.random(n)
            s = np.sqrt(r1)
            p = t[0] * (1 - s)[:, None] + t[1] * (s * (1 - r2))[:, None] + t[2] * (s * r2)[:, None]
            if name == "floor":
                c = np.where((p[:, 1] > D / 2)[:, None], RED, BLUE)
            else:
                c = np.broadcast_to(CRATE_RGB if name == "crate" else WALL, p.shape)
            pts.append(p)
            cols.append(np.asarray(c, dtype=np.float64) / 255.0)
    return np.concatenate(pts), np.concatenate(cols)


def write_pcd_room(path: Path, colours: bool = True) -> Path:
    import open3d as o3d

    pts, cols = room_points()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if colours:
        pcd.colors = o3d.utility.Vector3dVector(cols)
    path.parent.mkdir(parents=True, exist_ok=True)
    o3d.io.write_point_cloud(str(path), pcd)
    return path


def write_rgbd_sequence(folder: Path, scene, size: tuple[int, int] = (96, 72)) -> Path:
    """Three posed RGB-D frames of ``scene`` (a ``ScanScene`` of the room, ground-truth frame) in the Redwood
    layout of ``worlds.load.RGBD_LAYOUT`` (depth in mm, trajectory.log)."""
    from navcrafter.models.camera.cameras import Intrinsics, look_at
    from navcrafter.models.simulation.render import render

    w, h = size
    K = Intrinsics.from_fov(70.0, w, h)
    (folder / "color").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    log = []
    eye = np.array([-1.0, -0.5, 1.4])  # the world is centred: the room spans x in [-2.5, 2.5], y in [-2, 2]
    targets = [(2.0, 1.5, 0.0), (2.0, -1.5, 0.2), (-2.0, 1.5, 0.2)]
    for i, tgt in enumerate(targets):
        c2w = look_at(eye, np.asarray(tgt, dtype=np.float64), up=np.array([0.0, 0.0, 1.0]))
        r = render(scene, c2w, K)
        Image.fromarray(r.rgb).save(folder / "color" / f"{i:03d}.png")
        Image.fromarray(np.round(r.depth * 1000).astype(np.uint16)).save(folder / "depth" / f"{i:03d}.png")
        log.append(f"{i} {i} {i + 1}")
        log += [" ".join(f"{x:.8f}" for x in row) for row in c2w]
    (folder / "trajectory.log").write_text("\n".join(log) + "\n")
    fx, fy, cx, cy = K.K[0, 0], K.K[1, 1], K.K[0, 2], K.K[1, 2]
    (folder / "camera.json").write_text(json.dumps({"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": w,
                                                    "height": h, "depth_scale": 1000.0, "depth_max": 8.0}))
    return folder

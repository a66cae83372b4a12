"""A world: a scanned surface in the ground-truth frame (metres, z up, floor at z = 0), as a triangle soup
with its colour source, and its storage (``world.npz`` beside the demo photos' hidden truth)."""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from navcrafter.models.simulation.worlds import WORLD_VERSION, WorldError

COLOUR_MODES = ("texture", "vertex", "neutral")
NEUTRAL_NOTE = ("the scan has no colour: rendered in neutral grey with headlight shading (a labelled stand-in, "
                "not the scene's appearance)")


@dataclass
class World:
    """A scanned surface. ``corners [F, 3, 3]`` (metres, ground-truth frame) is a triangle soup, so that
    patches can move without tearing their neighbours. Colour: ``texture`` (``uvs [F, 3, 2]`` in OpenGL
    convention, v up; ``texture_id [F]`` into ``textures``, -1 where a triangle has none and uses
    ``corner_rgb``), ``vertex`` (``corner_rgb [F, 3, 3]`` in [0, 1]: vertex or face colours) or ``neutral``."""

    name: str
    corners: np.ndarray
    colour: str
    corner_rgb: np.ndarray | None = None
    uvs: np.ndarray | None = None
    texture_id: np.ndarray | None = None
    textures: list[np.ndarray] = field(default_factory=list)
    floor: bool = False  # a floor plane was found (or the up axis was given): cameras go at eye height
    info: dict = field(default_factory=dict)  # source file, format, scale, up, warnings

    def __post_init__(self) -> None:
        if self.colour not in COLOUR_MODES:
            raise ValueError(f"colour mode {self.colour!r} not in {COLOUR_MODES}")
        self.corners = np.ascontiguousarray(self.corners, dtype=np.float32).reshape(-1, 3, 3)

    @property
    def n_triangles(self) -> int:
        return len(self.corners)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        pts = self.corners.reshape(-1, 3)
        return pts.min(0).astype(np.float64), pts.max(0).astype(np.float64)

    # -- storage ---------------------------------------------------------------------------------------
    def to_bytes(self) -> bytes:
        arrays = {"corners": self.corners}
        for k in ("corner_rgb", "uvs", "texture_id"):
            v = getattr(self, k)
            if v is not None:
                arrays[k] = v
        for i, t in enumerate(self.textures):
            arrays[f"texture_{i}"] = t
        meta = {"version": WORLD_VERSION, "name": self.name, "colour": self.colour, "floor": self.floor,
                "textures": len(self.textures), "info": self.info}
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    def save(self, path: str | Path) -> str:
        """Write ``world.npz``; returns its sha256."""
        data = self.to_bytes()
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_bytes(data)
        return hashlib.sha256(data).hexdigest()

    @classmethod
    def from_bytes(cls, data: bytes, where: str) -> World:
        try:
            z = np.load(io.BytesIO(data), allow_pickle=False)
            meta = json.loads(bytes(z["meta"]).decode())
        except Exception as exc:
            raise WorldError(f"{where}: not a readable world file ({exc}); run `navcrafter demo-data --world` "
                             f"again") from exc
        if int(meta.get("version", -1)) != WORLD_VERSION:
            raise WorldError(f"{where}: world format v{meta.get('version')} is not this version's "
                             f"v{WORLD_VERSION}; run `navcrafter demo-data --world` again")
        get = (lambda k: z[k] if k in z.files else None)
        return cls(meta["name"], z["corners"], meta["colour"], get("corner_rgb"), get("uvs"), get("texture_id"),
                   [z[f"texture_{i}"] for i in range(int(meta["textures"]))], bool(meta["floor"]), meta["info"])

    def merged_mesh(self):
        """The world as an Open3D mesh (welded soup, vertex colours where known) for viewers and the PLY."""
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh()
        mesh.vertices = o3d.utility.Vector3dVector(self.corners.reshape(-1, 3).astype(np.float64))
        mesh.triangles = o3d.utility.Vector3iVector(np.arange(3 * self.n_triangles).reshape(-1, 3))
        rgb = self.corner_rgb
        if self.colour == "texture":
            ids = np.repeat(self.texture_id, 3)
            uv = self.uvs.reshape(-1, 2)
            rgb = np.full((len(uv), 3), 0.6) if self.corner_rgb is None else self.corner_rgb.reshape(-1, 3)
            rgb = rgb.astype(np.float64).copy()
            for t in range(len(self.textures)):
                sel = ids == t
                rgb[sel] = texture_lookup(self.textures[t], uv[sel])
        if rgb is not None:
            mesh.vertex_colors = o3d.utility.Vector3dVector(np.asarray(rgb, dtype=np.float64).reshape(-1, 3))
        else:
            mesh.paint_uniform_color((0.6, 0.6, 0.6))
        return mesh


def texture_lookup(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colour ``[N, 3]`` in [0, 1] of a uint8 texture ``[h, w, 3]`` at OpenGL UVs (v up, repeating)."""
    h, w = texture.shape[:2]
    tex = texture  # uint8: only the gathered texels are converted (scan textures are often 4k x 4k)
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = (1.0 - np.mod(uv[:, 1], 1.0)) * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, x1 = np.mod(x0, w), np.mod(x0 + 1, w)
    y0, y1 = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return (top * (1 - fy) + bot * fy) / 255.0


def sample_surface(corners: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points drawn uniformly by area on the triangle soup ``corners [F, 3, 3]``."""
    a = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    p = a / a.sum() if a.sum() > 0 else None
    f = rng.choice(len(corners), size=n, p=p)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return (corners[f] * w[:, :, None]).sum(1)


def ransac_planes(corners: np.ndarray, n_points: int, max_planes: int, min_share: float, seed: int = 0
                  ) -> tuple[np.ndarray, float, list[tuple[np.ndarray, float, int]], np.ndarray]:
    """Planes of the surface found one after another by RANSAC (Open3D ``segment_plane``) on ``n_points`` points
    drawn from it, each fitted to the points the earlier ones left, until ``max_planes`` or one holds fewer than
    ``min_share`` of them: ``(points, threshold, [(unit normal n, d, inliers)], rest)`` with ``n . x + d = 0`` on
    the plane, the threshold 0.5 % of the points' diagonal and ``rest`` the points on none of the planes
    (``load.find_up`` and ``segments`` read them)."""
    # deferred: open3d loads only when a scan is read or segmented
    import open3d as o3d

    pts = sample_surface(corners, n_points, np.random.default_rng(seed))
    diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    thr = max(0.005 * diag, 1e-6)
    o3d.utility.random.seed(seed)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    rest = np.ones(len(pts), dtype=bool)
    planes = []
    for _ in range(max_planes):
        idx = np.flatnonzero(rest)
        if len(idx) < min_share * len(pts):
            break
        model, inl = pcd.select_by_index(idx).segment_plane(thr, 3, 1000)
        if len(inl) < min_share * len(pts):
            break
        n, d = np.asarray(model[:3]), float(model[3])
        k = np.linalg.norm(n)
        planes.append((n / k, d / k, len(inl)))
        rest[idx[np.asarray(inl)]] = False
    return pts, thr, planes, rest

"""Point-cloud fusion and PLY input/output.

Fusion is a deterministic voxel average (pure numpy: the same inputs give the same cloud, bit for bit,
in any process), weighted by confidence; colours are averaged, confidence keeps the maximum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from navcrafter.models.camera.cameras import unproject_depth

_BITS = 21  # per axis: 2^21 voxels of 2 cm span 42 km
_OFFSET = 1 << (_BITS - 1)


@dataclass
class Cloud:
    points: np.ndarray  # [N, 3] float32
    colors: np.ndarray  # [N, 3] uint8
    confidence: np.ndarray  # [N] float32

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float32).reshape(-1, 3)
        self.colors = np.asarray(self.colors, dtype=np.uint8).reshape(-1, 3)
        self.confidence = np.asarray(self.confidence, dtype=np.float32).reshape(-1)
        n = len(self.points)
        if len(self.colors) != n or len(self.confidence) != n:
            raise ValueError(f"cloud arrays disagree: {n} points, {len(self.colors)} colours, "
                             f"{len(self.confidence)} confidences")

    def __len__(self) -> int:
        return len(self.points)

    @classmethod
    def empty(cls) -> Cloud:
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    @classmethod
    def concat(cls, clouds: list[Cloud]) -> Cloud:
        if not clouds:
            return cls.empty()
        return cls(np.concatenate([c.points for c in clouds]), np.concatenate([c.colors for c in clouds]),
                   np.concatenate([c.confidence for c in clouds]))


def voxel_index(points: np.ndarray, voxel: float) -> tuple[int, np.ndarray]:
    """Number of occupied voxels and, per point, the index of its voxel (voxels in sorted order)."""
    if voxel <= 0:
        raise ValueError(f"voxel size must be positive, got {voxel}")
    q = np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64) + _OFFSET
    if len(q) and (q.min() < 0 or q.max() >= (1 << _BITS)):
        raise ValueError(f"cloud extent exceeds the voxel grid ({(1 << _BITS) * voxel:.0f} units per axis)")
    key = (q[:, 0] << (2 * _BITS)) | (q[:, 1] << _BITS) | q[:, 2]
    uniq, inv = np.unique(key, return_inverse=True)
    return len(uniq), inv.reshape(-1)


def thin_points(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel: the mean of its points (float64)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((0, 3))
    n, inv = voxel_index(points, voxel)
    counts = np.bincount(inv, minlength=n)
    return np.stack([np.bincount(inv, weights=points[:, i], minlength=n) for i in range(3)], 1) / counts[:, None]


def voxel_fuse(cloud: Cloud, voxel: float) -> Cloud:
    """One point per occupied voxel: confidence-weighted mean position and colour, max confidence."""
    if voxel <= 0:
        raise ValueError(f"voxel size must be positive, got {voxel}")
    if len(cloud) == 0:
        return Cloud.empty()
    n, inv = voxel_index(cloud.points, voxel)
    w = np.maximum(cloud.confidence.astype(np.float64), 1e-6)
    wsum = np.bincount(inv, weights=w, minlength=n)
    pts = np.stack([np.bincount(inv, weights=w * cloud.points[:, i], minlength=n)
                    for i in range(3)], axis=1) / wsum[:, None]
    cols = np.stack([np.bincount(inv, weights=w * cloud.colors[:, i], minlength=n)
                     for i in range(3)], axis=1) / wsum[:, None]
    conf = np.zeros(n, dtype=np.float32)
    np.maximum.at(conf, inv, cloud.confidence)
    return Cloud(pts.astype(np.float32), np.clip(np.rint(cols), 0, 255).astype(np.uint8), conf)


# --------------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------------
_PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("confidence", "<f4")])


def ply_bytes(cloud: Cloud, comments: list[str] = ()) -> bytes:
    """Binary little-endian PLY with x, y, z, red, green, blue, confidence per vertex."""
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" for c in comments]
    header += [f"element vertex {len(cloud)}",
               "property float x", "property float y", "property float z",
               "property uchar red", "property uchar green", "property uchar blue",
               "property float confidence", "end_header"]
    rec = np.empty(len(cloud), dtype=_PLY_DTYPE)
    rec["x"], rec["y"], rec["z"] = cloud.points.T
    rec["red"], rec["green"], rec["blue"] = cloud.colors.T
    rec["confidence"] = cloud.confidence
    return ("\n".join(header) + "\n").encode("ascii") + rec.tobytes()


def read_ply(data: bytes) -> tuple[Cloud, list[str]]:
    """Read a PLY written by ``ply_bytes``; returns the cloud and its header comments."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError("only binary little-endian PLY is supported")
    n = next(int(h.split()[2]) for h in header if h.startswith("element vertex"))
    props = [h.split()[2] for h in header if h.startswith("property")]
    if props != list(_PLY_DTYPE.names):
        raise ValueError(f"unexpected PLY properties {props}")
    rec = np.frombuffer(data, dtype=_PLY_DTYPE, count=n, offset=end + len(b"end_header\n"))
    cloud = Cloud(np.stack([rec["x"], rec["y"], rec["z"]], 1), np.stack([rec["red"], rec["green"], rec["blue"]], 1),
                  rec["confidence"])
    return cloud, [h[len("comment "):] for h in header if h.startswith("comment ")]


def views_to_cloud(images: np.ndarray, depth: np.ndarray, confidence: np.ndarray, c2w: np.ndarray,
                   K: np.ndarray, min_confidence: float, stride: int = 1,
                   max_depth: float = np.inf) -> Cloud:
    """Unproject views ``[S, H, W]`` (z-depth, world poses ``[S, 4, 4]``, intrinsics ``[S, 3, 3]``)
    to one cloud, keeping pixels with confidence >= ``min_confidence`` and depth < ``max_depth``."""
    parts = []
    for i in range(len(depth)):
        mask = (confidence[i] >= min_confidence) & (depth[i] < max_depth)
        pts, idx = unproject_depth(depth[i], c2w[i], K[i], mask=mask, stride=stride)
        parts.append(Cloud(pts, images[i].reshape(-1, 3)[idx], confidence[i].reshape(-1)[idx]))
    return Cloud.concat(parts)

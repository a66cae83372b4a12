"""Camera maths: intrinsics, poses, interpolation and Plücker rays.

Conventions (used everywhere in navcrafter, stored as-is):

* **Poses are camera-to-world** 4x4 matrices ``c2w = [[R, t], [0, 1]]`` in the **OpenCV** camera
  convention: +x right, +y down, +z forward (the viewing direction). ``t`` is the camera centre in
  world coordinates; a world point ``X`` has camera coordinates ``R^T (X - t)``.
* **A scene's world frame is its input camera's frame**: the input photo has ``c2w = I``, so world
  "up" is -y for an upright photo. Units are those of the geometry model (metres for metric models
  and for the simulation backend).
* **Pixels**: pixel ``(row i, col j)`` covers ``[j, j+1) x [i, i+1)``; its centre is
  ``(u, v) = (j + 0.5, i + 0.5)`` (the COLMAP convention). A centred principal point is
  ``cx = W/2, cy = H/2``.
* **Depth** is z-depth (distance along the optical axis), not distance along the ray.
* **Quaternions** are ``(w, x, y, z)``, unit norm.

Arrays are numpy float64 unless stated otherwise; functions accept a leading batch axis where noted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

PluckerConvention = Literal["relative", "ray", "paper"]
PLUCKER_CONVENTIONS: tuple[str, ...] = ("relative", "ray", "paper")
MIN_POSE_SCALE = 1e-6  # below this largest relative translation a clip is a pure rotation: scale 1


# --------------------------------------------------------------------------------------------------
# Intrinsics
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    @classmethod
    def from_fov(cls, fov_x_deg: float, width: int, height: int) -> Intrinsics:
        """Square pixels, centred principal point, horizontal field of view in degrees."""
        if not 0 < fov_x_deg < 180:
            raise ValueError(f"fov_x_deg must be in (0, 180), got {fov_x_deg}")
        f = 0.5 * width / np.tan(np.deg2rad(fov_x_deg) / 2)
        return cls(float(f), float(f), width / 2, height / 2, int(width), int(height))

    @classmethod
    def from_matrix(cls, K: np.ndarray, width: int, height: int) -> Intrinsics:
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_x_deg(self) -> float:
        return float(np.rad2deg(2 * np.arctan(self.width / (2 * self.fx))))

    @property
    def fov_y_deg(self) -> float:
        return float(np.rad2deg(2 * np.arctan(self.height / (2 * self.fy))))

    def crop(self, x0: float, y0: float, width: int, height: int) -> Intrinsics:
        """Intrinsics of the sub-image whose top-left corner is pixel edge ``(x0, y0)``."""
        return Intrinsics(self.fx, self.fy, self.cx - x0, self.cy - y0, int(width), int(height))

    def resize(self, width: int, height: int) -> Intrinsics:
        """Intrinsics after resampling the whole image to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, int(width), int(height))

    def to_dict(self) -> dict[str, float | int]:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                   int(d["width"]), int(d["height"]))


# --------------------------------------------------------------------------------------------------
# Poses
# --------------------------------------------------------------------------------------------------
def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s) ``[..., 4, 4]`` without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """OpenCV camera-to-world pose at ``eye`` looking at ``target``; image "up" follows ``up``.

    ``up`` is the world direction that should appear upwards in the image (camera -y). The default
    suits a scene's world frame (the input camera's OpenCV frame, where up is -y).
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z = z / n
    down = -np.asarray(up, dtype=np.float64)
    x = np.cross(down, z)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x = x / nx
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations (batched), in degrees."""
    R = np.einsum("...ji,...jk->...ik", R_a, R_b)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0)))


def axis_angle_to_matrix(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues' formula."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * Kx + (1 - np.cos(angle_rad)) * (Kx @ Kx)


# --------------------------------------------------------------------------------------------------
# Quaternions and interpolation
# --------------------------------------------------------------------------------------------------
def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix ``[..., 3, 3]`` to unit quaternion ``[..., 4]`` (w, x, y, z), w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    q = np.empty((R.shape[0], 4))
    tr = np.trace(R, axis1=1, axis2=2)
    for i, (m, t) in enumerate(zip(R, tr)):
        if t > 0:
            s = np.sqrt(t + 1.0) * 2
            q[i] = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
            q[i] = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
            q[i] = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
            q[i] = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q.reshape(*batch, 4)


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternion(s) ``[..., 4]`` (w, x, y, z) to rotation matrices ``[..., 3, 3]``."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1)
    return R.reshape(*q.shape[:-1], 3, 3)


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    ``t`` may be a scalar or a 1-D array; returns ``[len(t), 4]`` (or ``[4]`` for a scalar).
    ``t=0`` gives ``q0`` exactly, ``t=1`` gives ``q1`` (or ``-q1``, the same rotation) exactly.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    scalar = np.ndim(t) == 0
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))[:, None]
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 1 - 1e-10:  # (nearly) identical rotations: lerp is exact to rounding
        out = (1 - t) * q0 + t * q1
        out /= np.linalg.norm(out, axis=1, keepdims=True)
    else:
        theta = np.arccos(min(dot, 1.0))
        s = np.sin(theta)
        out = (np.sin((1 - t) * theta) / s) * q0 + (np.sin(t * theta) / s) * q1
    ends = t[:, 0]
    out[ends == 0.0] = q0
    out[ends == 1.0] = q1
    return out[0] if scalar else out


def slerp_vectors(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation of two 3-vectors: direction by great-circle, length linearly."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))[:, None]
    ra, rb = np.linalg.norm(a), np.linalg.norm(b)
    if ra < 1e-12 or rb < 1e-12:
        return (1 - t) * a + t * b
    ua, ub = a / ra, b / rb
    omega = np.arccos(np.clip(np.dot(ua, ub), -1.0, 1.0))
    if omega < 1e-9:
        u = np.broadcast_to(ua, (t.shape[0], 3))
    elif np.pi - omega < 1e-6:
        raise ValueError("slerp_vectors: opposite directions have no unique great circle")
    else:
        u = (np.sin((1 - t) * omega) * ua + np.sin(t * omega) * ub) / np.sin(omega)
    return u * ((1 - t) * ra + t * rb)


def interpolate_poses(c2w_start: np.ndarray, c2w_end: np.ndarray, num: int,
                      centre: np.ndarray | None = None) -> np.ndarray:
    """``num`` poses from start to end (both included): SLERP rotation, positions on an arc.

    With ``centre`` the camera centre moves on the spherical arc around it (radius interpolated
    linearly), as in the paper's SphericalInterpolate; without, it moves on a straight line.
    The first and last poses are the inputs, bit for bit.
    """
    if num < 2:
        raise ValueError(f"interpolate_poses needs num >= 2, got {num}")
    t = np.linspace(0.0, 1.0, num)
    q = slerp(matrix_to_quat(c2w_start[:3, :3]), matrix_to_quat(c2w_end[:3, :3]), t)
    R = quat_wxyz_to_matrix(q)
    p0, p1 = c2w_start[:3, 3], c2w_end[:3, 3]
    if centre is None:
        pos = (1 - t)[:, None] * p0 + t[:, None] * p1
    else:
        c = np.asarray(centre, dtype=np.float64)
        pos = c + slerp_vectors(p0 - c, p1 - c, t)
    out = np.tile(np.eye(4), (num, 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = pos
    out[0], out[-1] = c2w_start, c2w_end
    return out


# --------------------------------------------------------------------------------------------------
# Rays, projection, Plücker embedding
# --------------------------------------------------------------------------------------------------
def pixel_centres(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` grids ``[H, W]`` of pixel centres (``j + 0.5``, ``i + 0.5``)."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return u, v


def camera_directions(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """``K^-1 [u, v, 1]^T`` for every pixel centre: camera-frame directions ``[H, W, 3]``, z = 1."""
    u, v = pixel_centres(height, width)
    K = np.asarray(K, dtype=np.float64)
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def world_rays(c2w: np.ndarray, K: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and (z-normalised, so ``t`` equals z-depth) directions ``[H, W, 3]`` in world."""
    d_cam = camera_directions(K, height, width)
    d = d_cam @ np.asarray(c2w)[:3, :3].T
    o = np.broadcast_to(np.asarray(c2w)[:3, 3], d.shape)
    return o, d


def relative_poses(c2w: np.ndarray, origin: np.ndarray | None = None,
                   scale: float | None = None) -> tuple[np.ndarray, float]:
    """A clip's camera-to-world poses in its own frame, translations scale-normalised (CameraCtrl-style).

    ``c2w``: ``[T, 4, 4]`` world poses. Returns ``(c2w_rel [T, 4, 4], scale)`` with
    ``c2w_rel[i] = inv(origin) @ c2w[i]`` and its translation divided by ``scale``. By default
    ``origin = c2w[0]`` (so ``c2w_rel[0] = I``) and ``scale`` = the largest ``|t_rel|`` over the clip
    when it exceeds ``MIN_POSE_SCALE`` (1e-6), else 1 (a pure rotation). ``scale`` is returned so the
    same normalisation can be applied to other poses (training and inference share it: pass the clip's
    ``origin`` and ``scale`` to express extra poses, e.g. a reference frame, in the clip's frame; their
    ``|t|`` may then exceed 1).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) == 0:
        raise ValueError(f"c2w must be [T, 4, 4] with T >= 1, got {c2w.shape}")
    origin = c2w[0] if origin is None else np.asarray(origin, dtype=np.float64)
    if origin.shape != (4, 4):
        raise ValueError(f"origin must be a [4, 4] camera-to-world pose, got {origin.shape}")
    rel = np.einsum("ij,tjk->tik", invert_pose(origin), c2w)
    if scale is None:
        largest = float(np.linalg.norm(rel[:, :3, 3], axis=-1).max())
        scale = largest if largest > MIN_POSE_SCALE else 1.0
    scale = float(scale)
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale must be a positive number, got {scale}")
    rel[:, :3, 3] /= scale
    return rel, scale


def _plucker_lines(c2w: np.ndarray, Ks: np.ndarray, height: int, width: int, add_t: bool) -> np.ndarray:
    out = np.empty((len(c2w), height, width, 6), dtype=np.float32)
    for i in range(len(c2w)):
        R, t = c2w[i, :3, :3], c2w[i, :3, 3]
        d = camera_directions(Ks[i], height, width) @ R.T
        if add_t:
            d = d + t
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        m = np.cross(np.broadcast_to(t, d.shape), d)
        out[i, ..., :3] = m
        out[i, ..., 3:] = d
    return out


def plucker_rays(c2w: np.ndarray, K: np.ndarray, height: int, width: int,
                 convention: PluckerConvention = "relative", *, origin: np.ndarray | None = None,
                 scale: float | None = None) -> np.ndarray:
    """Per-pixel Plücker embedding ``[T, H, W, 6] = (m, d) = (t x d, d)`` as float32.

    ``c2w``: ``[T, 4, 4]`` (or ``[4, 4]``) world poses; ``K``: ``[T, 3, 3]`` or one ``[3, 3]`` for all frames.

    * ``convention="relative"`` (default; what RealEstate10K/DL3DV camera-control training pipelines do,
      CameraCtrl-style): the poses are first made relative to the clip's first camera and scale-normalised
      (``relative_poses``: ``c2w_rel[i] = inv(c2w[0]) @ c2w[i]``, so frame 0 is the identity, translations
      divided by the clip's largest ``|t_rel|``), then each pixel's true Plücker line is taken:
      ``d = normalise(R K^-1 [u, v, 1]^T)``, ``m = t x d``. The embedding is invariant to where the clip is
      in the world and to its units. ``origin`` / ``scale`` override the clip's own (``c2w[0]`` and its
      scale): rays of extra poses in another clip's frame (``clip_relative_rays``).
    * ``convention="ray"``: the same true Plücker line on the absolute world ``c2w``.
    * ``convention="paper"`` follows the paper's equation literally on the absolute world ``c2w``:
      ``d = normalise(R K^-1 [u, v, 1]^T + t)``, ``m = t x d``. Far from the world origin the ``+ t`` dominates:
      with ``|t| = 10`` the directions span ~1/10 of the field of view and barely move when the camera
      turns, which is why it is no longer the default.

    All three satisfy ``m . d = 0`` and ``|d| = 1``; "ray" and "paper" agree whenever ``t = 0``, and
    "relative" equals "ray" for a clip whose first camera is the world frame and whose scale is 1. The
    camera-control model must be trained and run with one convention; it is recorded in its config
    (``CameraControlConfig.plucker_convention``) and in an exported synthesizer's manifest.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    single = c2w.ndim == 2
    if single:
        c2w = c2w[None]
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
        raise ValueError(f"c2w must be [T, 4, 4] or [4, 4], got {c2w.shape}")
    T = c2w.shape[0]
    K = np.asarray(K, dtype=np.float64)
    Ks = np.broadcast_to(K, (T, 3, 3)) if K.ndim == 2 else K
    if Ks.shape != (T, 3, 3):
        raise ValueError(f"K must be [3,3] or [{T},3,3], got {K.shape}")
    if convention not in PLUCKER_CONVENTIONS:
        raise ValueError(f"unknown Plücker convention {convention!r}; use one of {list(PLUCKER_CONVENTIONS)}")
    if convention == "relative":
        c2w, _ = relative_poses(c2w, origin, scale)
    elif origin is not None or scale is not None:
        raise ValueError(f"origin/scale only apply to the 'relative' convention, not {convention!r} "
                         f"(which embeds absolute world poses)")
    out = _plucker_lines(c2w, Ks, height, width, add_t=convention == "paper")
    return out[0] if single else out


def clip_relative_rays(clip_c2w: np.ndarray, c2w_extra: np.ndarray, K: np.ndarray, height: int, width: int,
                       convention: PluckerConvention = "relative") -> np.ndarray:
    """Rays ``[R, H, W, 6]`` of extra poses ``c2w_extra [R, 4, 4]`` (or ``[4, 4]``) in the embedding frame of the
    clip ``clip_c2w [T, 4, 4]``, i.e. comparable with ``plucker_rays(clip_c2w, K, H, W, convention)`` (both in
    the same world frame).

    For "relative": the clip's first camera is the origin and the clip's scale (``relative_poses(clip_c2w)``)
    normalises the extra translations too (a reference frame outside the clip may then have ``|t| > 1``). "ray"
    and "paper" embed absolute world poses, so the clip does not enter. ``K``: ``[3, 3]`` or ``[R, 3, 3]``.
    """
    c2w_extra = np.asarray(c2w_extra, dtype=np.float64)
    if c2w_extra.ndim == 2:
        c2w_extra = c2w_extra[None]
    if convention != "relative":
        return plucker_rays(c2w_extra, K, height, width, convention)
    clip_c2w = np.asarray(clip_c2w, dtype=np.float64)
    if clip_c2w.ndim == 2:
        clip_c2w = clip_c2w[None]
    _, scale = relative_poses(clip_c2w)
    return plucker_rays(c2w_extra, K, height, width, "relative", origin=clip_c2w[0], scale=scale)


def project(points: np.ndarray, c2w: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points ``[N, 3]`` to pixel coordinates ``[N, 2]`` (u, v) and z-depth ``[N]``."""
    w2c = invert_pose(c2w)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (pc @ np.asarray(K).T)[:, :2] / z[:, None]
    return uv, z


def unproject_depth(depth: np.ndarray, c2w: np.ndarray, K: np.ndarray,
                    mask: np.ndarray | None = None, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Lift a z-depth map ``[H, W]`` to world points.

    Returns ``points [M, 3]`` and the flat pixel indices ``[M]`` (into ``H*W``) they came from.
    Pixels with non-finite or non-positive depth, or outside ``mask``, are dropped.
    """
    H, W = depth.shape
    d = camera_directions(K, H, W)
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= mask
    if stride > 1:
        sub = np.zeros_like(valid)
        sub[::stride, ::stride] = True
        valid &= sub
    idx = np.flatnonzero(valid)
    pc = d.reshape(-1, 3)[idx] * depth.reshape(-1)[idx, None]
    pw = pc @ np.asarray(c2w)[:3, :3].T + np.asarray(c2w)[:3, 3]
    return pw, idx


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + t`` between point sets ``[N, 3]`` (Umeyama 1991)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama needs two [N,3] arrays of equal shape, got {src.shape}, {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def estimated_clip_cameras(planned: np.ndarray, view_index: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """Cameras of every frame of a clip from the estimates of some (``tasks.readers.camera_path`` with estimated
    cameras): the correction ``E_i = est_i @ inv(plan_i)`` is known at frame 0 (identity) and at the estimated
    frames, and interpolated in between (rotation by SLERP, translation linearly), then applied to the plan."""
    T = len(planned)
    known = {0: np.eye(4)}
    for j, i in enumerate(np.asarray(view_index)):
        known[int(i)] = np.asarray(estimated[j], dtype=np.float64) @ invert_pose(planned[int(i)])
    at = sorted(known)
    out = np.empty_like(planned)
    for i in range(T):
        if i in known:
            out[i] = known[i] @ planned[i]
            continue
        hi = next((a for a in at if a > i), None)
        lo = max(a for a in at if a < i)
        if hi is None:
            corr = known[lo]
        else:
            corr = interpolate_poses(known[lo], known[hi], hi - lo + 1)[i - lo]
        out[i] = corr @ planned[i]
    return out

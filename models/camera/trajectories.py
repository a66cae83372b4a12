"""Camera trajectories for rendering: presets about a framed scene, and camera files from other tools.

Every pose is an OpenCV camera-to-world matrix (``cameras.py``: +x right, +y down, +z forward).

**Presets** (``PRESETS``; ``preset_trajectory(name, frame, num, ...)``) are pure functions of a :class:`Frame`
(the start camera, the point it looks at and the world's up direction) and return a :class:`Trajectory`:
``c2w`` [N, 4, 4] and a per-frame focal-length factor (1 except for ``zoom``). Frame 0 is the start camera
itself. Signs: positive ``degrees`` turn or move the camera to its right (orbit, arc, pan, look-around) or up
(tilt); positive ``amount`` moves it in (dolly), right (truck) or up (pedestal); ``amount`` is a fraction of
the start camera's distance to the target, except for ``zoom`` (the final focal-length factor).

=============  =======================================================================  ===================
preset         motion                                                                   default
=============  =======================================================================  ===================
orbit          about the vertical axis through the target, looking at it                degrees 360
arc            a partial orbit                                                          degrees 60
dolly          along the view axis (in: amount > 0)                                     amount 0.5
pan            turns about the camera's own vertical (y) axis, position fixed           degrees 30
tilt           turns about the camera's x axis (up: degrees > 0)                        degrees 20
zoom           focal length from 1x to ``amount``x, pose fixed                          amount 2
truck          sideways along the camera's x axis (right: amount > 0)                   amount 0.5
pedestal       along the camera's up axis (-y; up: amount > 0)                          amount 0.25
spiral         a widening circle in the camera's image plane, looking at the target     amount 0.2, 2 turns
lookaround     camera fixed, turning all around the vertical axis                       degrees 360
=============  =======================================================================  ===================

A full turn (``|degrees|`` a multiple of 360) does not repeat frame 0 at its end, so the video loops.
``frame_bounds`` frames a bare point set (a PLY's Gaussians): a robust bounding box, a start camera outside it
looking at its centre from the distance at which the box's bounding sphere fills the narrower field of view.

**Camera files** (``read_camera_file``; one parser per format, each returning a :class:`CameraFile`):

* RealEstate10K pose ``.txt`` (``read_re10k``): a URL line, then per frame ``timestamp fx fy cx cy k1 k2`` and
  the world-to-camera 3x4 matrix row-major, OpenCV axes; intrinsics normalised by the image width/height;
* nerfstudio / DL3DV ``transforms.json`` (``read_transforms``): ``frames[i].transform_matrix``, camera-to-world
  in OpenGL axes (+x right, +y up, +z back), converted by flipping the camera's y and z axes; intrinsics
  ``fl_x, fl_y, cx, cy, w, h`` at the top level or per frame (frames in ``file_path`` order, as nerfstudio);
* nerfstudio ``camera_path.json`` (``read_camera_path``): ``camera_path[i].camera_to_world`` (16 numbers,
  row-major, OpenGL axes) and ``fov`` (vertical, degrees) per camera, ``render_width/height`` (square pixels).
* plain camera-to-world matrices (``read_matrices``): a ``.npy`` array ``[N, 4, 4]`` (or ``[N, 3, 4]``), or a
  ``.json`` list of N 4x4 (or 3x4) matrices, or an object ``{"c2w": [...], "convention": "opencv"|"opengl"}``;
  the camera axes are OpenCV's unless the file (JSON ``convention``) or the caller (``convention=``) says OpenGL.

A malformed file raises ``ValueError`` naming the file and the line or JSON field.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from navcrafter.models.camera.camerafiles import read_nerfstudio_transforms, read_re10k_cameras
from navcrafter.models.camera.cameras import Intrinsics, axis_angle_to_matrix, invert_pose, look_at

WORLD_UP = (0.0, -1.0, 0.0)  # a scene's world frame is its input camera's: up is -y
GL_CV_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL <-> OpenCV camera axes (its own inverse)


# --------------------------------------------------------------------------------------------------
# Frames and trajectories
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Frame:
    """What a preset moves about: the start camera ``c2w`` [4, 4], the ``target`` [3] it looks at (or near) and
    the world's ``up`` direction (default: the start camera's up, -y)."""

    c2w: np.ndarray
    target: np.ndarray
    up: np.ndarray | None = None

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise ValueError(f"Frame.c2w must be a finite 4x4 pose, got shape {c2w.shape}")
        up = -c2w[:3, 1] if self.up is None else np.asarray(self.up, dtype=np.float64)
        if up.shape != (3,) or np.linalg.norm(up) < 1e-12:
            raise ValueError(f"Frame.up must be a non-zero 3-vector, got {up}")
        object.__setattr__(self, "c2w", c2w)
        object.__setattr__(self, "target", np.asarray(self.target, dtype=np.float64).reshape(3))
        object.__setattr__(self, "up", up / np.linalg.norm(up))
        if self.distance < 1e-9:
            raise ValueError("Frame: the start camera sits on its target")

    @property
    def eye(self) -> np.ndarray:
        return self.c2w[:3, 3]

    @property
    def distance(self) -> float:
        """From the start camera to the target."""
        return float(np.linalg.norm(self.target - self.eye))


@dataclass(frozen=True)
class Trajectory:
    """Poses ``c2w`` [N, 4, 4] (OpenCV) and per-frame focal-length factors ``focal_scale`` [N]."""

    c2w: np.ndarray
    focal_scale: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, dtype=np.float64)
        if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
            raise ValueError(f"a trajectory's c2w must be [N, 4, 4], got {c2w.shape}")
        scale = np.ones(len(c2w)) if self.focal_scale is None else np.asarray(self.focal_scale, dtype=np.float64)
        if scale.shape != (len(c2w),):
            raise ValueError(f"focal_scale must be [{len(c2w)}], got {scale.shape}")
        object.__setattr__(self, "c2w", c2w)
        object.__setattr__(self, "focal_scale", scale)

    def __len__(self) -> int:
        return len(self.c2w)

    def intrinsics(self, base: Intrinsics) -> np.ndarray:
        """K [N, 3, 3]: ``base`` with its focal lengths scaled per frame."""
        K = np.repeat(base.K[None], len(self), axis=0)
        K[:, 0, 0] *= self.focal_scale
        K[:, 1, 1] *= self.focal_scale
        return K


def _horizontal(up: np.ndarray) -> np.ndarray:
    """A unit direction perpendicular to ``up``: world +z (a camera's forward) projected, else +x."""
    for d in ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0)):
        h = np.asarray(d) - np.dot(d, up) * up
        if np.linalg.norm(h) > 1e-6:
            return h / np.linalg.norm(h)
    raise AssertionError("unreachable")


def robust_bounds(points: np.ndarray, opacities: np.ndarray | None = None, *,
                  percentiles: tuple[float, float] = (2, 98), min_opacity: float = 0.05,
                  min_points: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` [3]: per-axis percentiles of ``points`` [N, 3], over the points of opacity >= ``min_opacity``
    when at least ``max(min_points, 1 %)`` of them are (else over all): stray and transparent Gaussians do not
    stretch the box."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    finite = np.isfinite(pts).all(axis=1)
    if not finite.any():
        raise ValueError("robust_bounds: no finite points")
    if opacities is not None:
        op = np.asarray(opacities, dtype=np.float64).reshape(-1)
        if len(op) != len(pts):
            raise ValueError(f"robust_bounds: {len(pts)} points but {len(op)} opacities")
        keep = finite & (op >= min_opacity)
        if keep.sum() >= max(min_points, 0.01 * finite.sum()):
            finite = keep
    pts = pts[finite]
    lo, hi = np.percentile(pts, percentiles, axis=0)
    return lo, hi


def frame_bounds(lo: np.ndarray, hi: np.ndarray, intrinsics: Intrinsics, up: np.ndarray = WORLD_UP,
                 *, min_radius: float = 1e-3) -> Frame:
    """A start camera that looks at the centre of the box ``[lo, hi]`` horizontally (along world +z projected
    perpendicular to ``up``), from the distance at which the box's bounding sphere just fits the narrower field
    of view of ``intrinsics``."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, min_radius)
    half = np.deg2rad(min(intrinsics.fov_x_deg, intrinsics.fov_y_deg)) / 2
    distance = radius / np.sin(half)
    eye = centre - distance * _horizontal(up)
    return Frame(look_at(eye, centre, up), centre, up)


# --------------------------------------------------------------------------------------------------
# Presets
# --------------------------------------------------------------------------------------------------
def _angles(num: int, degrees: float) -> np.ndarray:
    """Radians from 0 to ``degrees``: both ends for a partial turn, without the end for a full one (a loop)."""
    if num < 1:
        raise ValueError(f"a trajectory needs at least 1 frame, got {num}")
    full = degrees != 0 and abs(degrees) % 360 < 1e-9
    t = np.arange(num) / num if full else np.linspace(0.0, 1.0, num) if num > 1 else np.zeros(1)
    return np.deg2rad(degrees) * t


def _fractions(num: int) -> np.ndarray:
    if num < 1:
        raise ValueError(f"a trajectory needs at least 1 frame, got {num}")
    return np.linspace(0.0, 1.0, num) if num > 1 else np.zeros(1)


def _rotate_about(c2w: np.ndarray, axis: np.ndarray, point: np.ndarray, angle: float) -> np.ndarray:
    """The rigid motion "rotate by ``angle`` about the world line through ``point`` along ``axis``" applied to
    a pose."""
    R = axis_angle_to_matrix(axis, angle)
    out = np.eye(4)
    out[:3, :3] = R @ c2w[:3, :3]
    out[:3, 3] = point + R @ (c2w[:3, 3] - point)
    return out


def _local_rotation(c2w: np.ndarray, axis: tuple[float, float, float], angle: float) -> np.ndarray:
    """Turn a pose about one of its own axes (position fixed)."""
    out = c2w.copy()
    out[:3, :3] = c2w[:3, :3] @ axis_angle_to_matrix(np.asarray(axis), angle)
    return out


def _translated(c2w: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    out = np.repeat(c2w[None], len(offsets), axis=0)
    out[:, :3, 3] += offsets
    return out


def orbit(frame: Frame, num: int, degrees: float = 360.0) -> Trajectory:
    """About the vertical axis (``frame.up``) through the target; ``degrees > 0``: the camera moves right."""
    return Trajectory(np.stack([_rotate_about(frame.c2w, frame.up, frame.target, a) for a in _angles(num, degrees)]))


def arc(frame: Frame, num: int, degrees: float = 60.0) -> Trajectory:
    """A partial orbit."""
    return orbit(frame, num, degrees)


def dolly(frame: Frame, num: int, amount: float = 0.5) -> Trajectory:
    """Along the view axis by ``amount`` x the distance to the target (> 0: in, < 0: out)."""
    if amount >= 1:
        raise ValueError(f"dolly amount {amount} would reach the target; use less than 1")
    forward = frame.c2w[:3, 2]
    return Trajectory(_translated(frame.c2w, _fractions(num)[:, None] * amount * frame.distance * forward))


def truck(frame: Frame, num: int, amount: float = 0.5) -> Trajectory:
    """Sideways along the camera's x axis by ``amount`` x the distance to the target (> 0: right)."""
    right = frame.c2w[:3, 0]
    return Trajectory(_translated(frame.c2w, _fractions(num)[:, None] * amount * frame.distance * right))


def pedestal(frame: Frame, num: int, amount: float = 0.25) -> Trajectory:
    """Along the camera's up axis (-y) by ``amount`` x the distance to the target (> 0: up)."""
    up = -frame.c2w[:3, 1]
    return Trajectory(_translated(frame.c2w, _fractions(num)[:, None] * amount * frame.distance * up))


def pan(frame: Frame, num: int, degrees: float = 30.0) -> Trajectory:
    """Turn about the camera's vertical (y, image-down) axis; ``degrees > 0``: to the right."""
    return Trajectory(np.stack([_local_rotation(frame.c2w, (0.0, 1.0, 0.0), a) for a in _angles(num, degrees)]))


def tilt(frame: Frame, num: int, degrees: float = 20.0) -> Trajectory:
    """Turn about the camera's x axis; ``degrees > 0``: up."""
    return Trajectory(np.stack([_local_rotation(frame.c2w, (1.0, 0.0, 0.0), a) for a in _angles(num, degrees)]))


def zoom(frame: Frame, num: int, amount: float = 2.0) -> Trajectory:
    """Focal length from 1x to ``amount`` x (geometrically), pose fixed (> 1: in)."""
    if amount <= 0:
        raise ValueError(f"zoom factor must be positive, got {amount}")
    return Trajectory(np.repeat(frame.c2w[None], num, axis=0), amount ** _fractions(num))


def spiral(frame: Frame, num: int, amount: float = 0.2, turns: float = 2.0) -> Trajectory:
    """A circle in the camera's image plane widening from 0 to ``amount`` x the distance to the target over
    ``turns`` turns (first right, then up), re-aimed at the target."""
    t = _fractions(num)
    theta = 2 * np.pi * turns * t
    r = amount * frame.distance * t
    x, up_cam = frame.c2w[:3, 0], -frame.c2w[:3, 1]
    eyes = frame.eye + r[:, None] * (np.cos(theta)[:, None] * x + np.sin(theta)[:, None] * up_cam)
    return Trajectory(np.stack([_reaimed(frame, e) for e in eyes]))


def _reaimed(frame: Frame, eye: np.ndarray) -> np.ndarray:
    """The start pose moved to ``eye`` and turned as a look-at camera turns (its offset from an exact look-at at
    the target is kept, so an ``eye`` at the start gives the start pose)."""
    start = look_at(frame.eye, frame.target, frame.up)
    return look_at(eye, frame.target, frame.up) @ invert_pose(start) @ frame.c2w


def look_around(frame: Frame, num: int, degrees: float = 360.0) -> Trajectory:
    """Camera fixed, turning about the vertical axis (``frame.up``) through itself; ``degrees > 0``: right."""
    return Trajectory(np.stack([_rotate_about(frame.c2w, -frame.up, frame.eye, a) for a in _angles(num, degrees)]))


@dataclass(frozen=True)
class Preset:
    fn: Callable[..., Trajectory]
    takes: str  # "degrees" or "amount": which of the two options sizes the motion
    help: str


PRESETS: dict[str, Preset] = {
    "orbit": Preset(orbit, "degrees", "around the target (360)"),
    "arc": Preset(arc, "degrees", "a partial orbit (60)"),
    "dolly": Preset(dolly, "amount", "in along the view axis (0.5 of the distance)"),
    "pan": Preset(pan, "degrees", "turn right about the camera's vertical axis (30)"),
    "tilt": Preset(tilt, "degrees", "turn up (20)"),
    "zoom": Preset(zoom, "amount", "focal length x2"),
    "truck": Preset(truck, "amount", "sideways to the right (0.5 of the distance)"),
    "pedestal": Preset(pedestal, "amount", "up (0.25 of the distance)"),
    "spiral": Preset(spiral, "amount", "a widening circle, 2 turns (radius 0.2 of the distance)"),
    "lookaround": Preset(look_around, "degrees", "camera fixed, looking all around (360)"),
}


def preset_trajectory(name: str, frame: Frame, num: int, *, degrees: float | None = None,
                      amount: float | None = None) -> Trajectory:
    """The preset ``name`` (see ``PRESETS``) with its default size unless ``degrees`` / ``amount`` is given
    (the one that does not apply to the preset is an error)."""
    if name not in PRESETS:
        raise ValueError(f"unknown trajectory preset {name!r}; use one of {', '.join(PRESETS)} or a camera file")
    preset = PRESETS[name]
    given = {"degrees": degrees, "amount": amount}
    other = "amount" if preset.takes == "degrees" else "degrees"
    if given[other] is not None:
        raise ValueError(f"the {name} preset is sized by {preset.takes}, not {other}")
    kwargs = {} if given[preset.takes] is None else {preset.takes: float(given[preset.takes])}
    return preset.fn(frame, num, **kwargs)


# --------------------------------------------------------------------------------------------------
# Camera files
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraFile:
    """Poses read from a camera file: ``c2w`` [N, 4, 4] (OpenCV, in the file's world), and when the file has
    them, ``K`` [N, 3, 3] for images of ``size`` (width, height) pixels, or normalised by the image width and
    height when ``size`` is None (RealEstate10K)."""

    path: str
    format: str
    c2w: np.ndarray
    K: np.ndarray | None = None
    size: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.c2w)

    def intrinsics_at(self, width: int, height: int) -> np.ndarray | None:
        """K [N, 3, 3] for images of ``width`` x ``height`` (the whole image resampled), or None."""
        if self.K is None:
            return None
        sx, sy = (width, height) if self.size is None else (width / self.size[0], height / self.size[1])
        K = self.K.copy()
        K[:, 0] *= sx
        K[:, 1] *= sy
        return K


def _json(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"camera file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: the JSON must be an object, got {type(doc).__name__}")
    return doc


def read_re10k(path: str | Path) -> CameraFile:
    """A RealEstate10K pose file (``camerafiles.read_re10k_cameras``)."""
    cams = read_re10k_cameras(path)
    K = np.zeros((len(cams.w2c), 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2] = cams.intrinsics.T
    K[:, 2, 2] = 1.0
    return CameraFile(str(path), "re10k", invert_pose(cams.w2c), K, None)


def read_transforms(path: str | Path) -> CameraFile:
    """A nerfstudio / DL3DV ``transforms.json`` (``camerafiles.read_nerfstudio_transforms``), frames in
    ``file_path`` order. Each frame's intrinsics are expressed at the first frame's size; a frame needs
    ``w``/``h`` or ``cx``/``cy`` to know its size."""
    frames, _ = read_nerfstudio_transforms(path)
    Ks, size = [], None
    for i, f in enumerate(frames):
        w = f.w if f.w is not None else (round(2 * f.cx) if f.cx is not None else None)
        h = f.h if f.h is not None else (round(2 * f.cy) if f.cy is not None else None)
        if w is None or h is None or w <= 0 or h <= 0:
            raise ValueError(f"{path}: frames[{i}] ({f.file_path}): the image size is unknown; give 'w' and 'h' "
                             "(top level or per frame)")
        cx = f.cx if f.cx is not None else w / 2
        cy = f.cy if f.cy is not None else h / 2
        size = size or (int(w), int(h))
        sx, sy = size[0] / w, size[1] / h
        Ks.append([[f.fx * sx, 0.0, cx * sx], [0.0, f.fy * sy, cy * sy], [0.0, 0.0, 1.0]])
    c2w = np.stack([f.c2w_gl for f in frames]) @ GL_CV_FLIP
    return CameraFile(str(path), "transforms", c2w, np.asarray(Ks, dtype=np.float64), size)


def read_camera_path(path: str | Path) -> CameraFile:
    """A nerfstudio ``camera_path.json`` (the viewer's render path): perspective cameras only."""
    path = Path(path)
    doc = _json(path)
    cams = doc.get("camera_path")
    if not isinstance(cams, list) or not cams:
        raise ValueError(f"{path}: 'camera_path' must be a non-empty list of cameras")
    try:
        width, height = int(doc["render_width"]), int(doc["render_height"])
    except KeyError as exc:
        raise ValueError(f"{path}: missing field {exc.args[0]!r} (the render size in pixels)") from None
    except (TypeError, ValueError):
        raise ValueError(f"{path}: 'render_width' / 'render_height' must be integers") from None
    if width <= 0 or height <= 0:
        raise ValueError(f"{path}: render size must be positive, got {width}x{height}")
    kind = str(doc.get("camera_type", "perspective")).lower()
    if kind != "perspective":
        raise ValueError(f"{path}: camera_type {kind!r} is not supported; only 'perspective' cameras render")
    c2w, Ks = [], []
    for i, cam in enumerate(cams):
        where = f"{path}: camera_path[{i}]"
        if not isinstance(cam, dict):
            raise ValueError(f"{where}: must be an object with 'camera_to_world' and 'fov'")
        try:
            M = np.asarray(cam["camera_to_world"], dtype=np.float64).reshape(-1)
        except KeyError:
            raise ValueError(f"{where}: missing field 'camera_to_world' (16 numbers, row-major)") from None
        except (TypeError, ValueError):
            raise ValueError(f"{where}.camera_to_world: not a list of numbers") from None
        if M.size == 12:
            M = np.concatenate([M, [0.0, 0.0, 0.0, 1.0]])
        if M.size != 16 or not np.isfinite(M).all():
            raise ValueError(f"{where}.camera_to_world: expected 16 finite numbers, got {M.size}")
        M = M.reshape(4, 4)
        _check_pose(M, f"{where}.camera_to_world")
        try:
            fov = float(cam["fov"])
        except KeyError:
            raise ValueError(f"{where}: missing field 'fov' (vertical field of view, degrees)") from None
        except (TypeError, ValueError):
            raise ValueError(f"{where}.fov: not a number") from None
        if not 0 < fov < 180:
            raise ValueError(f"{where}.fov: must be in (0, 180) degrees, got {fov}")
        f = 0.5 * height / np.tan(np.deg2rad(fov) / 2)  # square pixels, as nerfstudio renders it
        c2w.append(M @ GL_CV_FLIP)
        Ks.append([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return CameraFile(str(path), "camera_path", np.stack(c2w), np.asarray(Ks), (width, height))


def _check_pose(M: np.ndarray, where: str, tol: float = 1e-2) -> None:
    R = M[:3, :3]
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ValueError(f"{where}: last row is {M[3].tolist()}, expected [0, 0, 0, 1]")
    if np.abs(R.T @ R - np.eye(3)).max() > tol or np.linalg.det(R) < 0:
        raise ValueError(f"{where}: the 3x3 block is not a rotation (R^T R != I or det < 0)")


CONVENTIONS = ("opencv", "opengl")


def read_matrices(path: str | Path, convention: str = "opencv") -> CameraFile:
    """Plain camera-to-world matrices (``.npy`` or ``.json``, see the module docstring) in the camera axes of
    ``convention`` (a JSON object's own ``convention`` field wins), returned in OpenCV axes."""
    path = Path(path)
    where = str(path)
    if path.suffix.lower() == ".npy":
        try:
            M = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable .npy array ({exc})") from None
    else:
        doc = json.loads(path.read_text()) if path.is_file() else None
        if isinstance(doc, dict):
            if "c2w" not in doc:
                raise ValueError(f"{path}: a JSON object of matrices needs the field 'c2w' (a list of 4x4 "
                                 f"camera-to-world matrices); its fields are {sorted(doc)[:10]}")
            convention = str(doc.get("convention", convention)).lower()
            doc, where = doc["c2w"], f"{path}: c2w"
        try:
            M = np.asarray(doc, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: not a list of numeric matrices") from None
    if convention not in CONVENTIONS:
        raise ValueError(f"{path}: convention {convention!r} must be one of {', '.join(CONVENTIONS)}")
    M = np.asarray(M, dtype=np.float64)
    if M.ndim != 3 or M.shape[1:] not in ((4, 4), (3, 4)) or len(M) == 0:
        raise ValueError(f"{where}: expected N camera-to-world matrices of shape [N, 4, 4] or [N, 3, 4], got "
                         f"shape {list(M.shape)}")
    if M.shape[1] == 3:
        M = np.concatenate([M, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(M), 1, 1))], axis=1)
    for i, m in enumerate(M):
        if not np.isfinite(m).all():
            raise ValueError(f"{where}[{i}]: not finite")
        _check_pose(m, f"{where}[{i}]")
    if convention == "opengl":
        M = M @ GL_CV_FLIP
    return CameraFile(str(path), f"matrices ({convention})", M, None, None)


CAMERA_FILE_FORMATS: dict[str, Callable[[str | Path], CameraFile]] = {
    "re10k": read_re10k,
    "transforms": read_transforms,
    "camera_path": read_camera_path,
    "matrices": read_matrices,
}


def camera_file_format(path: str | Path) -> str:
    """Which parser reads ``path``: ``.txt`` is RealEstate10K; a JSON with ``camera_path`` is nerfstudio's
    render path, one with ``frames`` a ``transforms.json``."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"camera file {path} does not exist")
    if path.suffix.lower() == ".txt":
        return "re10k"
    if path.suffix.lower() == ".npy":
        return "matrices"
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
        if isinstance(doc, list) or (isinstance(doc, dict) and "c2w" in doc):
            return "matrices"
        if not isinstance(doc, dict):
            raise ValueError(f"{path}: the JSON must be an object or a list of matrices, got {type(doc).__name__}")
        if "camera_path" in doc:
            return "camera_path"
        if "frames" in doc:
            return "transforms"
        raise ValueError(f"{path}: neither a nerfstudio camera_path.json (field 'camera_path'), a transforms.json "
                         f"(field 'frames') nor camera-to-world matrices (a list, or field 'c2w'); its fields are "
                         f"{sorted(doc)[:10]}")
    raise ValueError(f"{path}: unknown camera file type {path.suffix!r}; give a RealEstate10K .txt, a "
                     "transforms.json, a nerfstudio camera_path.json or camera-to-world matrices (.npy / .json)")


def read_camera_file(path: str | Path, convention: str = "opencv") -> CameraFile:
    """Parse any supported camera file (format chosen by ``camera_file_format``); ``convention``: the camera axes
    of plain matrices (the other formats state their own)."""
    fmt = camera_file_format(path)
    return read_matrices(path, convention) if fmt == "matrices" else CAMERA_FILE_FORMATS[fmt](path)


def rebase_path(c2w: np.ndarray, start: np.ndarray) -> np.ndarray:
    """A camera path re-based on its first camera and placed at ``start``: ``start @ inv(c2w[0]) @ c2w``
    (``navcrafter render --relative``: a camera file's motion from the start view)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return np.asarray(start, dtype=np.float64) @ invert_pose(c2w[0]) @ c2w

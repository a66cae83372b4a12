"""A user's camera path in place of the planner (``plan.trajectory``; ``explore --trajectory``).

Each iteration ``k`` takes entry ``(k - 1) mod len(plan.trajectory)``, which is either

* a **preset** ``NAME[:SIZE]`` of ``models/camera/trajectories.py`` (orbit, arc, dolly, pan, tilt, truck, pedestal,
  spiral, lookaround; ``SIZE`` is the preset's degrees or amount, e.g. ``arc:-45``, ``dolly:0.3``), started at the
  iteration's current camera and aimed at the scene centre ``o`` (the planner's), with the world's up (-y of the
  input camera). Amounts are fractions of the distance to ``o``, so presets are scaled to the scene by its initial
  geometry. ``zoom`` is refused: a clip has one focal length;
* a **camera file** (RealEstate10K ``.txt``, ``transforms.json``, nerfstudio ``camera_path.json``, or plain
  camera-to-world matrices ``.npy`` / ``.json`` in the axes of ``plan.trajectory_convention``). The rule: poses are
  taken **relative to the file's first camera** (``inv(F_0) F_i``), their translations scaled so that **the farthest
  camera lies ``plan.trajectory_extent`` x the distance from the current camera to ``o``** from the first (the
  file's own units when ``trajectory_extent`` is 0), resampled to ``synthesis.num_frames`` poses evenly spaced over
  the file's frames (positions linear, rotations slerp), and composed onto the current camera.

The path is then checked by the collision detector G of the collision-aware planner (``planners.CollisionDetector``:
clearance r_safe plus the follow error, and seen free space). A colliding path is kept, with a warning naming the
frames and their clearance, unless ``plan.trajectory_repair`` is set: then CollisionOptimization repairs it (same
end poses) when it can, and the warning says when it cannot.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from navcrafter.models.camera import trajectories as tr
from navcrafter.models.camera.cameras import invert_pose

REFUSED_PRESETS = {"zoom": "a clip has one focal length; use dolly to move closer"}


@dataclass(frozen=True)
class TrajectorySpec:
    """One entry of ``plan.trajectory``: a preset with its size, or a camera file."""

    text: str
    preset: str | None = None
    size: float | None = None
    path: str | None = None


def parse_spec(text: str) -> TrajectorySpec:
    """``NAME[:SIZE]`` of a preset, or the path of an existing camera file (checked here, so a bad entry fails
    before any work). Raises ``ValueError`` naming the entry."""
    text = str(text).strip()
    name, _, size = text.partition(":")
    if name in tr.PRESETS and not Path(text).exists():
        if name in REFUSED_PRESETS:
            raise ValueError(f"trajectory {text!r}: the {name} preset cannot drive exploration "
                             f"({REFUSED_PRESETS[name]})")
        try:
            value = float(size) if size else None
        except ValueError:
            raise ValueError(f"trajectory {text!r}: SIZE after ':' must be a number (the preset's "
                             f"{tr.PRESETS[name].takes})") from None
        return TrajectorySpec(text, preset=name, size=value)
    if not Path(text).is_file():
        names = ", ".join(p for p in tr.PRESETS if p not in REFUSED_PRESETS)
        raise ValueError(f"trajectory {text!r} is neither a preset NAME[:SIZE] ({names}) nor an existing camera file")
    tr.read_camera_file(text)  # a file that is not a trajectory fails here, naming the line or field
    return TrajectorySpec(text, path=str(Path(text).resolve()))


def resample(c2w: np.ndarray, num: int) -> np.ndarray:
    """``num`` poses evenly spaced over the frames of ``c2w`` [N, 4, 4]: positions linear, rotations slerp."""
    from scipy.spatial.transform import Rotation, Slerp

    c2w = np.asarray(c2w, dtype=np.float64)
    if len(c2w) == num:
        return c2w.copy()
    if len(c2w) == 1:
        return np.repeat(c2w, num, axis=0)
    t_in = np.linspace(0.0, 1.0, len(c2w))
    t = np.linspace(0.0, 1.0, num)
    out = np.tile(np.eye(4), (num, 1, 1))
    out[:, :3, :3] = Slerp(t_in, Rotation.from_matrix(c2w[:, :3, :3]))(t).as_matrix()
    for j in range(3):
        out[:, j, 3] = np.interp(t, t_in, c2w[:, j, 3])
    return out


@dataclass
class UserPath:
    trajectory: np.ndarray  # [T, 4, 4] world c2w, frame 0 = the current camera
    source: dict = field(default_factory=dict)  # what made it (stored in the plan step's attrs)


def user_path(spec: TrajectorySpec, current: np.ndarray, centre: np.ndarray, num: int, *, extent: float,
              convention: str = "opencv") -> UserPath:
    """The path of ``spec`` from the ``current`` camera, ``num`` poses (see the module docstring)."""
    current = np.asarray(current, dtype=np.float64)
    d = float(np.linalg.norm(np.asarray(centre) - current[:3, 3]))
    if spec.preset is not None:
        preset = tr.PRESETS[spec.preset]
        kwargs = {} if spec.size is None else {preset.takes: spec.size}
        frame = tr.Frame(current, np.asarray(centre), up=tr.WORLD_UP)
        path = tr.preset_trajectory(spec.preset, frame, num, **kwargs)
        return UserPath(path.c2w, {"kind": "preset", "preset": spec.preset, preset.takes: spec.size,
                                   "distance_to_centre": d})
    cam = tr.read_camera_file(spec.path, convention)
    rel = np.einsum("ij,njk->nik", invert_pose(cam.c2w[0]), cam.c2w)
    far = float(np.linalg.norm(rel[:, :3, 3], axis=1).max())
    scale = 1.0
    if extent > 0:
        if far < 1e-12:
            scale = 1.0  # the camera only turns: nothing to scale
        else:
            scale = extent * d / far
    rel[:, :3, 3] *= scale
    traj = np.einsum("ij,njk->nik", current, resample(rel, num))
    traj[0] = current
    digest = hashlib.sha256(Path(spec.path).read_bytes()).hexdigest()
    return UserPath(traj, {"kind": "file", "path": spec.path, "format": cam.format, "sha256": digest,
                           "file_poses": len(cam), "scale": scale, "file_extent": far, "distance_to_centre": d})


def trajectory_spec(entries: list[str], k: int) -> TrajectorySpec:
    """The entry iteration ``k`` (1-based) takes."""
    return parse_spec(entries[(k - 1) % len(entries)])

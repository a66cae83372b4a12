"""Simulation data engine: procedural scenes rendered along exact camera paths, written as dataset files.

``write_dataset(out, kind, sequences=..., frames=..., resolution=..., seed=...)`` renders ``sequences``
sequences of ``frames`` frames each and writes them in the **on-disk format the readers of
``schemas/datasets`` read** (``kind="re10k"``: RealEstate10K, ``kind="dl3dv"``: DL3DV nerfstudio), so
``open_dataset(kind, out, ...)`` (RealEstate10K: with ``split=None``, or ``split=`` as given here) reads the
exact cameras back (up to float64 rounding of the normalised intrinsics and of the world-to-camera inversion).
It stands in for the real datasets where they cannot be downloaded (tests, CPU benchmarks of camera-control
training) and adds what they lack: the true depth of every frame.

Layouts (what the readers expect; see their module docstrings)::

    kind="re10k"  <out>[/<split>]/<seq>.txt                 URL line ("simulation://..."), then per frame
                                                            "timestamp_us fx/W fy/H cx/W cy/H 0 0" + the
                                                            3x4 world-to-camera matrix (OpenCV), row-major
                  <out>[/<split>]/<seq>/<timestamp_us>.png  the frame (timestamps: 30 fps, frame i at
                                                            round(i * 1e6 / 30) us)
    kind="dl3dv"  <out>/<seq>/transforms.json               nerfstudio: global w, h, fl_x, fl_y, cx, cy,
                                                            camera_model "OPENCV"; per frame file_path
                                                            "images/frame_00001.png" (1-based) and the
                                                            OpenGL camera-to-world transform_matrix
                  <out>/<seq>/images/frame_00001.png        the frames
    both          <out>/simulation.json                     provenance: the SIMULATION label and, per sequence,
                                                            the scene spec (kind, seed, generator version),
                                                            trajectory kind, field of view, the exact pixel
                                                            intrinsics "K" and OpenCV camera-to-world "c2w"
                                                            (scene frame) of every frame

**Depth extension** (``depth=True``; the real datasets have none): the z-depth of every frame (distance along
the optical axis, in dataset units, i.e. the scene's metres, ``0`` where no surface was hit: the sky of
``street`` scenes) is written next to its image as ``<image stem>.depth.npy``, float32 ``[H, W]`` of the
image's own size (``<seq>/<timestamp_us>.depth.npy``, ``images/frame_00001.depth.npy``). The readers ignore
these files (they list images by extension only); ``tasks/training/clips.py`` reads them for the point-cloud
render conditioning.

Sequences, all determined by ``seed`` (sequence ``i`` draws from ``default_rng([seed, i])``, so a sequence
does not depend on how many are written, nor on ``kind``): scene kind ``scene_kinds[i % len(scene_kinds)]``,
trajectory ``trajectories[i % len(trajectories)]``, scene seed, field of view (the scene's input-photo field
of view +-5 deg) and the trajectory's parameters drawn from the generator. World frame: the scene's
ground-truth frame (z up, metres); the first frame is the scene's input-photo pose. Trajectories (``frames``
poses spanning the whole sequence; ``L`` is the free distance ahead of the first camera, capped to
[0.5, 12] m, which sets their scale):

* ``orbit``: around a vertical axis through a centre 0.6-0.9 L ahead, 25-60 deg of azimuth, slight height
  change, looking at the centre;
* ``dolly``: straight forward or back along the viewing axis (with a little sideways drift), 0.3-0.6 L,
  eased, orientation fixed;
* ``pan``: rotation in place, 25-70 deg of yaw and up to +-12 deg of pitch;
* ``nbv``: a next-best-view-like path, a smooth random walk (C1 cubic curve through 4 random waypoints,
  mostly horizontal steps of 0.15-0.35 L) looking at the centre with a smoothly jittered look-at point.

Every trajectory starts at the input-photo camera (in free space by construction of the scenes) and is checked
collision-free: the camera centre, sampled at most ``CLEARANCE / 2`` apart along the path, keeps at least
``CLEARANCE`` (0.2 m) from every surface (``SimScene.distance``), so the whole path lies in the free space the
input camera is in. A draw that fails is redrawn (new parameters, amplitude x0.75, at most ``MAX_ATTEMPTS`` draws);
if none passes the sequence raises ``RuntimeError`` naming it.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from PIL import Image

from navcrafter.models.camera.cameras import Intrinsics, invert_pose, look_at
from navcrafter.models.camera.trajectories import GL_CV_FLIP  # OpenCV <-> OpenGL camera axes (its own inverse)
from navcrafter.models.simulation import LABEL
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.scenes import GENERATOR_VERSION, KINDS, UP, SimScene, generate_scene

DatasetKind = Literal["re10k", "dl3dv"]
TRAJECTORIES = ("orbit", "dolly", "pan", "nbv")
DEPTH_SUFFIX = ".depth.npy"  # <image stem> + DEPTH_SUFFIX beside each image
MANIFEST = "simulation.json"
CLEARANCE = 0.2  # metres between any camera centre on a path and the nearest surface
MAX_ATTEMPTS = 10
NBV_WAYPOINTS = 4
FPS = 30


def depth_path(image_path: str | Path) -> Path:
    """The depth file written beside an image: ``<stem>.depth.npy`` in the image's folder."""
    p = Path(image_path)
    return p.with_name(p.stem + DEPTH_SUFFIX)


# --------------------------------------------------------------------------------------------------
# Trajectories (scene ground-truth frame, z up; OpenCV camera-to-world)
# --------------------------------------------------------------------------------------------------
def _free_distance(scene: SimScene, origin: np.ndarray, direction: np.ndarray) -> float:
    """Distance from ``origin`` along ``direction`` to the first surface (``inf`` if none)."""
    import open3d as o3d

    rc, _ = scene.raycasting()
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    ray = np.concatenate([origin, d])[None].astype(np.float32)
    return float(rc.cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])


def _smoothstep(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def _direction(yaw: float, pitch: float) -> np.ndarray:
    """Unit vector with azimuth ``yaw`` about +z and elevation ``pitch`` (radians)."""
    return np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])


def _yaw_pitch(v: np.ndarray) -> tuple[float, float]:
    v = v / np.linalg.norm(v)
    return float(np.arctan2(v[1], v[0])), float(np.arcsin(np.clip(v[2], -1.0, 1.0)))


def _catmull_rom(points: np.ndarray, t: np.ndarray) -> np.ndarray:
    """C1 curve through ``points [K, 3]`` (uniform knots over t in [0, 1]), at rest at both ends: cubic
    Hermite segments with Catmull-Rom tangents inside and zero tangents at the first and last point."""
    K = len(points)
    tang = np.zeros_like(points)
    tang[1:-1] = (points[2:] - points[:-2]) / 2
    x = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0) * (K - 1)
    k = np.minimum(np.floor(x).astype(int), K - 2)
    u = (x - k)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    return h00 * points[k] + h10 * tang[k] + h01 * points[k + 1] + h11 * tang[k + 1]


def _trajectory(kind: str, eye: np.ndarray, forward: np.ndarray, L: float, t: np.ndarray,
                rng: np.random.Generator, amp: float, scene: SimScene) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres ``[N, 3]`` and look-at points ``[N, 3]`` at path parameters ``t`` in [0, 1]."""
    yaw0, pitch0 = _yaw_pitch(forward)
    if kind == "orbit":
        centre = eye + forward * L * rng.uniform(0.6, 0.9)
        rel = eye - centre
        sweep = amp * np.deg2rad(rng.uniform(25.0, 60.0)) * rng.choice([-1.0, 1.0])
        dz = amp * rng.uniform(-0.15, 0.15) * np.linalg.norm(rel)
        ang = sweep * t
        c, s = np.cos(ang), np.sin(ang)
        pos = np.stack([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1], rel[2] + dz * t], axis=1) + centre
        return pos, np.broadcast_to(centre, pos.shape).copy()
    if kind == "dolly":
        sign = 1.0 if rng.random() < 0.6 else -1.0
        side = np.cross(forward, UP)
        side /= np.linalg.norm(side)
        direction = sign * forward + side * rng.uniform(-0.2, 0.2)
        direction /= np.linalg.norm(direction)
        travel = amp * L * rng.uniform(0.3, 0.6)
        free = _free_distance(scene, eye, direction) - 2 * CLEARANCE
        travel = min(travel, max(free, 0.0))
        pos = eye + direction * (travel * _smoothstep(t))[:, None]
        return pos, pos + forward
    if kind == "pan":
        dyaw = amp * np.deg2rad(rng.uniform(25.0, 70.0)) * rng.choice([-1.0, 1.0])
        dpitch = amp * np.deg2rad(rng.uniform(-12.0, 12.0))
        e = _smoothstep(t)
        dirs = np.stack([_direction(yaw0 + dyaw * x, np.clip(pitch0 + dpitch * x, -1.2, 1.2)) for x in e])
        pos = np.broadcast_to(eye, dirs.shape).copy()
        return pos, pos + dirs
    if kind == "nbv":
        centre = eye + forward * L * rng.uniform(0.6, 0.9)
        way, targets = [eye], [centre]
        for _ in range(NBV_WAYPOINTS - 1):
            step = rng.normal(size=3) * np.array([1.0, 1.0, 0.3])
            step *= amp * L * rng.uniform(0.15, 0.35) / np.linalg.norm(step)
            way.append(way[-1] + step)
            targets.append(centre + rng.normal(size=3) * 0.15 * L * amp * np.array([1.0, 1.0, 0.5]))
        return _catmull_rom(np.stack(way), t), _catmull_rom(np.stack(targets), t)
    raise ValueError(f"unknown trajectory kind {kind!r}; choose from {TRAJECTORIES}")


def _poses(pos: np.ndarray, look: np.ndarray, L: float) -> np.ndarray | None:
    """look_at poses; ``None`` when a look-at point is too close or straight above/below the camera."""
    out = []
    for p, q in zip(pos, look):
        v = q - p
        n = np.linalg.norm(v)
        if n < 0.1 * min(L, 1.0) or abs(v[2]) / n > 0.97:
            return None
        out.append(look_at(p, q, up=UP))
    return np.stack(out)


def _collision_free(scene: SimScene, kind: str, eye, forward, L, rng_state, amp) -> bool:
    """Whether the path (sampled at most CLEARANCE/2 apart) keeps CLEARANCE from every surface."""
    rng = np.random.default_rng()
    rng.bit_generator.state = rng_state
    coarse = np.linspace(0.0, 1.0, 64)
    pos, _ = _trajectory(kind, eye, forward, L, coarse, rng, amp, scene)
    length = float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum())
    n = max(64, int(np.ceil(length / (CLEARANCE / 2))) + 1)
    rng.bit_generator.state = rng_state
    pos, _ = _trajectory(kind, eye, forward, L, np.linspace(0.0, 1.0, n), rng, amp, scene)
    return bool(np.all(scene.distance(pos) >= CLEARANCE))


def sequence_trajectory(scene: SimScene, kind: str, frames: int, rng: np.random.Generator) -> np.ndarray:
    """``frames`` collision-free OpenCV camera-to-world poses ``[frames, 4, 4]`` of trajectory ``kind``
    starting at the scene's input-photo camera (see the module docstring); raises ``RuntimeError`` when no
    draw passes the collision check."""
    if frames < 2:
        raise ValueError(f"frames must be >= 2, got {frames}")
    eye = scene.camera_c2w[:3, 3].copy()
    forward = scene.camera_c2w[:3, 2].copy()
    hit = _free_distance(scene, eye, forward)
    L = float(np.clip(hit if np.isfinite(hit) else 12.0, 0.5, 12.0))
    t = np.linspace(0.0, 1.0, frames)
    amp = 1.0
    for _ in range(MAX_ATTEMPTS):
        state = rng.bit_generator.state
        free = _collision_free(scene, kind, eye, forward, L, state, amp)
        rng.bit_generator.state = state
        pos, look = _trajectory(kind, eye, forward, L, t, rng, amp, scene)  # the same draws; advances rng
        poses = _poses(pos, look, L) if free else None
        if poses is not None:
            return poses
        amp *= 0.75
    raise RuntimeError(f"scene {scene.kind}/{scene.seed}: no collision-free {kind!r} trajectory found in "
                       f"{MAX_ATTEMPTS} draws (clearance {CLEARANCE} m); use another seed or trajectory kind")


# --------------------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------------------
def _num(v: float) -> str:
    return repr(float(v))  # shortest string that reads back to the same double


def _save_frame(rgb: np.ndarray, depth: np.ndarray | None, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path)
    if depth is not None:
        np.save(depth_path(path), depth.astype(np.float32))


def _write_re10k(base: Path, name: str, url: str, c2w: np.ndarray, K: Intrinsics, rgbs, depths) -> None:
    base.mkdir(parents=True, exist_ok=True)
    lines = [url]
    for i, pose in enumerate(c2w):
        ts = int(round(i * 1e6 / FPS))
        w2c = invert_pose(pose)
        nums = [K.fx / K.width, K.fy / K.height, K.cx / K.width, K.cy / K.height, 0.0, 0.0]
        nums += list(w2c[:3, :].reshape(-1))
        lines.append(" ".join([str(ts)] + [_num(v) for v in nums]))
        _save_frame(rgbs[i], None if depths is None else depths[i], base / name / f"{ts}.png")
    (base / f"{name}.txt").write_text("\n".join(lines) + "\n")


def _write_dl3dv(base: Path, name: str, c2w: np.ndarray, K: Intrinsics, rgbs, depths) -> None:
    scene = base / name
    frames = []
    for i, pose in enumerate(c2w):
        rel = f"images/frame_{i + 1:05d}.png"
        frames.append({"file_path": rel, "transform_matrix": (pose @ GL_CV_FLIP).tolist()})
        _save_frame(rgbs[i], None if depths is None else depths[i], scene / rel)
    doc = {"w": K.width, "h": K.height, "fl_x": K.fx, "fl_y": K.fy, "cx": K.cx, "cy": K.cy,
           "camera_model": "OPENCV", "frames": frames}
    (scene / "transforms.json").write_text(json.dumps(doc, indent=1))


def write_dataset(out: str | Path, kind: DatasetKind, *, sequences: int, frames: int,
                  resolution: int | tuple[int, int], seed: int, scene_kinds: Sequence[str] = KINDS,
                  trajectories: Sequence[str] = TRAJECTORIES, depth: bool = True, split: str | None = None
                  ) -> list[str]:
    """Render ``sequences`` simulated sequences of ``frames`` frames into ``out`` in dataset ``kind``'s format.

    ``resolution``: frame size, ``int`` (square) or ``(height, width)``. ``split``: RealEstate10K only, the split
    folder (``<out>/<split>/``; ``None``: directly in ``out``, read with ``split=None``). ``depth``: also write
    ``<stem>.depth.npy`` beside every image (module docstring). Returns the sequence names, in order.
    """
    if kind not in ("re10k", "dl3dv"):
        raise ValueError(f"kind must be 're10k' or 'dl3dv', got {kind!r}")
    if kind == "dl3dv" and split is not None:
        raise ValueError("split= is a RealEstate10K folder level; DL3DV scenes go directly under out")
    if sequences < 1 or frames < 2:
        raise ValueError(f"need sequences >= 1 and frames >= 2, got sequences={sequences}, frames={frames}")
    H, W = (resolution, resolution) if isinstance(resolution, int) else (int(resolution[0]), int(resolution[1]))
    if min(H, W) < 1:
        raise ValueError(f"resolution must be positive, got {resolution}")
    bad = [k for k in scene_kinds if k not in KINDS] + [t for t in trajectories if t not in TRAJECTORIES]
    if bad or not scene_kinds or not trajectories:
        raise ValueError(f"scene_kinds must be a non-empty subset of {KINDS} and trajectories of {TRAJECTORIES}; "
                         f"got {tuple(scene_kinds)}, {tuple(trajectories)}")
    out = Path(out)
    base = out if split is None else out / split
    base.mkdir(parents=True, exist_ok=True)
    names, records = [], []
    for i in range(sequences):
        rng = np.random.default_rng([int(seed), i])
        scene_kind = scene_kinds[i % len(scene_kinds)]
        traj = trajectories[i % len(trajectories)]
        scene_seed = int(rng.integers(0, 2**31 - 1))
        scene = generate_scene(scene_kind, scene_seed)
        fov = float(np.clip(scene.camera_fov_x_deg + rng.uniform(-5.0, 5.0), 20.0, 120.0))
        K = Intrinsics.from_fov(fov, W, H)
        traj_rng = np.random.default_rng([int(seed), i, zlib.crc32(traj.encode())])
        c2w = sequence_trajectory(scene, traj, frames, traj_rng)
        renders = [render(scene, pose, K) for pose in c2w]
        rgbs = [r.rgb for r in renders]
        depths = [r.depth for r in renders] if depth else None
        name = f"sim-{i:05d}-{scene_kind}-{traj}"
        if kind == "re10k":
            url = f"simulation://{scene_kind}/{scene_seed}/{traj}"
            _write_re10k(base, name, url, c2w, K, rgbs, depths)
        else:
            _write_dl3dv(base, name, c2w, K, rgbs, depths)
        names.append(name)
        records.append({"name": name, "scene": scene.spec, "trajectory": traj, "frames": int(frames),
                        "fov_x_deg": fov, "height": H, "width": W, "depth": bool(depth),
                        "K": K.K.tolist(), "c2w": c2w.tolist()})
    manifest = {"note": LABEL, "format": kind, "split": split, "seed": int(seed),
                "generator_version": GENERATOR_VERSION,
                "frame": "scene ground truth: z up, metres; cameras OpenCV camera-to-world",
                "depth": f"<image stem>{DEPTH_SUFFIX}: float32 [H, W] z-depth in metres, 0 = no surface"
                         if depth else None,
                "sequences": records}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return names

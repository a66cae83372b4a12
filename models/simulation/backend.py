"""The simulation backend: ground-truth renders standing in for the learned models.

It exists so that the whole product runs, and is measured against ground truth, where no model
weights are present. Everything it produces is labelled ``backend: simulation``.

* **Synthesizer** renders the true scene along the requested trajectory (a perfect video model). It checks the
  request's images (shapes, the reference frame given with its camera) but never looks at their pixels: its frame
  0 is the truth at ``trajectory[0]``, which is what the conditioning image shows (the working image, or the
  previous clip's last frame, a render at the same pose); the reference (input photo) adds nothing to the truth.
* **Geometry** returns the true depth and relative cameras of the requested views, corrupted like a
  feed-forward model's output: an arbitrary global scale per call, per-pixel depth noise, pose
  jitter, optional focal error, low confidence at depth discontinuities, nothing on the sky.
  Results are in the first view's frame (``c2w[0] = I``), as VGGT returns them.
* **MonoDepth** returns affine-invariant inverse depth (unknown scale and shift) and the sky mask.
* **Refiner** moves a render of the fitted Gaussians a fraction ``refine_strength`` of the way to the true
  view at that camera and adds pixel noise (``refine_noise``): a diffusion refiner that repairs most, not
  all, of the artifacts. It measures the refine step's plumbing and what a good refiner can give, not
  Difix itself.

Frames of reference: the scene's *world* is the input camera's OpenCV frame at the scale of the
first geometry call (``world_scale`` = that call's scale relative to metres). ``SimulationTruth``
maps between world and the generator's ground-truth frame (z-up, metres).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics, axis_angle_to_matrix, invert_pose
from navcrafter.models.roles import (
    Backend,
    GeometryPrediction,
    MonoDepthPrediction,
    SynthesisRequest,
)
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.scenes import GENERATOR_VERSION, SimScene, generate_scene
from navcrafter.schemas.config import SimulationConfig

BACKEND = "simulation"


class SimulationError(RuntimeError):
    """The simulation backend cannot serve this input (e.g. a real photo without ground truth)."""


@functools.lru_cache(maxsize=4)
def cached_scene(kind: str, seed: int) -> SimScene:
    return generate_scene(kind, seed)


@dataclass
class SimulationTruth:
    """Hidden ground truth of one scene, as recorded by ingest (and the first geometry call)."""

    scene: SimScene
    photo_c2w: np.ndarray  # input camera, ground-truth frame
    work_intrinsics: Intrinsics  # true intrinsics of the working image
    world_scale: float | None = None  # world units per metre; known after the first geometry call

    @classmethod
    def from_record(cls, record: dict, world_scale: float | None = None) -> SimulationTruth:
        spec = record["scene"]
        if int(spec.get("generator_version", -1)) != GENERATOR_VERSION:
            raise SimulationError(
                f"ground truth was made by scene generator v{spec.get('generator_version')}, this is "
                f"v{GENERATOR_VERSION}; regenerate the demo data with `navcrafter demo-data`")
        return cls(cached_scene(spec["kind"], int(spec["seed"])), np.asarray(record["photo_c2w"], dtype=np.float64),
                   Intrinsics.from_dict(record["work_intrinsics"]), world_scale)

    def _scale(self) -> float:
        if self.world_scale is None:
            raise SimulationError("the scene's world scale is unknown: run the initial geometry step first")
        return self.world_scale

    def gt_pose(self, c2w_world: np.ndarray) -> np.ndarray:
        """World camera pose(s) ``[..., 4, 4]`` to the ground-truth frame."""
        w = self._scale()
        out = np.array(c2w_world, dtype=np.float64, copy=True)
        R_in, t_in = self.photo_c2w[:3, :3], self.photo_c2w[:3, 3]
        out[..., :3, :3] = R_in @ out[..., :3, :3]
        out[..., :3, 3] = (out[..., :3, 3] / w) @ R_in.T + t_in
        return out

    def gt_pose_or_photo(self, c2w_world: np.ndarray) -> np.ndarray:
        """Like ``gt_pose``, but also serves the input camera alone before the world scale is known
        (the first geometry call defines the world)."""
        if self.world_scale is None:
            if len(c2w_world) != 1 or not np.allclose(c2w_world[0], np.eye(4)):
                raise SimulationError("the scene's world scale is unknown: run the initial geometry step first")
            return self.photo_c2w[None].copy()
        return self.gt_pose(c2w_world)

    def gt_points(self, points_world: np.ndarray) -> np.ndarray:
        w = self._scale()
        return (np.asarray(points_world, dtype=np.float64) / w) @ self.photo_c2w[:3, :3].T + self.photo_c2w[:3, 3]

    def world_points(self, points_gt: np.ndarray) -> np.ndarray:
        w = self._scale()
        return w * ((np.asarray(points_gt, dtype=np.float64) - self.photo_c2w[:3, 3]) @ self.photo_c2w[:3, :3])

    def intrinsics_for(self, height: int, width: int) -> Intrinsics:
        K = self.work_intrinsics
        return K if (K.height, K.width) == (height, width) else K.resize(width, height)


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed & 0xFFFFFFFFFFFFFFFF)


def _require_hint(hint_c2w: np.ndarray | None, n: int) -> np.ndarray:
    if hint_c2w is None:
        raise SimulationError("the simulation backend needs the requested camera poses (hint_c2w)")
    hint = np.asarray(hint_c2w, dtype=np.float64).reshape(-1, 4, 4)
    if len(hint) != n:
        raise ValueError(f"hint_c2w has {len(hint)} poses for {n} frames")
    return hint


class _SimulationRole:
    backend = BACKEND

    def __init__(self, truth: SimulationTruth, config: SimulationConfig) -> None:
        self.truth, self.config = truth, config


class SimulationSynthesizer(_SimulationRole):

    def synthesize(self, request: SynthesisRequest) -> np.ndarray:
        H, W = _check_request(request)
        K = self.truth.intrinsics_for(H, W)
        poses = self.truth.gt_pose(request.trajectory)
        frames = np.empty((len(poses), H, W, 3), dtype=np.uint8)
        for i, c2w in enumerate(poses):
            frames[i] = render(self.truth.scene, c2w, K, supersample=self.config.supersample).rgb
        return frames


def _check_request(request: SynthesisRequest) -> tuple[int, int]:
    """(H, W) of a request whose images and cameras have the shapes of the ``SynthesisRequest`` contract: a
    uint8 conditioning image [H, W, 3], a trajectory [T, 4, 4] (T >= 1), and the reference frame either absent
    or given whole (an image like the conditioning image, with its [4, 4] world c2w)."""
    image = np.asarray(request.image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"request.image must be uint8 [H, W, 3], got {image.dtype} {image.shape}")
    traj = np.asarray(request.trajectory)
    if traj.ndim != 3 or traj.shape[1:] != (4, 4) or len(traj) == 0:
        raise ValueError(f"request.trajectory must be [T, 4, 4] with T >= 1, got {traj.shape}")
    if (request.reference_image is None) != (request.reference_c2w is None):
        raise ValueError("request.reference_image and request.reference_c2w come together (the input photo and "
                         "its camera) or not at all")
    if request.reference_image is not None:
        ref = np.asarray(request.reference_image)
        if ref.shape != image.shape or ref.dtype != np.uint8:
            raise ValueError(f"request.reference_image must be uint8 {image.shape} like request.image, got "
                             f"{ref.dtype} {ref.shape}")
        if np.shape(request.reference_c2w) != (4, 4):
            raise ValueError(f"request.reference_c2w must be [4, 4], got {np.shape(request.reference_c2w)}")
    return image.shape[0], image.shape[1]


class SimulationGeometry(_SimulationRole):

    def predict(self, frames: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None) -> GeometryPrediction:
        S, H, W = frames.shape[:3]
        hint = _require_hint(hint_c2w, S)
        cfg, rng = self.config, _rng(seed)
        scale = float(np.exp(rng.normal(0.0, cfg.scale_sigma)))  # this call's units per metre
        # relative poses to view 0, in metres, then in this call's units
        gt = self.truth.gt_pose_or_photo(hint)
        rel = invert_pose(gt[0]) @ gt
        rel[0] = np.eye(4)  # exactly, as VGGT's first frame
        rel[:, :3, 3] *= scale
        K_true = self.truth.intrinsics_for(H, W)
        depth = np.zeros((S, H, W), dtype=np.float32)
        conf = np.zeros((S, H, W), dtype=np.float32)
        c2w = np.empty((S, 4, 4))
        Ks = np.empty((S, 3, 3))
        for i in range(S):
            r = render(self.truth.scene, gt[i], K_true, colour=False)
            d = r.depth.astype(np.float64) * scale * (1.0 + rng.normal(0.0, cfg.depth_noise, (H, W)))
            depth[i] = np.where(r.hit, d, 0.0)
            conf[i] = np.where(r.hit, np.where(_discontinuity(r.depth, r.hit), cfg.edge_confidence, 1.0), 0.0)
            pose = rel[i].copy()
            if i > 0:
                axis = rng.normal(size=3)
                pose[:3, :3] = axis_angle_to_matrix(axis, np.deg2rad(rng.normal(0, cfg.pose_rot_deg))) @ pose[:3, :3]
                pose[:3, 3] += rng.normal(0.0, cfg.pose_trans * scale, 3)
            c2w[i] = pose
            f = 1.0 + rng.normal(0.0, cfg.focal_noise)
            Ks[i] = K_true.K
            Ks[i, 0, 0] *= f
            Ks[i, 1, 1] *= f
        return GeometryPrediction(c2w=c2w, K=Ks, depth=depth, confidence=conf,
                                  extras={"simulation_scale": scale})


def _discontinuity(depth: np.ndarray, hit: np.ndarray, rel: float = 0.05) -> np.ndarray:
    """Pixels next to a relative depth jump larger than ``rel`` or to a miss."""
    d = np.where(hit, depth, 0.0)
    edge = np.zeros_like(hit)
    for axis in (0, 1):
        a = np.take(d, range(1, d.shape[axis]), axis=axis)
        b = np.take(d, range(0, d.shape[axis] - 1), axis=axis)
        jump = np.abs(a - b) > rel * np.maximum(np.minimum(a, b), 1e-6)
        jump |= (a == 0) != (b == 0)
        if axis == 0:
            edge[1:] |= jump
            edge[:-1] |= jump
        else:
            edge[:, 1:] |= jump
            edge[:, :-1] |= jump
    return edge & hit


class SimulationMonoDepth(_SimulationRole):

    def predict(self, image: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None) -> MonoDepthPrediction:
        H, W = image.shape[:2]
        hint = _require_hint(hint_c2w, 1)
        gt = self.truth.gt_pose_or_photo(hint)[0]
        r = render(self.truth.scene, gt, self.truth.intrinsics_for(H, W), colour=False)
        rng = _rng(seed)
        inv = np.where(r.hit, 1.0 / np.maximum(r.depth, 1e-6), 0.0)
        a = float(np.exp(rng.normal(0.0, 1.0)))
        b = float(rng.uniform(0.0, 0.2)) * a * float(np.median(inv[r.hit])) if r.hit.any() else 0.0
        noisy = inv * (1.0 + rng.normal(0.0, 2 * self.config.depth_noise, inv.shape))
        rel = np.where(r.hit, a * noisy + b, 0.0).astype(np.float32)
        return MonoDepthPrediction(inv_depth=rel, sky=~r.hit if self.truth.scene.sky else np.zeros_like(r.hit))


class SimulationRefiner(_SimulationRole):

    def refine(self, rendered: np.ndarray, reference: np.ndarray | None, *, seed: int,
               hint_c2w: np.ndarray | None = None, hint_intrinsics: Intrinsics | None = None) -> np.ndarray:
        H, W = rendered.shape[:2]
        gt_pose = self.truth.gt_pose(_require_hint(hint_c2w, 1))[0]
        K = hint_intrinsics if hint_intrinsics is not None else self.truth.intrinsics_for(H, W)
        if (K.height, K.width) != (H, W):
            raise ValueError(f"hint_intrinsics are for {K.width}x{K.height}, the render is {W}x{H}")
        truth = render(self.truth.scene, gt_pose, K, supersample=max(2, self.config.supersample)).rgb
        r, t = rendered.astype(np.float64) / 255.0, truth.astype(np.float64) / 255.0
        out = r + self.config.refine_strength * (t - r)
        if self.config.refine_noise > 0:
            out = out + _rng(seed).normal(0.0, self.config.refine_noise, out.shape)
        return np.round(np.clip(out, 0.0, 1.0) * 255).astype(np.uint8)


def simulation_backend(truth: SimulationTruth, config: SimulationConfig) -> Backend:
    return Backend(name=BACKEND, synthesizer=SimulationSynthesizer(truth, config),
                   geometry=SimulationGeometry(truth, config), mono_depth=SimulationMonoDepth(truth, config),
                   refiner=SimulationRefiner(truth, config))

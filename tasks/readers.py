"""Readers of what several steps, reports and benchmarks read back from a scene's store: the camera path of its
clips (one definition of frames, poses, intrinsics and size), the scene centre, the current pose, and the
stored Gaussians and the fit's views."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.recipe import resize_image
from navcrafter.models.gaussians.train import TrainView
from navcrafter.models.planning.planners import scene_centre
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import FIT, GEOMETRY, PLAN, REFINE, SYNTHESIZE, StepSpec
from navcrafter.schemas.store import SceneStore


@dataclass(frozen=True)
class CameraPath:
    """Frames of a scene's clips at the cameras they were synthesized for (the planned poses): per frame its
    iteration ``k`` and index ``i`` in clip k, OpenCV c2w [F, 4, 4] and K [F, 3, 3] at ``width`` x ``height``.

    Repeated first frames: iteration k >= 2 starts at the last pose of clip k-1, and its clip is conditioned on
    clip k-1's last frame (``tasks/synthesize.py``), which an I2V model reproduces as frame 0. So frame 0 of
    clip k >= 2 is a second view of the camera of (k-1, T-1), a reproduction rather than a new view.
    ``distinct()`` drops the repeat and keeps the first occurrence (the frame clip k was conditioned on), so each
    camera of the path counts once; the lift step never selects frame 0 (``lifting.select_views``), and the fit
    trains on and holds out only distinct frames (its ``frame_ref``, which ``load_fit_views`` reads back)."""

    iteration: np.ndarray
    frame: np.ndarray
    c2w: np.ndarray
    K: np.ndarray
    width: int
    height: int

    def __len__(self) -> int:
        return len(self.c2w)

    @property
    def refs(self) -> list[tuple[int, int]]:
        """(k, i) of every frame."""
        return [(int(k), int(i)) for k, i in zip(self.iteration, self.frame)]

    def select(self, mask_or_index) -> CameraPath:
        return CameraPath(self.iteration[mask_or_index], self.frame[mask_or_index], self.c2w[mask_or_index],
                          self.K[mask_or_index], self.width, self.height)

    def distinct(self) -> CameraPath:
        """Without frame 0 of clips k >= 2: it reproduces the last frame of clip k-1 at the same pose (kept)."""
        return self.select((self.iteration == 1) | (self.frame > 0))

    def clip(self, k: int) -> CameraPath:
        return self.select(self.iteration == k)

    def intrinsics(self, f: int) -> Intrinsics:
        return Intrinsics.from_matrix(self.K[f], self.width, self.height)


def camera_path(scene: SceneStore, config: RunConfig, iterations: int | None = None) -> CameraPath:
    """Every frame of clips 1..``iterations`` (default ``config.iterations``; with the repeated first frames,
    which ``.distinct()`` drops), at the synthesis size."""
    iterations = config.iterations if iterations is None else iterations
    ks, idx, c2w, K = [], [], [], []
    for k in range(1, iterations + 1):
        traj, Kk = scene.read(PLAN, k, "trajectory"), scene.read(PLAN, k, "K")
        ks += [k] * len(traj)
        idx += list(range(len(traj)))
        c2w.append(np.asarray(traj, dtype=np.float64))
        K.append(np.repeat(np.asarray(Kk, dtype=np.float64)[None], len(traj), axis=0))
    height, width = config.synthesis.height, config.synthesis.width
    return CameraPath(np.asarray(ks, dtype=np.int64), np.asarray(idx, dtype=np.int64),
                      np.concatenate(c2w) if c2w else np.zeros((0, 4, 4)),
                      np.concatenate(K) if K else np.zeros((0, 3, 3)), int(width), int(height))


def input_pose(scene: SceneStore) -> np.ndarray:
    """World c2w of the input camera (``iter_0/geometry``: the identity, which defines the world frame)."""
    return scene.read(GEOMETRY, None, "c2w")


def current_pose(scene: SceneStore, k: int) -> np.ndarray:
    """Where iteration k starts: the input camera, then the last pose of the previous trajectory."""
    return np.eye(4) if k == 1 else scene.read(PLAN, k - 1, "trajectory")[-1]


def stored_scene_centre(scene: SceneStore, config: RunConfig) -> np.ndarray:
    """The scene centre ``o`` of a scene, from its initial geometry."""
    geo = scene.read_all(GEOMETRY)
    return scene_centre(geo["depth"], geo["confidence"], config.plan.centre_depth_quantile)


def load_gaussians(scene: SceneStore, step: StepSpec = FIT) -> GaussianModel:
    """The Gaussians a step stored (the fit's ``gaussians`` group by default; the refine step's ``renders``);
    the group must be complete."""
    scene.require_complete(step)
    arrays = scene.read_all(step)
    return GaussianModel(**{k: torch.from_numpy(np.ascontiguousarray(arrays[k])) for k in
                            ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")})


def load_refined_gaussians(scene: SceneStore) -> GaussianModel:
    """The refined model of a scene (its ``renders`` group must be complete)."""
    return load_gaussians(scene, REFINE)


def load_fit_views(scene: SceneStore) -> tuple[list[TrainView], list[TrainView]]:
    """The fit's training and held-out views, rebuilt from its group (frames from the synthesize steps,
    resized as the fit did; calibrated depth targets of the training views)."""
    scene.require_complete(FIT)
    g = scene.read_all(FIT)
    w, h = scene.status(FIT).attrs["resolution"]
    frames: dict[int, np.ndarray] = {}
    train, test = [], []
    for f, (k, i) in enumerate(np.asarray(g["frame_ref"])):
        if int(k) not in frames:
            frames[int(k)] = scene.read(SYNTHESIZE, int(k), "frames")
        img = resize_image(frames[int(k)][int(i)], h, w).astype(np.float32) / 255.0
        d = g["depth_targets"][f]
        view = TrainView(torch.from_numpy(img), torch.as_tensor(g["c2w"][f], dtype=torch.float32),
                         torch.as_tensor(g["K"][f], dtype=torch.float32),
                         torch.from_numpy(np.ascontiguousarray(d)) if (d > 0).any() else None)
        if g["holdout"][f]:
            test.append(view)
        elif g["train"][f]:
            train.append(view)
    return train, test

"""The Fun-Camera Plücker embedding (``videox_fun/data/utils.py``: relative poses, ``ray_condition``) and its temporal
packing (``fun_camera_pack``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from navcrafter.models.camera.camerafiles import RE10KCameras


def fun_camera_relative_poses(c2w: np.ndarray) -> np.ndarray:
    """``get_relative_pose``: frame 0 becomes the identity and frame ``i`` ``w2c_0 @ c2w_i`` (float32 ``[T, 4, 4]``).

    No translation normalisation (unlike navcrafter's ``"relative"`` convention): the translations keep the units
    of the poses (RealEstate10K's are ORB-SLAM's, per video).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) == 0:
        raise ValueError(f"c2w must be [T, 4, 4] with T >= 1, got {c2w.shape}")
    w2c0 = np.linalg.inv(c2w[0])
    out = np.concatenate([np.eye(4)[None], np.einsum("ij,tjk->tik", w2c0, c2w[1:])], axis=0)
    return out.astype(np.float32)


def _ray_condition(fxfycxcy: np.ndarray, c2w: np.ndarray, height: int, width: int) -> np.ndarray:
    """``ray_condition`` for one clip: ``[T, H, W, 6] = (o x d, d)`` float32 (computed in float32 as the official).

    Pixel centres ``(j + 0.5, i + 0.5)``; ``d = normalise([(u - cx)/fx, (v - cy)/fy, 1])`` in the camera frame, then
    rotated by ``R`` (``directions @ R^T``); ``o`` = the camera centre ``t``; the moment is ``cross(o, d)`` first.
    The official calls ``torch.cross`` without ``dim`` (the first axis of size 3): with exactly 3 frames (or
    ``H*W == 3``) it would take that axis instead; here the cross product is always over the xyz axis.
    """
    T = c2w.shape[0]
    i = np.arange(width, dtype=np.float32)[None, :].repeat(height, 0).reshape(1, -1) + np.float32(0.5)
    j = np.arange(height, dtype=np.float32)[:, None].repeat(width, 1).reshape(1, -1) + np.float32(0.5)
    fx, fy, cx, cy = (fxfycxcy[:, k:k + 1].astype(np.float32) for k in range(4))
    xs = (i - cx) / fx
    ys = (j - cy) / fy
    zs = np.ones_like(xs)
    dirs = np.stack([xs, ys, zs], axis=-1)  # [T, HW, 3]
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    rays_d = dirs @ np.swapaxes(c2w[:, :3, :3], -1, -2)
    rays_o = np.broadcast_to(c2w[:, None, :3, 3], rays_d.shape)
    plucker = np.concatenate([np.cross(rays_o, rays_d), rays_d], axis=-1)
    return plucker.reshape(T, height, width, 6).astype(np.float32)


def fun_camera_plucker(c2w: np.ndarray, K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Per-pixel Plücker embedding ``[T, H, W, 6]`` float32 as VideoX-Fun's camera control computes it.

    Mirrors ``videox_fun/data/utils.py`` (aigc-apps/VideoX-Fun, from CameraCtrl): ``process_pose_params`` /
    ``process_pose_file`` → ``get_relative_pose`` (``fun_camera_relative_poses``: poses relative to the first
    camera, frame 0 = identity, **no scale normalisation**) → ``ray_condition`` (pixel centres ``+0.5``,
    ``d = R · normalise(K^-1 [u, v, 1])``, ``o = t``, channels **``(o × d, d)``**: moment first, then direction).

    ``c2w``: ``[T, 4, 4]`` camera-to-world poses in the OpenCV convention (x right, y down, z forward: RealEstate10K's
    and navcrafter's). ``K``: ``[3, 3]`` (or ``[T, 3, 3]``) pixel intrinsics of the ``width x height`` frames, i.e.
    the official ``[fx·W, fy·H, cx·W, cy·H]`` after its aspect-ratio adjustment (``fun_camera_plucker_from_re10k``
    does that step from normalised RealEstate10K intrinsics). The official format has no skew: a skewed ``K`` is
    refused. The clip's first camera is the origin whatever ``c2w[0]`` is.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim == 2:
        c2w = c2w[None]
    T = c2w.shape[0] if c2w.ndim == 3 else 0
    K = np.asarray(K, dtype=np.float64)
    Ks = np.broadcast_to(K, (T, 3, 3)) if K.ndim == 2 else K
    if Ks.shape != (T, 3, 3):
        raise ValueError(f"K must be [3, 3] or [{T}, 3, 3], got {K.shape}")
    if np.any(np.abs(Ks[:, 0, 1]) > 1e-9):
        raise ValueError("K has skew (K[0, 1] != 0); the VideoX-Fun ray embedding takes fx, fy, cx, cy only")
    fxfycxcy = np.stack([Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2]], axis=-1).astype(np.float32)
    return _ray_condition(fxfycxcy, fun_camera_relative_poses(c2w), int(height), int(width))


def fun_camera_plucker_from_re10k(cam_params: RE10KCameras | Sequence[Sequence[float]], width: int, height: int,
                                  original_pose_width: int = 1280, original_pose_height: int = 720) -> np.ndarray:
    """``process_pose_params(cam_params, width, height, original_pose_width, original_pose_height)``: ``[T, H, W, 6]``.

    ``cam_params``: a RealEstate10K camera file as ``models.camera.camerafiles.read_re10k_cameras`` reads it (the
    one parser of the format), or its rows ``[T, 19]`` (``RE10KCameras.rows``).

    ``Camera(entry)``: normalised ``fx, fy, cx, cy = entry[1:5]``, ``w2c = entry[7:]`` as 3x4, ``c2w = inv(w2c)``.
    Aspect ratio: if the poses' ``W/H`` (1280/720 by default) exceeds the sample's, ``fx *= H·(W0/H0) / W``, else
    ``fy *= (W/(W0/H0)) / H``; then pixel intrinsics ``[fx·W, fy·H, cx·W, cy·H]``.
    """
    rows = np.asarray(cam_params.rows() if isinstance(cam_params, RE10KCameras) else cam_params, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != 19:
        raise ValueError(f"cam_params must be [T, 19] RealEstate10K rows, got {rows.shape}")
    fx, fy, cx, cy = rows[:, 1].copy(), rows[:, 2].copy(), rows[:, 3], rows[:, 4]
    w2c = np.tile(np.eye(4), (len(rows), 1, 1))
    w2c[:, :3, :] = rows[:, 7:].reshape(-1, 3, 4)
    c2w = np.linalg.inv(w2c)
    sample_ratio, pose_ratio = width / height, original_pose_width / original_pose_height
    if pose_ratio > sample_ratio:
        fx = (height * pose_ratio) * fx / width
    else:
        fy = (width / pose_ratio) * fy / height
    fxfycxcy = np.stack([fx * width, fy * height, cx * width, cy * height], axis=-1).astype(np.float32)
    return _ray_condition(fxfycxcy, fun_camera_relative_poses(c2w), int(height), int(width))


def fun_camera_pack(plucker: torch.Tensor, frames_per_latent: int = 4) -> torch.Tensor:
    """Rays ``[B, 6, T, H, W]`` (``T = 4(F-1)+1``) -> ``[B, 24, F, H, W]`` as the Fun pipeline packs
    ``control_camera_video``: frame 0 repeated 4 times in front, groups of 4 consecutive frames, channel
    ``4c + j`` = Plücker channel ``c`` of frame ``j`` of the group."""
    s = int(frames_per_latent)
    B, C, T, H, W = plucker.shape
    if (T - 1) % s:
        raise ValueError(f"plucker has {T} frames; it must have {s}(F-1)+1")
    x = torch.cat([plucker[:, :, :1].expand(-1, -1, s, -1, -1), plucker[:, :, 1:]], dim=2)  # [B, C, 4F, H, W]
    x = x.transpose(1, 2).reshape(B, -1, s, C, H, W).transpose(2, 3)  # [B, F, C, s, H, W]
    return x.reshape(B, -1, C * s, H, W).transpose(1, 2)

"""``fun-camera``: Wan2.1-Fun-V1.1-Control-Camera (aigc-apps/VideoX-Fun, Apache-2.0) on diffusers' Wan DiT.

A second synthesizer model beside NavCrafter's own camera control (``camcontrol.py``), built from the official
VideoX-Fun code's definitions (read at upstream commit 804a425, 2026-05-12; file paths below are in that repository):

* **Architecture** (``videox_fun/models/wan_transformer3d.py`` ``WanTransformer3DModel`` with
  ``add_control_adapter=True``; the adapter is ``videox_fun/models/wan_camera_adapter.py`` ``SimpleAdapter``): a
  Wan2.1 I2V DiT (``model_type="i2v"``: CLIP ``img_emb`` and the decoupled image cross-attention) whose patch
  embedding takes ``in_dim = 32`` channels, plus one camera adapter whose output is **added to the patch embedding's
  output** (``x = patch_embedding(x) + control_adapter(y_camera)``, before flattening to tokens) and nowhere else.
  Here the DiT is diffusers' ``WanTransformer3DModel`` (same maths as the official module; the key mapping is
  diffusers' own ``convert_wan_transformer_to_diffusers``) and the adapter is ``FunCameraAdapter``.
* **Adapter** (``SimpleAdapter``): per latent frame, ``PixelUnshuffle(8)`` of the ``24``-channel packed rays
  (``24·64 = 1536`` channels at the latent grid), ``Conv2d(1536, D, kernel 2, stride 2)`` onto the token grid, then
  one residual block ``x + conv2(relu(conv1(x)))`` (3x3 convs, no activation after the sum).
* **Input channels** (``videox_fun/pipeline/pipeline_wan_fun_control.py``, ``scripts/wan2.1_fun/train_control.py``):
  ``hidden_states = [noisy latents (16) | start-image latents (16)]``: the start image VAE-encoded as a one-frame
  video into latent frame 0, **all other latent frames exactly zero** (not VAE latents of black frames), and no
  I2V mask (confirmed by the maintainers in VideoX-Fun issue #409: "control camera uses no mask, only the first
  frame"). The CLIP features of the start image go to ``img_emb`` as in Wan I2V.
* **Temporal packing** (the pipeline's ``control_camera_latents``): rays ``[B, 6, T, H, W]`` at pixel resolution,
  frame 0 repeated 4 times in front (``4F`` frames), grouped by 4 consecutive frames; channel ``4c + j`` of latent
  frame ``k`` is Plücker channel ``c`` of frame ``j`` of group ``k`` (``fun_camera_pack``).
* **Plücker embedding** (``videox_fun/data/utils.py`` ``process_pose_file`` / ``process_pose_params``,
  ``get_relative_pose``, ``ray_condition``, ``Camera``; copied there from CameraCtrl): ``fun_camera_plucker``.

Weights: ``load_fun_camera(directory)`` reads the official transformer folder (``config.json`` +
``diffusion_pytorch_model.safetensors``, or its sharded index) with strict key and shape checks against the
architecture its ``config.json`` describes; ``save_fun_camera`` writes the same layout back. The layout of the
published 1.3B checkpoint is committed in ``keys/fun_camera_1_3b.json`` (generated from the official module, see
its header). ``export_fun_camera_dit`` exports the DiT to ONNX; the sampler is ``pipeline.sample_video`` (manifest
``config.condition_layout = "fun-camera"``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from diffusers.models.transformers.transformer_wan import WanTransformer3DModel

from navcrafter.models.checkpoints import listing as _short

MODEL_NAME = "fun-camera"  # synthesis.model
ARCHITECTURE = "wan2.1-fun-v1.1-control-camera"  # manifest architecture
PLUCKER_CONVENTION = "videox-fun"  # manifest config.plucker_convention (fun_camera_plucker)
CONDITION_LAYOUT = "fun-camera"  # manifest config.condition_layout (pipeline.prepare_conditions)
OFFICIAL_CONFIG = "config.json"
OFFICIAL_WEIGHTS = "diffusion_pytorch_model.safetensors"
OFFICIAL_INDEX = "diffusion_pytorch_model.safetensors.index.json"
KEY_LIST_1_3B = Path(__file__).parents[1] / "keys" / "fun_camera_1_3b.json"
VAE_STRIDE = (4, 8, 8)
LATENT_CHANNELS = 16
TEXT_TOKENS = 512
PLUCKER_CHANNELS = 6

FUN_DIT_INPUTS = ["hidden_states", "timestep", "encoder_hidden_states", "encoder_hidden_states_image", "plucker"]
FUN_DIT_OUTPUTS = ["noise_pred"]


class FunCameraWeightsError(ValueError):
    """A Fun-Camera checkpoint does not fit (file, missing / unexpected / wrong-shape keys and the fix are named)."""


# --------------------------------------------------------------------------------------------------
# Config
# --------------------------------------------------------------------------------------------------
@dataclass
class FunCameraConfig:
    """Sizes of a Fun-Camera DiT, named after the official ``config.json`` fields (``official_config``).

    ``image_dim``: CLIP feature width (the official ``MLPProj(1280, dim)`` hard-codes 1280; tiny test configs
    shrink it). ``in_dim_control_adapter``: packed ray channels (6 Plücker x 4 frames); ``downscale_factor``: the
    adapter's ``PixelUnshuffle`` factor (the VAE's spatial stride); ``adapter_residual_blocks``: 1 in the official
    code (``SimpleAdapter``'s default, not exposed in its config).
    """

    dim: int = 1536
    ffn_dim: int = 8960
    num_heads: int = 12
    num_layers: int = 30
    in_dim: int = 32
    out_dim: int = 16
    text_dim: int = 4096
    freq_dim: int = 256
    image_dim: int = 1280
    eps: float = 1e-6
    patch_size: tuple[int, int, int] = (1, 2, 2)
    text_len: int = TEXT_TOKENS
    in_dim_control_adapter: int = 24
    downscale_factor_control_adapter: int = 8
    adapter_residual_blocks: int = 1
    rope_max_seq_len: int = 1024  # the official rope_params(1024, ...)

    def __post_init__(self) -> None:
        self.patch_size = tuple(int(p) for p in self.patch_size)
        if self.dim % self.num_heads or (self.dim // self.num_heads) % 2:
            raise ValueError(f"dim {self.dim} must split into {self.num_heads} heads of even size")
        if self.in_dim_control_adapter % PLUCKER_CHANNELS:
            raise ValueError(f"in_dim_control_adapter must be 6 Plücker channels x frames per latent frame, got "
                             f"{self.in_dim_control_adapter}")
        if self.in_dim != 2 * LATENT_CHANNELS:
            raise ValueError(f"in_dim must be 32 (16 noisy + 16 start-image latents: the Control-Camera layout), "
                             f"got {self.in_dim}")

    @property
    def temporal_packing(self) -> int:
        return self.in_dim_control_adapter // PLUCKER_CHANNELS

    @classmethod
    def tiny(cls) -> FunCameraConfig:
        """Test size: 2 heads x 12, 2 layers (the tiny VAE's spatial stride is 8 as well)."""
        return cls(dim=24, ffn_dim=32, num_heads=2, num_layers=2, text_dim=32, image_dim=4, rope_max_seq_len=32)

    @classmethod
    def wan_1_3b(cls) -> FunCameraConfig:
        """Wan2.1-Fun-V1.1-1.3B-Control-Camera (``keys/fun_camera_1_3b.json``)."""
        return cls()

    @classmethod
    def wan_14b(cls) -> FunCameraConfig:
        """Wan2.1-Fun-V1.1-14B-Control-Camera (Wan2.1-14B sizes: 40 heads x 128, 40 layers, ffn 13824)."""
        return cls(dim=5120, ffn_dim=13824, num_heads=40, num_layers=40)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["patch_size"] = list(self.patch_size)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FunCameraConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown FunCameraConfig keys {unknown}; known: {sorted(known)}")
        return cls(**d)

    def diffusers_kwargs(self) -> dict[str, Any]:
        """``WanTransformer3DModel`` kwargs of the base (I2V: ``added_kv_proj_dim`` = the width, see camcontrol)."""
        return {"patch_size": self.patch_size, "num_attention_heads": self.num_heads,
                "attention_head_dim": self.dim // self.num_heads, "in_channels": self.in_dim,
                "out_channels": self.out_dim, "text_dim": self.text_dim, "freq_dim": self.freq_dim,
                "ffn_dim": self.ffn_dim, "num_layers": self.num_layers, "cross_attn_norm": True,
                "qk_norm": "rms_norm_across_heads", "eps": self.eps, "image_dim": self.image_dim,
                "added_kv_proj_dim": self.dim, "rope_max_seq_len": self.rope_max_seq_len}

    def official_config(self) -> dict[str, Any]:
        """The ``config.json`` of the official transformer folder (fields ``WanTransformer3DModel.__init__`` of
        wan_transformer3d.py reads; ``image_dim`` is a navcrafter extension, written only when it is not 1280)."""
        d: dict[str, Any] = {"_class_name": "WanTransformer3DModel", "model_type": "i2v",
                             "patch_size": list(self.patch_size), "text_len": self.text_len, "in_dim": self.in_dim,
                             "dim": self.dim, "ffn_dim": self.ffn_dim, "freq_dim": self.freq_dim,
                             "text_dim": self.text_dim, "out_dim": self.out_dim, "num_heads": self.num_heads,
                             "num_layers": self.num_layers, "window_size": [-1, -1], "qk_norm": True,
                             "cross_attn_norm": True, "eps": self.eps, "add_control_adapter": True,
                             "in_dim_control_adapter": self.in_dim_control_adapter,
                             "downscale_factor_control_adapter": self.downscale_factor_control_adapter,
                             "add_ref_conv": False}
        if self.image_dim != 1280:
            d["image_dim"] = self.image_dim
        if self.adapter_residual_blocks != 1:
            d["adapter_residual_blocks"] = self.adapter_residual_blocks
        if self.rope_max_seq_len != 1024:
            d["rope_max_seq_len"] = self.rope_max_seq_len
        return d

    @classmethod
    def from_official_config(cls, d: dict[str, Any], source: str = "config.json") -> FunCameraConfig:
        """Parse an official ``config.json`` (defaults as the official constructor's); refuses what this module
        does not build, naming the field."""
        def get(name, default):
            return d.get(name, default)

        problems = []
        if get("model_type", "t2v") != "i2v":
            problems.append(f"model_type {get('model_type', 't2v')!r} (the Control-Camera checkpoints are 'i2v')")
        if not get("add_control_adapter", False):
            problems.append("add_control_adapter is false (no camera adapter: not a Control-Camera checkpoint)")
        if get("add_ref_conv", False):
            problems.append("add_ref_conv is true (the full-reference conv of Fun-Control-Ref is not built)")
        if list(get("window_size", (-1, -1))) != [-1, -1]:
            problems.append(f"window_size {get('window_size', None)} (only global attention is built)")
        if not get("qk_norm", True) or not get("cross_attn_norm", True):
            problems.append("qk_norm / cross_attn_norm false (Wan2.1 uses both)")
        if get("cross_attn_type", None) not in (None, "i2v_cross_attn"):
            problems.append(f"cross_attn_type {get('cross_attn_type', None)!r}")
        if problems:
            raise FunCameraWeightsError(f"{source}: not a Wan2.1-Fun Control-Camera config this module builds: "
                                        + "; ".join(problems))
        try:
            return cls(dim=int(get("dim", 2048)), ffn_dim=int(get("ffn_dim", 8192)),
                       num_heads=int(get("num_heads", 16)), num_layers=int(get("num_layers", 32)),
                       in_dim=int(get("in_dim", 16)), out_dim=int(get("out_dim", 16)),
                       text_dim=int(get("text_dim", 4096)), freq_dim=int(get("freq_dim", 256)),
                       image_dim=int(get("image_dim", 1280)), eps=float(get("eps", 1e-6)),
                       patch_size=tuple(get("patch_size", (1, 2, 2))), text_len=int(get("text_len", 512)),
                       in_dim_control_adapter=int(get("in_dim_control_adapter", 24)),
                       downscale_factor_control_adapter=int(get("downscale_factor_control_adapter", 8)),
                       adapter_residual_blocks=int(get("adapter_residual_blocks", 1)),
                       rope_max_seq_len=int(get("rope_max_seq_len", 1024)))
        except ValueError as exc:
            raise FunCameraWeightsError(f"{source}: {exc}") from exc


# --------------------------------------------------------------------------------------------------
# Plücker embedding (videox_fun/data/utils.py)
# --------------------------------------------------------------------------------------------------
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


def parse_re10k_poses(text: str) -> list[list[float]]:
    """A RealEstate10K pose file's camera lines, as ``process_pose_file`` reads them: the first line (the video
    URL) is skipped, each further line is ``timestamp fx fy cx cy k1 k2 w2c(3x4, row-major)`` (19 numbers)."""
    rows = [[float(x) for x in line.strip().split(" ")] for line in text.splitlines()[1:] if line.strip()]
    bad = [i for i, r in enumerate(rows) if len(r) != 19]
    if bad:
        raise ValueError(f"RealEstate10K pose lines must hold 19 numbers; lines {[b + 2 for b in bad][:5]} do not")
    return rows


def fun_camera_plucker_from_re10k(cam_params: Sequence[Sequence[float]], width: int, height: int,
                                  original_pose_width: int = 1280, original_pose_height: int = 720) -> np.ndarray:
    """``process_pose_params(cam_params, width, height, original_pose_width, original_pose_height)``: ``[T, H, W, 6]``.

    ``Camera(entry)``: normalised ``fx, fy, cx, cy = entry[1:5]``, ``w2c = entry[7:]`` as 3x4, ``c2w = inv(w2c)``.
    Aspect ratio: if the poses' ``W/H`` (1280/720 by default) exceeds the sample's, ``fx *= H·(W0/H0) / W``, else
    ``fy *= (W/(W0/H0)) / H``; then pixel intrinsics ``[fx·W, fy·H, cx·W, cy·H]``.
    """
    rows = np.asarray(cam_params, dtype=np.float64)
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


# --------------------------------------------------------------------------------------------------
# Modules
# --------------------------------------------------------------------------------------------------
def pixel_unshuffle(x: torch.Tensor, r: int) -> torch.Tensor:
    """``nn.PixelUnshuffle(r)`` with reshapes only (``[N, C, H·r, W·r]`` -> ``[N, C·r², H, W]``, output channel
    ``c·r² + i·r + j`` from pixel ``(h·r + i, w·r + j)``); exports to plain ONNX Reshape/Transpose."""
    n, c, h, w = x.shape
    x = x.reshape(n, c, h // r, r, w // r, r).permute(0, 1, 3, 5, 2, 4)
    return x.reshape(n, c * r * r, h // r, w // r)


class _ResidualBlock2d(nn.Module):
    """``ResidualBlock`` of wan_camera_adapter.py: ``x + conv2(relu(conv1(x)))``."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(dim, dim, kernel_size=3, padding=1)
        self.conv2 = nn.Conv2d(dim, dim, kernel_size=3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(F.relu(self.conv1(x))) + x


class FunCameraAdapter(nn.Module):
    """``SimpleAdapter``: packed rays ``[B, 24, F, H, W]`` -> ``[B, D, F, H/(8·2), W/(8·2)]`` (frame by frame, 2D).

    Keys as the official module: ``conv.{weight,bias}``, ``residual_blocks.N.conv{1,2}.{weight,bias}``.
    """

    def __init__(self, in_dim: int, out_dim: int, kernel_size: Sequence[int], stride: Sequence[int],
                 downscale_factor: int = 8, num_residual_blocks: int = 1) -> None:
        super().__init__()
        self.downscale_factor = int(downscale_factor)
        self.conv = nn.Conv2d(in_dim * self.downscale_factor ** 2, out_dim, kernel_size=tuple(kernel_size),
                              stride=tuple(stride), padding=0)
        self.residual_blocks = nn.Sequential(*[_ResidualBlock2d(out_dim) for _ in range(num_residual_blocks)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, f, h, w = x.shape
        x = x.permute(0, 2, 1, 3, 4).reshape(b * f, c, h, w)
        x = self.residual_blocks(self.conv(pixel_unshuffle(x, self.downscale_factor)))
        return x.reshape(b, f, *x.shape[1:]).permute(0, 2, 1, 3, 4)


class FunCameraWan(nn.Module):
    """``base`` (diffusers ``WanTransformer3DModel``, I2V, 32 input channels) + ``control_adapter``.

    ``forward(hidden_states [B, 32, F, h, w], timestep [B], encoder_hidden_states [B, 512, text_dim],
    encoder_hidden_states_image [B, 257, image_dim], plucker [B, 6, 4(F-1)+1, 8h, 8w] | None) -> [B, 16, F, h, w]``.
    ``plucker`` are the raw rays (``fun_camera_plucker``, channels first); the packing is inside. The trailing
    arguments of NavCrafter's DiT (``cond``, ``lora_scale``, ``image_reference``, ``image_reference_plucker``) are
    accepted so that one sampler drives both models: ``lora_scale`` is ignored (no LoRA), the others must be None.
    """

    model_name = MODEL_NAME

    def __init__(self, config: FunCameraConfig, base: WanTransformer3DModel | None = None) -> None:
        super().__init__()
        self.config = config
        self.base = base if base is not None else WanTransformer3DModel(**config.diffusers_kwargs())
        p = config.patch_size
        self.control_adapter = FunCameraAdapter(config.in_dim_control_adapter, config.dim, p[1:], p[1:],
                                                config.downscale_factor_control_adapter,
                                                config.adapter_residual_blocks)
        self.control_adapter.to(device=self.base.device, dtype=self.base.dtype)

    def forward(self, hidden_states: torch.Tensor, timestep: torch.Tensor, encoder_hidden_states: torch.Tensor,
                encoder_hidden_states_image: torch.Tensor | None = None, plucker: torch.Tensor | None = None,
                cond: torch.Tensor | None = None, lora_scale: Any = None, image_reference: torch.Tensor | None = None,
                image_reference_plucker: torch.Tensor | None = None) -> torch.Tensor:
        if cond is not None or image_reference is not None or image_reference_plucker is not None:
            raise ValueError("the fun-camera DiT has no render condition or extra reference frames (cond, "
                             "image_reference, image_reference_plucker must be None)")
        base, cfg = self.base, self.config
        batch_size, channels, num_frames, height, width = hidden_states.shape
        if channels != cfg.in_dim:
            raise ValueError(f"hidden_states must have {cfg.in_dim} channels ([noisy 16 | start-image latents 16]), "
                             f"got {channels}")
        p_t, p_h, p_w = cfg.patch_size
        st = cfg.temporal_packing
        ds = cfg.downscale_factor_control_adapter
        ppf, pph, ppw = num_frames // p_t, height // p_h, width // p_w

        rotary_emb = base.rope(hidden_states)
        x = base.patch_embedding(hidden_states)
        if plucker is not None:
            want = (batch_size, PLUCKER_CHANNELS, (num_frames - 1) * st + 1, height * ds, width * ds)
            if tuple(plucker.shape) != want:
                raise ValueError(f"plucker must be [B, 6, {st}(F-1)+1, {ds}h, {ds}w] = {want} for hidden_states "
                                 f"{tuple(hidden_states.shape)}, got {tuple(plucker.shape)}")
            x = x + self.control_adapter(fun_camera_pack(plucker.to(x.dtype), st))
        x = x.flatten(2).transpose(1, 2).contiguous()

        temb, timestep_proj, encoder_hidden_states, encoder_hidden_states_image = base.condition_embedder(
            timestep, encoder_hidden_states, encoder_hidden_states_image, timestep_seq_len=None)
        timestep_proj = timestep_proj.unflatten(1, (6, -1))
        if encoder_hidden_states_image is not None:
            encoder_hidden_states = torch.concat([encoder_hidden_states_image, encoder_hidden_states], dim=1)
        for block in base.blocks:
            x = block(x, encoder_hidden_states, timestep_proj, rotary_emb)

        shift, scale = (base.scale_shift_table.to(temb.device) + temb.unsqueeze(1)).chunk(2, dim=1)
        x = (base.norm_out(x.float()) * (1 + scale) + shift).type_as(x)
        x = base.proj_out(x)
        x = x.reshape(batch_size, ppf, pph, ppw, p_t, p_h, p_w, -1).permute(0, 7, 1, 4, 2, 5, 3, 6)
        return x.flatten(6, 7).flatten(4, 5).flatten(2, 3)


def build_fun_camera(config: FunCameraConfig, seed: int = 0, device: str | torch.device | None = None,
                     dtype: torch.dtype | None = None) -> FunCameraWan:
    """A randomly initialised (seeded; the global RNG is untouched) ``FunCameraWan`` in eval mode."""
    devices = [torch.device(device)] if device is not None and torch.device(device).type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        with torch.device(device or "cpu"):
            model = FunCameraWan(config)
    if dtype is not None:
        model = model.to(dtype)
    return model.eval()


def tiny_fun_camera(seed: int = 0) -> FunCameraWan:
    return build_fun_camera(FunCameraConfig.tiny(), seed=seed)


# --------------------------------------------------------------------------------------------------
# Official checkpoint layout <-> ours
# --------------------------------------------------------------------------------------------------
_TOP = {"patch_embedding": "base.patch_embedding",
        "text_embedding.0": "base.condition_embedder.text_embedder.linear_1",
        "text_embedding.2": "base.condition_embedder.text_embedder.linear_2",
        "time_embedding.0": "base.condition_embedder.time_embedder.linear_1",
        "time_embedding.2": "base.condition_embedder.time_embedder.linear_2",
        "time_projection.1": "base.condition_embedder.time_proj",
        "img_emb.proj.0": "base.condition_embedder.image_embedder.norm1",
        "img_emb.proj.1": "base.condition_embedder.image_embedder.ff.net.0.proj",
        "img_emb.proj.3": "base.condition_embedder.image_embedder.ff.net.2",
        "img_emb.proj.4": "base.condition_embedder.image_embedder.norm2",
        "head.head": "base.proj_out"}
# inside blocks.N. (the official norm3 is the affine cross-attention norm, diffusers' norm2)
_BLOCK = {"self_attn.q": "attn1.to_q", "self_attn.k": "attn1.to_k", "self_attn.v": "attn1.to_v",
          "self_attn.o": "attn1.to_out.0", "self_attn.norm_q": "attn1.norm_q", "self_attn.norm_k": "attn1.norm_k",
          "cross_attn.q": "attn2.to_q", "cross_attn.k": "attn2.to_k", "cross_attn.v": "attn2.to_v",
          "cross_attn.o": "attn2.to_out.0", "cross_attn.norm_q": "attn2.norm_q", "cross_attn.norm_k": "attn2.norm_k",
          "cross_attn.k_img": "attn2.add_k_proj", "cross_attn.v_img": "attn2.add_v_proj",
          "cross_attn.norm_k_img": "attn2.norm_added_k", "norm3": "norm2", "ffn.0": "ffn.net.0.proj",
          "ffn.2": "ffn.net.2"}
_TOP_INV = {v: k for k, v in _TOP.items()}
_BLOCK_INV = {v: k for k, v in _BLOCK.items()}
_BLOCK_RE = re.compile(r"^blocks\.(\d+)\.(.+)\.(weight|bias)$")
_OUR_BLOCK_RE = re.compile(r"^base\.blocks\.(\d+)\.(.+)\.(weight|bias)$")


def official_to_ours(key: str) -> str | None:
    """Our parameter name of an official key (None: not a key of this architecture)."""
    if key.startswith("control_adapter."):
        return key
    if key == "head.modulation":
        return "base.scale_shift_table"
    m = re.match(r"^blocks\.(\d+)\.modulation$", key)
    if m:
        return f"base.blocks.{m.group(1)}.scale_shift_table"
    m = _BLOCK_RE.match(key)
    if m:
        inner = _BLOCK.get(m.group(2))
        return None if inner is None else f"base.blocks.{m.group(1)}.{inner}.{m.group(3)}"
    stem, _, leaf = key.rpartition(".")
    if stem in _TOP and leaf in ("weight", "bias"):
        return f"{_TOP[stem]}.{leaf}"
    return None


def ours_to_official(key: str) -> str:
    if key.startswith("control_adapter."):
        return key
    if key == "base.scale_shift_table":
        return "head.modulation"
    m = re.match(r"^base\.blocks\.(\d+)\.scale_shift_table$", key)
    if m:
        return f"blocks.{m.group(1)}.modulation"
    m = _OUR_BLOCK_RE.match(key)
    if m and m.group(2) in _BLOCK_INV:
        return f"blocks.{m.group(1)}.{_BLOCK_INV[m.group(2)]}.{m.group(3)}"
    stem, _, leaf = key.rpartition(".")
    if stem in _TOP_INV:
        return f"{_TOP_INV[stem]}.{leaf}"
    raise KeyError(f"{key}: no official name (not a parameter of the Fun-Camera layout)")


def _official_order(name: str) -> tuple:
    """The official state_dict order: embeddings, blocks (modulation first, then self_attn, norm3, cross_attn,
    ffn), head, img_emb, control_adapter."""
    top = ["patch_embedding", "text_embedding", "time_embedding", "time_projection", "blocks", "head", "img_emb",
           "control_adapter"]
    parts = name.split(".")
    rank = top.index(parts[0])
    if parts[0] == "blocks":
        stem, leaf = ".".join(parts[2:-1]), parts[-1]
        sub = ["", "self_attn.q", "self_attn.k", "self_attn.v", "self_attn.o", "self_attn.norm_q", "self_attn.norm_k",
               "norm3", "cross_attn.q", "cross_attn.k", "cross_attn.v", "cross_attn.o", "cross_attn.norm_q",
               "cross_attn.norm_k", "cross_attn.k_img", "cross_attn.v_img", "cross_attn.norm_k_img", "ffn.0", "ffn.2"]
        idx = sub.index(stem)  # "" = blocks.N.modulation
        return (rank, int(parts[1]), idx, leaf == "bias")
    if parts[0] == "head":
        return (rank, 0, 0 if parts[1] == "modulation" else 1, parts[-1] == "bias")
    return (rank, 0, 0, 0)


def official_layout(model: FunCameraWan) -> dict[str, tuple[int, ...]]:
    """Official names -> shapes of ``model``'s parameters, in the official state_dict order (works on meta)."""
    names = {ours_to_official(k): tuple(v.shape) for k, v in model.state_dict().items()}
    order = sorted(names, key=lambda n: (_official_order(n), list(names).index(n)))
    return {n: names[n] for n in order}


def read_key_list(path: str | os.PathLike = KEY_LIST_1_3B) -> tuple[dict[str, Any], dict[str, tuple[int, ...]]]:
    """The committed official layout: (its header, official key -> shape in file order)."""
    d = json.loads(Path(path).read_text())
    layout = {k: tuple(int(s) for s in shape) for k, shape in d["keys"]}
    return {k: v for k, v in d.items() if k != "keys"}, layout


def check_layout(found: dict[str, Sequence[int]], expected: dict[str, Sequence[int]], source: str) -> None:
    """Strict key and shape check; ``FunCameraWeightsError`` naming what is missing, unexpected or mis-shaped."""
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    mismatched = [f"{k}: file {list(found[k])} vs model {list(expected[k])}" for k in sorted(set(found) & set(expected))
                  if tuple(found[k]) != tuple(expected[k])]
    if not (missing or unexpected or mismatched):
        return
    problems = []
    if missing:
        problems.append(f"missing keys [{_short(missing)}]")
    if unexpected:
        problems.append(f"unexpected keys [{_short(unexpected)}]")
    if mismatched:
        problems.append(f"shape mismatch [{_short(mismatched)}]")
    raise FunCameraWeightsError(
        f"{source}: not the Wan2.1-Fun Control-Camera layout its config.json describes: " + "; ".join(problems)
        + ". Pass the official transformer folder (config.json + diffusion_pytorch_model*.safetensors of "
        "alibaba-pai/Wan2.1-Fun-V1.1-{1.3B,14B}-Control-Camera), unmodified, with the config.json it came with")


def _weight_files(directory: Path) -> list[Path]:
    index = directory / OFFICIAL_INDEX
    if index.is_file():
        shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        return [directory / s for s in shards]
    single = directory / OFFICIAL_WEIGHTS
    if single.is_file():
        return [single]
    found = sorted(directory.glob("diffusion_pytorch_model*.safetensors"))
    if found:
        return found
    pickles = sorted(p.name for p in directory.glob("*.pth")) + sorted(p.name for p in directory.glob("*.bin"))
    extra = f" (found {pickles}: only safetensors are read)" if pickles else ""
    raise FileNotFoundError(f"{directory}: no {OFFICIAL_WEIGHTS} or {OFFICIAL_INDEX}{extra}")


def _transformer_dir(directory: Path) -> Path:
    """The official model folder holds the transformer at its root (``transformer_subpath: ./``); a folder with a
    ``transformer/`` sub-folder is accepted too."""
    if (directory / OFFICIAL_CONFIG).is_file():
        return directory
    if (directory / "transformer" / OFFICIAL_CONFIG).is_file():
        return directory / "transformer"
    raise FileNotFoundError(f"{directory}: no {OFFICIAL_CONFIG} (the official Wan2.1-Fun-V1.1-*-Control-Camera "
                            f"folder has config.json and diffusion_pytorch_model.safetensors at its root)")


def read_fun_camera_config(directory: str | os.PathLike) -> FunCameraConfig:
    d = _transformer_dir(Path(directory))
    return FunCameraConfig.from_official_config(json.loads((d / OFFICIAL_CONFIG).read_text()),
                                                str(d / OFFICIAL_CONFIG))


def load_fun_camera(directory: str | os.PathLike, torch_dtype: torch.dtype | None = None) -> FunCameraWan:
    """``FunCameraWan`` from the official checkpoint folder (``config.json`` + safetensors, single or sharded).

    The architecture is built from ``config.json`` on the meta device, every tensor name and shape of the files is
    checked against it (``check_layout``: missing, unexpected and wrong-shape keys are all refused, unlike the
    official loader, which skips mismatches and initialises missing keys), then the tensors are loaded. Float32 by
    default (what the ONNX export runs); ``torch_dtype`` casts.
    """
    from safetensors import safe_open

    d = _transformer_dir(Path(directory))
    config = read_fun_camera_config(d)
    with torch.device("meta"):
        expected = official_layout(FunCameraWan(config))
    files = _weight_files(d)
    found: dict[str, tuple[int, ...]] = {}
    where: dict[str, Path] = {}
    for f in files:
        if not f.is_file():
            raise FileNotFoundError(f"{f}: listed in {OFFICIAL_INDEX} but missing")
        with safe_open(str(f), framework="pt") as sf:
            for k in sf.keys():
                if k in found:
                    raise FunCameraWeightsError(f"{f}: key {k} also in {where[k]}")
                found[k], where[k] = tuple(sf.get_slice(k).get_shape()), f
    check_layout(found, expected, str(d))
    model = FunCameraWan(config)
    state = {}
    for f in files:
        with safe_open(str(f), framework="pt") as sf:
            for k in sf.keys():
                state[official_to_ours(k)] = sf.get_tensor(k).to(torch_dtype or torch.float32)
    model.load_state_dict(state, strict=True)
    if torch_dtype is not None:
        model = model.to(torch_dtype)
    return model.eval()


def fun_camera_state_dict_official(model: FunCameraWan) -> dict[str, torch.Tensor]:
    """``model``'s weights under the official names, in the official order."""
    ours = model.state_dict()
    by_official = {ours_to_official(k): v for k, v in ours.items()}
    return {k: by_official[k].detach().contiguous().cpu() for k in official_layout(model)}


def save_fun_camera(model: FunCameraWan, directory: str | os.PathLike) -> Path:
    """Write the official layout (``config.json`` + ``diffusion_pytorch_model.safetensors``) that
    ``load_fun_camera`` (and the official loader) reads; the config is written last (temp file + rename)."""
    from safetensors.torch import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    tmp = directory / (OFFICIAL_WEIGHTS + ".tmp")
    save_file(fun_camera_state_dict_official(model), str(tmp), metadata={"format": "pt"})
    os.replace(tmp, directory / OFFICIAL_WEIGHTS)
    tmp = directory / (OFFICIAL_CONFIG + ".tmp")
    tmp.write_text(json.dumps(model.config.official_config(), indent=2))
    os.replace(tmp, directory / OFFICIAL_CONFIG)
    return directory


# --------------------------------------------------------------------------------------------------
# NavCrafter control initialised from Fun-Camera (the shared Wan2.1 base)
# --------------------------------------------------------------------------------------------------
@torch.no_grad()
def init_navcrafter_from_fun_camera(fun: FunCameraWan, control_config=None):
    """A ``camcontrol.CameraControlledWan`` whose **base** is Fun-Camera's DiT and whose control is fresh
    (zero-initialised, so the result equals that base exactly until trained).

    What transfers: every base tensor (embeddings, blocks, head, CLIP ``img_emb``) has the same name and shape
    in both layouts except the patch embedding, whose 32 input channels ``[noisy | start image]`` are placed at
    NavCrafter's 36-channel I2V layout ``[noisy (0:16) | mask (16:20) | condition (20:36)]`` with zero weights on
    the mask channels (Fun-Camera was trained without a mask). What does not: the camera adapter
    (``SimpleAdapter``: one 2D pixel-unshuffle conv added once after the patch embedding, on un-normalised
    ``(o x d, d)`` rays) has no counterpart in NavCrafter's control (3D-conv adapter projected into every block,
    LoRA encoder, reference attention, render embedding), so the control starts from zero. See
    models/synthesis/README.md ("Fun-Camera").
    """
    from navcrafter.models.synthesis.camcontrol import CameraControlledWan

    cfg = fun.config
    kwargs = {**cfg.diffusers_kwargs(), "in_channels": 2 * LATENT_CHANNELS + 4}
    with torch.device(fun.base.device):
        base = WanTransformer3DModel(**kwargs).to(fun.base.dtype)
    src = fun.base.state_dict()
    dst = base.state_dict()
    if set(src) != set(dst):
        raise FunCameraWeightsError(f"the base layouts differ: {_short(sorted(set(src) ^ set(dst)))}")
    for k, v in src.items():
        if k == "patch_embedding.weight":
            w = torch.zeros_like(dst[k])
            w[:, :LATENT_CHANNELS] = v[:, :LATENT_CHANNELS]
            w[:, LATENT_CHANNELS + 4:] = v[:, LATENT_CHANNELS:]
            dst[k].copy_(w)
        else:
            dst[k].copy_(v)
    return CameraControlledWan(base.eval(), control_config).eval()


# --------------------------------------------------------------------------------------------------
# ONNX export
# --------------------------------------------------------------------------------------------------
class _FunExportWrapper(nn.Module):
    def __init__(self, model: FunCameraWan) -> None:
        super().__init__()
        self.model = model

    def forward(self, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker):
        return self.model(hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker)


def fun_example_inputs(model: FunCameraWan, example_shape: Sequence[int], image_tokens: int = 257,
                       seed: int = 0) -> dict[str, torch.Tensor]:
    """Random inputs named as the graph's; ``example_shape = (batch, F, h, w)`` in latent units."""
    b, f, h, w = (int(v) for v in example_shape)
    c = model.config
    st, ds = c.temporal_packing, c.downscale_factor_control_adapter
    g = torch.Generator().manual_seed(seed)
    dtype = model.base.dtype

    def r(*shape):
        return torch.randn(*shape, generator=g).to(dtype)

    return {"hidden_states": r(b, c.in_dim, f, h, w), "timestep": torch.linspace(100.0, 900.0, b).to(dtype),
            "encoder_hidden_states": r(b, TEXT_TOKENS, c.text_dim),
            "encoder_hidden_states_image": r(b, image_tokens, c.image_dim),
            "plucker": r(b, PLUCKER_CHANNELS, (f - 1) * st + 1, h * ds, w * ds)}


def export_fun_camera_dit(model: FunCameraWan, out_path: str | os.PathLike, example_shape: Sequence[int] = (2, 2, 4, 4),
                          image_tokens: int = 257, dynamic: bool = True):
    """Export the Fun-Camera DiT to ONNX (``out_path`` + ``.data``): inputs ``FUN_DIT_INPUTS`` -> ``noise_pred``.

    ``dynamic``: batch, latent frames, height, width and image tokens dynamic (text fixed at 512), else exactly
    ``example_shape``."""
    from torch.export import Dim

    from navcrafter.models.runtime.onnxio import export_graph

    b, f, h, w = (int(v) for v in example_shape)
    p_t, p_h, p_w = model.config.patch_size
    if p_t != 1 or h % p_h or w % p_w or f < 2 or b < 1:
        raise ValueError(f"example_shape (batch, F, h, w) needs F >= 2 and h, w multiples of the patch "
                         f"({p_h}, {p_w}); got {tuple(example_shape)}")
    inputs = fun_example_inputs(model, example_shape, image_tokens)
    st, ds = model.config.temporal_packing, model.config.downscale_factor_control_adapter
    dynamic_shapes = None
    if dynamic:
        rope_max = model.config.rope_max_seq_len
        batch = Dim("batch", min=1, max=1024)
        frames = Dim("latent_frames", min=2, max=rope_max)
        hh, hw = Dim("half_height", min=1, max=rope_max), Dim("half_width", min=1, max=rope_max)
        dynamic_shapes = ({0: batch, 2: frames, 3: p_h * hh, 4: p_w * hw}, {0: batch}, {0: batch},
                          {0: batch, 1: Dim("image_tokens", min=2, max=4096)},
                          {0: batch, 2: st * frames - (st - 1), 3: ds * p_h * hh, 4: ds * p_w * hw})
    info = export_graph(_FunExportWrapper(model).eval(), tuple(inputs[n] for n in FUN_DIT_INPUTS), Path(out_path),
                        input_names=list(FUN_DIT_INPUTS), output_names=list(FUN_DIT_OUTPUTS),
                        dynamic_shapes=dynamic_shapes)
    info.notes = (f"Wan2.1-Fun Control-Camera DiT (VideoX-Fun); plucker_convention={PLUCKER_CONVENTION} "
                  f"(fun_camera_plucker: (o x d, d), first camera = identity, no scale); input "
                  f"[noisy 16 | start-image latents 16]; text tokens fixed at {TEXT_TOKENS}"
                  + ("" if dynamic else f"; static shapes {tuple(example_shape)}"))
    return info

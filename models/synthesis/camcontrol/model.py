"""Camera-controlled Wan2.1 DiT (NavCrafter's multi-stage camera control) on top of diffusers' Wan.

The base model is diffusers' ``WanTransformer3DModel`` (Wan2.1 I2V layout), used as-is: its rope, patch
embedding, condition embedder, blocks, output norm and projection. ``CameraControlledWan`` wraps it and
adds four zero-initialised control paths, so an untrained wrapper returns exactly the base output:

1. **Camera adapter A (dual-branch injection).** A 3D-conv encoder maps per-pixel Plücker rays
   ``[B, 6, T, 8h, 8w]`` to tokens ``x_c [B, L, D]`` on the DiT's token grid (``L = F * h/2 * w/2``).
   In every block ``i``: ``hidden += P_i(x_c)`` before the block, and inside the block's self-attention
   ``attn_out += S_i(x_c)`` (after ``to_out``, before the block's gate). ``P_i``/``S_i`` (``pre_proj`` /
   ``attn_proj``) are low-rank ``D -> r -> D`` (``projection_rank`` ``r``, capped at ``D``; the down
   projection random, the up projection zero-initialised): a full ``Linear(D, D)`` pair per block is ~2.1 B
   parameters on Wan2.1-I2V-14B, ~13 % of the base (``control_parameter_counts``). ``projection_rank = 0``
   is the full zero-initialised ``Linear(D, D)`` of format-version-1 weights.
2. **LoRA control.** A lightweight 3D-conv encoder maps the same Plücker rays to ``x_l [B, L, r_in]``; in
   every block's self-attention ``Q' = Q + α·U_q(D_q x_l)`` (same for K and V) on the projection outputs,
   before the q/k RMS norms and rope. ``U_*`` are zero-initialised; ``α`` (``lora_scale``) is an input so
   the sampler can choose it (the paper uses 0.7).
3. **Reference-frame attention.** A set of latent frames ``S`` (always including frame 0) are *reference
   frames*: their **clean** latents are patch-embedded (``ref_embedding``, initialised from the base patch
   embedding as "a known clean frame") into reference tokens placed at their frame's rope position, and
   every video token attends to them in a second, decoupled attention inside each self-attention::

       r_i     = ref_tokens + P_i(x_c)[S]                     (camera of the reference frame)
       K_r,V_r = norm_k(W_k LN(r_i)), W_v LN(r_i)             (the block's own projections, rope at S)
       attn    = SDPA(Q, K, V) + [SDPA(Q, K_img, V_img)] + g_i ⊙ SDPA(Q, K_r, V_r)

   with a per-channel gate ``g_i`` initialised to zero (a decoupled branch, like Wan's image branch,
   keeps the base attention's softmax untouched, which concatenating keys would not). During training
   (``model.train()``) ``S`` is ``{0} ∪`` a random subset of ``num_reference_frames - 1`` other latent
   frames drawn from a seeded generator, and the clean latents come from ``reference_latents`` (the
   training loop passes the clean video latents). At inference ``S = inference_reference_frames`` (default
   ``(0,)``, baked into an exported graph) and the clean latents are the I2V conditioning latents
   (channels 20:36 of ``hidden_states``), whose frame 0 is the encoded conditioning image.
   **Extra reference frames** (``image_reference [B, 16, R, h, w]``, clean latents of views outside the clip,
   e.g. the scene's input photo when a clip starts elsewhere, with their rays ``image_reference_plucker
   [B, 6, R, 8h, 8w]`` in the clip's Plücker frame: ``models.camera.cameras.clip_relative_rays``) join the
   same reference set: patch-embedded with ``ref_embedding``, their camera tokens are the adapter run on each
   frame's rays as a one-frame clip (``x_c`` of that frame), and their rope is the one of latent frame 0 (a
   known clean frame at the start of the clip, like the I2V conditioning frame: where the view is comes from
   its camera tokens, not from a time position it does not have).
4. **Render conditioning.** ``cond [B, cond_channels, F, h, w]`` enters through an extended patch
   embedding: ``patch_embedding(hidden_states) + cond_embedding(cond)``, which equals one Conv3d over the
   concatenated channels whose new input channels are zero-initialised. The default ``cond_channels = 20``
   is ``16`` VAE latents of the current point cloud rendered along the trajectory + ``4`` visibility-mask
   channels packed exactly like Wan's I2V mask (``pack_visibility_mask``): channel ``c`` of latent frame
   ``k`` is the (8×8 average-pooled) visibility of video frame ``4k - 3 + c`` (frame 0 for all four
   channels of latent frame 0).

**Plücker convention** (``CameraControlConfig.plucker_convention``, default ``"relative"``): rays are computed
from the clip's poses made relative to its first camera and scale-normalised by the clip's largest translation
(CameraCtrl-style, as RealEstate10K/DL3DV training clips are), then the true Plücker line of each pixel ray;
``"ray"`` and ``"paper"`` (the paper's literal ``d = normalise(RK^-1[u,v,1] + t)``) on absolute world poses stay
selectable (see ``models.camera.cameras.plucker_rays``). The convention is saved with the weights and recorded in
an exported synthesizer's manifest.

Temporal alignment follows the Wan VAE: latent frame 0 is video frame 0, latent frame ``k ≥ 1`` covers video
frames ``4k-3 .. 4k``; so ``T = 4(F - 1) + 1``. Both Plücker encoders repeat frame 0 three times in front
(``4F`` frames) and patchify with stride 4 in time.

Weights: the base comes from a diffusers-format directory; the control weights are one safetensors file
plus a JSON config (``save_camera_control`` / ``load_camera_control``), never pickles. Format version 2 (low-rank
projections, ``projection_rank`` in the config); version-1 files load as ``projection_rank = 0`` with the
convention they record.
The whole wrapper exports to ONNX (``export_dit``) with dynamic batch, frames, height, width and number of extra
reference frames.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F
from diffusers.models.attention_dispatch import dispatch_attention_fn
from diffusers.models.transformers.transformer_wan import WanTransformer3DModel, _get_qkv_projections

from navcrafter.models.camera.cameras import PLUCKER_CONVENTIONS, PluckerConvention

VAE_STRIDE = (4, 8, 8)  # Wan2.1 VAE: time, height, width
LATENT_CHANNELS = 16  # Wan2.1 VAE latent channels
TEXT_TOKENS = 512  # diffusers' Wan I2V path splits image/text tokens at `shape[1] - 512`
CONTROL_WEIGHTS = "camera_control.safetensors"
CONTROL_CONFIG = "camera_control.json"
CONTROL_FORMAT = "navcrafter-camera-control"
CONTROL_FORMAT_VERSION = 2  # 2: low-rank pre_proj/attn_proj (projection_rank); 1: full Linear(D, D)
READABLE_FORMAT_VERSIONS = (1, 2)
# what a version-1 config lacks, as version 1 built it
_V1_DEFAULTS: dict[str, Any] = {"projection_rank": 0, "plucker_convention": "paper"}

DIT_INPUTS = ["hidden_states", "timestep", "encoder_hidden_states", "encoder_hidden_states_image", "plucker",
              "cond", "lora_scale", "image_reference", "image_reference_plucker"]
DIT_OUTPUTS = ["noise_pred"]

# Tiny random Wan2.1 I2V config for tests (see shared/FACTS.md): 2 heads x 12 dims, 2 layers.
TINY_I2V_CONFIG: dict[str, Any] = {
    "patch_size": (1, 2, 2), "num_attention_heads": 2, "attention_head_dim": 12, "in_channels": 36,
    "out_channels": 16, "text_dim": 32, "freq_dim": 256, "ffn_dim": 32, "num_layers": 2, "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads", "eps": 1e-6, "image_dim": 4, "added_kv_proj_dim": 24,
    "rope_max_seq_len": 32,
}

# Wan2.1-1.3B width with the I2V input layout (Wan2.1 has no official 1.3B I2V checkpoint; this is what a
# 1.3B-width I2V/camera model looks like). diffusers needs added_kv_proj_dim == inner_dim (12*128 = 1536):
# add_k_proj/add_v_proj act on the CLIP tokens *after* the condition embedder projected them to inner_dim.
WAN_1_3B_I2V_CONFIG: dict[str, Any] = {
    "patch_size": (1, 2, 2), "num_attention_heads": 12, "attention_head_dim": 128, "in_channels": 36,
    "out_channels": 16, "text_dim": 4096, "freq_dim": 256, "ffn_dim": 8960, "num_layers": 30, "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads", "eps": 1e-6, "image_dim": 1280, "added_kv_proj_dim": 1536,
    "rope_max_seq_len": 1024,
}

# Wan2.1-I2V-14B (the diffusers transformer config of Wan-AI/Wan2.1-I2V-14B-*-Diffusers): 40 heads x 128 = 5120,
# 40 layers; added_kv_proj_dim == inner_dim as above.
WAN_14B_I2V_CONFIG: dict[str, Any] = {
    "patch_size": (1, 2, 2), "num_attention_heads": 40, "attention_head_dim": 128, "in_channels": 36,
    "out_channels": 16, "text_dim": 4096, "freq_dim": 256, "ffn_dim": 13824, "num_layers": 40, "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads", "eps": 1e-6, "image_dim": 1280, "added_kv_proj_dim": 5120,
    "rope_max_seq_len": 1024,
}


class CameraControlWeightsError(ValueError):
    """Camera-control weights do not fit the model (file, keys and shapes are named in the message)."""


# --------------------------------------------------------------------------------------------------
# Config
# --------------------------------------------------------------------------------------------------
TRAINING_LORA_SCALE = 1.0  # the camera LoRA's strength while it is trained (inference: CameraControlConfig.lora_scale)


@dataclass
class CameraControlConfig:
    """Hyper-parameters of the camera-control modules (the base DiT's sizes come from the base config).

    ``adapter_channels``/``adapter_res_blocks``: width/depth of the camera adapter A.
    ``lora_in_channels`` (``r_in``) and ``lora_rank``: the LoRA control encoder width and the LoRA rank.
    ``lora_scale``: default ``α`` at inference when the caller passes none (the paper's 0.7; the sampler passes
    ``synthesis.lora_scale`` explicitly); in training mode the default is ``TRAINING_LORA_SCALE`` (1.0).
    ``cond_channels``: extra patch-embedding channels (16 render latents + 4 packed visibility mask).
    ``num_reference_frames``: reference frames drawn per training sample (frame 0 included).
    ``inference_reference_frames``: reference latent frames at inference (baked into an export).
    ``reference_seed``: seed of the training-time reference-frame generator.
    ``projection_rank``: rank ``r`` of the per-block ``pre_proj``/``attn_proj`` (``D -> r -> D``, capped at the
    DiT width ``D``); ``0`` = full ``Linear(D, D)`` (format-version-1 weights; a saved config without the field
    loads as 0).
    ``plucker_convention``: how the Plücker rays were computed (``models.camera.cameras.plucker_rays``:
    ``"relative"`` (default), ``"ray"`` or ``"paper"``); recorded so the weights are always run with the
    convention they were trained with (saved configs keep the one they record).
    """

    adapter_channels: int = 64
    adapter_res_blocks: int = 1
    lora_in_channels: int = 32
    lora_rank: int = 16
    lora_scale: float = 0.7
    cond_channels: int = 20
    num_reference_frames: int = 2
    inference_reference_frames: tuple[int, ...] = (0,)
    reference_seed: int = 0
    projection_rank: int = 64
    plucker_convention: PluckerConvention = "relative"  # models.camera.cameras.plucker_rays default
    latent_channels: int = LATENT_CHANNELS
    vae_stride: tuple[int, int, int] = VAE_STRIDE
    extra: dict[str, Any] = field(default_factory=dict)  # free-form notes (training run, data, ...)

    def __post_init__(self) -> None:
        self.inference_reference_frames = tuple(int(i) for i in self.inference_reference_frames)
        self.vae_stride = tuple(int(s) for s in self.vae_stride)
        if self.plucker_convention not in PLUCKER_CONVENTIONS:
            raise ValueError(f"plucker_convention must be one of {list(PLUCKER_CONVENTIONS)}, "
                             f"got {self.plucker_convention!r}")
        if int(self.projection_rank) < 0:
            raise ValueError(f"projection_rank must be >= 0 (0 = full D x D projections), got {self.projection_rank}")
        for name in ("adapter_channels", "lora_in_channels", "lora_rank", "latent_channels"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.cond_channels < 0 or self.adapter_res_blocks < 0 or self.num_reference_frames < 0:
            raise ValueError("cond_channels, adapter_res_blocks and num_reference_frames must be >= 0")
        if self.inference_reference_frames and min(self.inference_reference_frames) < 0:
            raise ValueError(f"inference_reference_frames must be >= 0, got {self.inference_reference_frames}")
        if len(self.vae_stride) != 3:
            raise ValueError(f"vae_stride must have 3 entries (t, h, w), got {self.vae_stride}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["inference_reference_frames"] = list(self.inference_reference_frames)
        d["vae_stride"] = list(self.vae_stride)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraControlConfig:
        """A saved config. One without ``projection_rank`` predates low-rank projections: it loads as 0."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown CameraControlConfig keys {unknown}; known: {sorted(known)}")
        return cls(**{"projection_rank": 0, **d})


def tiny_camera_config() -> CameraControlConfig:
    """Tiny test control (``projection_rank`` 64, capped at the tiny DiT's width 24)."""
    return CameraControlConfig(adapter_channels=16, adapter_res_blocks=1, lora_in_channels=8, lora_rank=4,
                               num_reference_frames=2)


def wan_1_3b_camera_config() -> tuple[dict[str, Any], CameraControlConfig]:
    """(base ``WanTransformer3DModel`` kwargs at Wan2.1-1.3B width with I2V inputs, control config).

    Build with random weights: ``build_camera_wan(*wan_1_3b_camera_config(), device="cuda")``.
    Rank-128 projections: 47 M control parameters, 3.0 % of the 1.56 B base (full-rank ones are 142 M at D=1536,
    30 layers: 165 M, 10.6 %, with the encoders); see ``control_parameter_counts`` and models/synthesis/README.md.
    """
    return dict(WAN_1_3B_I2V_CONFIG), CameraControlConfig(adapter_channels=320, adapter_res_blocks=2,
                                                          lora_in_channels=128, lora_rank=64,
                                                          projection_rank=128, num_reference_frames=3)


def wan_14b_camera_config() -> tuple[dict[str, Any], CameraControlConfig]:
    """(Wan2.1-I2V-14B base kwargs, control config): rank-256 projections, 266 M control parameters, 1.6 % of the
    16.4 B base (full-rank ones are 2.10 B: 2.15 B, 13.1 %, in all). Counts: ``control_parameter_counts``."""
    return dict(WAN_14B_I2V_CONFIG), CameraControlConfig(adapter_channels=320, adapter_res_blocks=2,
                                                         lora_in_channels=128, lora_rank=64,
                                                         projection_rank=256, num_reference_frames=3)


# --------------------------------------------------------------------------------------------------
# Helpers: frames, masks, reference selection
# --------------------------------------------------------------------------------------------------
def latent_frames(num_video_frames: int, temporal_stride: int = 4) -> int:
    """Wan VAE: video frame 0 is latent frame 0, then ``temporal_stride`` video frames per latent frame."""
    if num_video_frames < 1 or (num_video_frames - 1) % temporal_stride:
        raise ValueError(f"number of video frames must be {temporal_stride}k+1, got {num_video_frames}")
    return (num_video_frames - 1) // temporal_stride + 1


def video_frames(num_latent_frames: int, temporal_stride: int = 4) -> int:
    return (num_latent_frames - 1) * temporal_stride + 1


def _pad_first_frame(x: torch.Tensor, temporal_stride: int) -> torch.Tensor:
    """``[B, C, T, H, W]`` -> ``[B, C, T + s - 1, H, W]``: frame 0 repeated so it forms its own group."""
    if temporal_stride == 1:
        return x
    first = x[:, :, :1].expand(-1, -1, temporal_stride - 1, -1, -1)
    return torch.cat([first, x], dim=2)


def pack_visibility_mask(mask: torch.Tensor, vae_stride: Sequence[int] = VAE_STRIDE) -> torch.Tensor:
    """Pixel visibility ``[B, T, H, W]`` (1 = the point cloud covers the pixel) to ``[B, 4, F, H/8, W/8]``.

    Wan I2V mask layout: frame 0 repeated ``4`` times in front, then each group of 4 video frames becomes
    the 4 channels of one latent frame; spatially the fraction of visible pixels per 8×8 cell.
    """
    st, sh, sw = vae_stride
    if mask.ndim != 4:
        raise ValueError(f"mask must be [B, T, H, W], got {tuple(mask.shape)}")
    B, T, H, W = mask.shape
    nf = latent_frames(T, st)
    if H % sh or W % sw:
        raise ValueError(f"mask size {H}x{W} must be a multiple of {sh}x{sw}")
    m = F.avg_pool2d(mask.float().reshape(B * T, 1, H, W), (sh, sw)).reshape(B, 1, T, H // sh, W // sw)
    m = _pad_first_frame(m, st)  # [B, 1, 4F, h, w]
    return m.reshape(B, nf, st, H // sh, W // sw).transpose(1, 2).contiguous()


def make_render_condition(render_latents: torch.Tensor, visibility: torch.Tensor,
                          vae_stride: Sequence[int] = VAE_STRIDE) -> torch.Tensor:
    """``cond`` input: VAE latents of the renders ``[B, 16, F, h, w]`` + pixel visibility ``[B, T, 8h, 8w]``."""
    packed = pack_visibility_mask(visibility, vae_stride).to(render_latents.dtype)
    if packed.shape[2:] != render_latents.shape[2:]:
        raise ValueError(f"render latents {tuple(render_latents.shape)} and visibility mask "
                         f"{tuple(visibility.shape)} describe different frame counts or sizes")
    return torch.cat([render_latents, packed], dim=1)


def plucker_to_tensor(rays, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``models.cameras.plucker_rays`` output ``[T, H, W, 6]`` (numpy or torch) to ``[1, 6, T, H, W]``."""
    t = torch.as_tensor(rays, dtype=dtype)
    if t.ndim != 4 or t.shape[-1] != 6:
        raise ValueError(f"Plücker rays must be [T, H, W, 6], got {tuple(t.shape)}")
    return t.permute(3, 0, 1, 2).unsqueeze(0).contiguous()


def _runs(frames: Sequence[int]) -> list[tuple[int, int]]:
    """Sorted frame indices as (start, length) runs of consecutive frames."""
    runs: list[list[int]] = []
    for f in frames:
        if runs and f == runs[-1][0] + runs[-1][1]:
            runs[-1][1] += 1
        else:
            runs.append([f, 1])
    return [(s, n) for s, n in runs]


def _take_frames(x: torch.Tensor, dim: int, frames: Sequence[int], frame_size) -> torch.Tensor:
    """Frames ``frames`` of ``x`` along ``dim``, where one frame is ``frame_size`` consecutive entries."""
    parts = [x.narrow(dim, s * frame_size, n * frame_size) for s, n in _runs(frames)]
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=dim)


def select_reference_frames(num_latent_frames: int, num_reference_frames: int,
                            generator: torch.Generator | None = None) -> torch.Tensor:
    """Sorted latent-frame indices ``[R]`` (int64): frame 0 plus ``R - 1`` distinct random others.

    ``R = min(num_reference_frames, num_latent_frames)``; an empty tensor when ``num_reference_frames == 0``.
    """
    if num_latent_frames < 1:
        raise ValueError(f"num_latent_frames must be >= 1, got {num_latent_frames}")
    k = min(int(num_reference_frames), int(num_latent_frames))
    if k <= 0:
        return torch.zeros(0, dtype=torch.long)
    others = torch.randperm(num_latent_frames - 1, generator=generator)[: k - 1] + 1
    return torch.sort(torch.cat([torch.zeros(1, dtype=torch.long), others])).values


# --------------------------------------------------------------------------------------------------
# Control modules
# --------------------------------------------------------------------------------------------------
def _zero_(module: nn.Module) -> nn.Module:
    for p in module.parameters():
        nn.init.zeros_(p)
    return module


class _ResBlock3d(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv3d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv3d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.silu(self.conv1(F.silu(x))))


class CameraAdapter(nn.Module):
    """Camera adapter A: Plücker rays ``[B, 6, T, H, W]`` -> tokens ``x_c [B, L, D]``.

    Frame 0 padded to its own temporal group, a (4, 8, 8)-strided conv to the latent grid, residual 3D
    convs, a patch-strided conv to the token grid, a linear to the DiT width.
    """

    def __init__(self, channels: int, out_dim: int, patch_size: Sequence[int], vae_stride: Sequence[int],
                 res_blocks: int = 1, in_channels: int = 6) -> None:
        super().__init__()
        self.vae_stride = tuple(vae_stride)
        self.to_latent = nn.Conv3d(in_channels, channels, kernel_size=self.vae_stride, stride=self.vae_stride)
        self.res = nn.ModuleList([_ResBlock3d(channels) for _ in range(res_blocks)])
        self.to_tokens = nn.Conv3d(channels, channels, kernel_size=tuple(patch_size), stride=tuple(patch_size))
        self.proj = nn.Linear(channels, out_dim)

    def forward(self, plucker: torch.Tensor) -> torch.Tensor:
        x = self.to_latent(_pad_first_frame(plucker, self.vae_stride[0]))
        for block in self.res:
            x = block(x)
        x = self.to_tokens(F.silu(x))
        return self.proj(F.silu(x.flatten(2).transpose(1, 2)))


class LoRAControlEncoder(nn.Module):
    """Lightweight encoder: Plücker rays ``[B, 6, T, H, W]`` -> LoRA control tokens ``x_l [B, L, r_in]``."""

    def __init__(self, channels: int, patch_size: Sequence[int], vae_stride: Sequence[int],
                 in_channels: int = 6) -> None:
        super().__init__()
        self.vae_stride = tuple(vae_stride)
        stride = tuple(v * p for v, p in zip(vae_stride, patch_size))
        self.patchify = nn.Conv3d(in_channels, channels, kernel_size=stride, stride=stride)
        self.mix = nn.Conv3d(channels, channels, 3, padding=1)

    def forward(self, plucker: torch.Tensor) -> torch.Tensor:
        x = self.patchify(_pad_first_frame(plucker, self.vae_stride[0]))
        x = x + self.mix(F.silu(x))
        return x.flatten(2).transpose(1, 2)


class _LoRA(nn.Module):
    """``W_u (W_d x)`` with ``W_u`` zero-initialised (no biases)."""

    def __init__(self, in_features: int, rank: int, out_features: int) -> None:
        super().__init__()
        self.down = nn.Linear(in_features, rank, bias=False)
        self.up = _zero_(nn.Linear(rank, out_features, bias=False))
        nn.init.kaiming_uniform_(self.down.weight, a=math.sqrt(5))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.up(self.down(x))


class _LowRankProjection(nn.Module):
    """``up(down(x))``: ``D -> r -> D``, ``down`` random (no bias), ``up`` zero-initialised (weight and bias), so it
    outputs exactly zero until trained."""

    def __init__(self, dim: int, rank: int) -> None:
        super().__init__()
        self.down = nn.Linear(dim, rank, bias=False)
        self.up = _zero_(nn.Linear(rank, dim))
        nn.init.kaiming_uniform_(self.down.weight, a=math.sqrt(5))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.up(self.down(x))


def _projection(dim: int, rank: int) -> nn.Module:
    """Zero-output ``x_c`` projection: full ``Linear(D, D)`` for ``rank == 0`` (format v1), else low-rank with
    ``min(rank, D)``."""
    if rank == 0:
        return _zero_(nn.Linear(dim, dim))
    return _LowRankProjection(dim, min(int(rank), dim))


class CameraControlBlock(nn.Module):
    """Per-DiT-block control weights (all zero-initialised where they touch the base stream)."""

    def __init__(self, dim: int, kv_dim: int, lora_in: int, rank: int, projection_rank: int = 0) -> None:
        super().__init__()
        self.pre_proj = _projection(dim, projection_rank)  # x_c -> added to the block input
        self.attn_proj = _projection(dim, projection_rank)  # x_c -> added to the self-attention output
        self.lora_q = _LoRA(lora_in, rank, dim)
        self.lora_k = _LoRA(lora_in, rank, kv_dim)
        self.lora_v = _LoRA(lora_in, rank, kv_dim)
        self.ref_gate = nn.Parameter(torch.zeros(dim))  # reference-frame attention branch gate


class CameraControl(nn.Module):
    """All camera-control weights (what ``save_camera_control`` writes)."""

    def __init__(self, config: CameraControlConfig, base_config: Any) -> None:
        super().__init__()
        dim = base_config.num_attention_heads * base_config.attention_head_dim
        patch = tuple(base_config.patch_size)
        self.adapter = CameraAdapter(config.adapter_channels, dim, patch, config.vae_stride,
                                     config.adapter_res_blocks)
        self.lora_encoder = LoRAControlEncoder(config.lora_in_channels, patch, config.vae_stride)
        self.cond_embedding = (_zero_(nn.Conv3d(config.cond_channels, dim, kernel_size=patch, stride=patch,
                                                bias=False)) if config.cond_channels else None)
        self.ref_embedding = nn.Conv3d(config.latent_channels, dim, kernel_size=patch, stride=patch)
        self.blocks = nn.ModuleList([CameraControlBlock(dim, dim, config.lora_in_channels, config.lora_rank,
                                                        config.projection_rank)
                                     for _ in range(base_config.num_layers)])


def _count(module: nn.Module | None) -> int:
    return sum(p.numel() for p in module.parameters()) if module is not None else 0


def control_parameter_counts(base_config: dict[str, Any], control_config: CameraControlConfig | None = None
                             ) -> dict[str, Any]:
    """Parameter counts of a base DiT (``WanTransformer3DModel`` kwargs) and its camera control, built on
    ``torch.device("meta")`` (no memory, well under a second even at 14B).

    Returns ``{"base", "control", "ratio" (control / base), "parts": {adapter, lora_encoder, cond_embedding,
    ref_embedding, projections (pre_proj + attn_proj of all blocks), lora, ref_gate}}``.
    """
    control_config = control_config or CameraControlConfig()
    with torch.device("meta"):
        base = WanTransformer3DModel(**base_config)
        control = CameraControl(control_config, base.config)
    blocks = control.blocks
    parts = {"adapter": _count(control.adapter), "lora_encoder": _count(control.lora_encoder),
             "cond_embedding": _count(control.cond_embedding), "ref_embedding": _count(control.ref_embedding),
             "projections": sum(_count(b.pre_proj) + _count(b.attn_proj) for b in blocks),
             "lora": sum(_count(b.lora_q) + _count(b.lora_k) + _count(b.lora_v) for b in blocks),
             "ref_gate": sum(b.ref_gate.numel() for b in blocks)}
    n_base, n_control = _count(base), _count(control)
    assert sum(parts.values()) == n_control
    return {"base": n_base, "control": n_control, "ratio": n_control / n_base, "parts": parts}


# --------------------------------------------------------------------------------------------------
# Attention processor
# --------------------------------------------------------------------------------------------------
@dataclass
class _ControlState:
    control: CameraControl
    x_c: torch.Tensor | None  # [B, L, D]
    x_l: torch.Tensor | None  # [B, L, r_in]
    lora_scale: torch.Tensor  # scalar
    ref_tokens: torch.Tensor | None  # [B, Lr, D]
    ref_x_c: torch.Tensor | None  # [B, Lr, D] (x_c at the reference positions)
    ref_rope: tuple[torch.Tensor, torch.Tensor] | None  # each [1, Lr, 1, head_dim]
    eps: float


def _apply_rotary_emb(x: torch.Tensor, freqs_cos: torch.Tensor, freqs_sin: torch.Tensor) -> torch.Tensor:
    # The same elementwise float ops as diffusers' WanAttnProcessor (so the untrained wrapper is bit-exact),
    # interleaved with stack/flatten instead of strided writes into empty_like (a smaller exported graph).
    x1, x2 = x.unflatten(-1, (-1, 2)).unbind(-1)
    cos = freqs_cos[..., 0::2]
    sin = freqs_sin[..., 1::2]
    out = torch.stack([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1).flatten(-2)
    return out.type_as(x)


class CameraControlAttnProcessor:
    """Self-attention (``attn1``) processor of one ``WanTransformerBlock`` with camera control.

    Computes exactly what diffusers' ``WanAttnProcessor`` computes, plus, when the wrapper has set
    ``state`` for the current forward: LoRA deltas on Q/K/V, the reference-frame attention branch and the
    ``x_c`` projection added to the attention output. With ``state = None`` it is the base processor.
    """

    _attention_backend = None
    _parallel_config = None

    def __init__(self, index: int) -> None:
        self.index = index
        self.state: _ControlState | None = None

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states: torch.Tensor | None = None,
                 attention_mask: torch.Tensor | None = None,
                 rotary_emb: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        if encoder_hidden_states is not None or attn.add_k_proj is not None:
            raise ValueError("CameraControlAttnProcessor is for the self-attention (attn1) only")
        st = self.state
        blk = st.control.blocks[self.index] if st is not None else None

        query, key, value = _get_qkv_projections(attn, hidden_states, None)
        if blk is not None and st.x_l is not None:
            query = query + st.lora_scale * blk.lora_q(st.x_l)
            key = key + st.lora_scale * blk.lora_k(st.x_l)
            value = value + st.lora_scale * blk.lora_v(st.x_l)

        query = attn.norm_q(query)
        key = attn.norm_k(key)
        query = query.unflatten(2, (attn.heads, -1))
        key = key.unflatten(2, (attn.heads, -1))
        value = value.unflatten(2, (attn.heads, -1))
        if rotary_emb is not None:
            query = _apply_rotary_emb(query, *rotary_emb)
            key = _apply_rotary_emb(key, *rotary_emb)

        hidden_states = dispatch_attention_fn(query, key, value, attn_mask=attention_mask, dropout_p=0.0,
                                              is_causal=False, backend=self._attention_backend,
                                              parallel_config=self._parallel_config)
        hidden_states = hidden_states.flatten(2, 3).type_as(query)

        if blk is not None and st.ref_tokens is not None:
            hidden_states = hidden_states + blk.ref_gate * self._reference_attention(attn, st, blk, query)

        hidden_states = attn.to_out[0](hidden_states)
        hidden_states = attn.to_out[1](hidden_states)
        if blk is not None and st.x_c is not None:
            hidden_states = hidden_states + blk.attn_proj(st.x_c)
        return hidden_states

    def _reference_attention(self, attn, st: _ControlState, blk: CameraControlBlock,
                             query: torch.Tensor) -> torch.Tensor:
        ref = st.ref_tokens
        if st.ref_x_c is not None:
            ref = ref + blk.pre_proj(st.ref_x_c)
        ref = F.layer_norm(ref.float(), (ref.shape[-1],), eps=st.eps).type_as(ref)
        if getattr(attn, "fused_projections", False):
            _, key, value = attn.to_qkv(ref).chunk(3, dim=-1)
        else:
            key, value = attn.to_k(ref), attn.to_v(ref)
        key = attn.norm_k(key).unflatten(2, (attn.heads, -1))
        value = value.unflatten(2, (attn.heads, -1))
        if st.ref_rope is not None:
            key = _apply_rotary_emb(key, *st.ref_rope)
        out = dispatch_attention_fn(query, key, value, attn_mask=None, dropout_p=0.0, is_causal=False,
                                    backend=self._attention_backend, parallel_config=None)
        return out.flatten(2, 3).type_as(query)


# --------------------------------------------------------------------------------------------------
# Base weights
# --------------------------------------------------------------------------------------------------
def load_wan_transformer(directory: str | os.PathLike, torch_dtype: torch.dtype | None = None
                         ) -> WanTransformer3DModel:
    """``WanTransformer3DModel`` from a diffusers-format directory (``<dir>/transformer`` or ``<dir>`` itself).

    Uses ``WanTransformer3DModel.from_pretrained`` when ``accelerate`` is installed. Without it diffusers 0.42
    refuses Wan outright (``low_cpu_mem_usage`` falls back to False, which ``_keep_in_fp32_modules``
    forbids), so the same files are read here: config + (sharded) safetensors, names checked, no pickles.
    """
    from diffusers.utils import is_accelerate_available

    directory = Path(directory)
    if (directory / "transformer" / "config.json").is_file():
        directory = directory / "transformer"
    elif not (directory / "config.json").is_file():
        raise FileNotFoundError(f"{directory}: no diffusers Wan transformer (expected "
                                f"{directory / 'transformer' / 'config.json'} or {directory / 'config.json'})")
    if is_accelerate_available():
        kwargs = {"torch_dtype": torch_dtype} if torch_dtype is not None else {}
        return WanTransformer3DModel.from_pretrained(directory, **kwargs)

    from diffusers.models.modeling_utils import no_init_weights
    from safetensors.torch import load_file

    single = directory / "diffusion_pytorch_model.safetensors"
    index = directory / "diffusion_pytorch_model.safetensors.index.json"
    if single.is_file():
        files = [single]
    elif index.is_file():
        files = [directory / f for f in sorted(set(json.loads(index.read_text())["weight_map"].values()))]
    else:
        raise FileNotFoundError(f"{directory}: no diffusion_pytorch_model.safetensors (or .index.json); "
                                f"only safetensors checkpoints are read")
    with no_init_weights():
        model = WanTransformer3DModel.from_config(WanTransformer3DModel.load_config(directory))
    state: dict[str, torch.Tensor] = {}
    for f in files:
        state.update(load_file(str(f)))
    ignore = WanTransformer3DModel._keys_to_ignore_on_load_unexpected or []
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(k for k in set(state) - set(expected) if not any(p in k for p in ignore))
    mismatched = [f"{k}: file {list(state[k].shape)} vs model {list(v.shape)}" for k, v in expected.items()
                  if k in state and state[k].shape != v.shape]
    if missing or unexpected or mismatched:
        raise CameraControlWeightsError(f"{directory}: Wan weights do not fit its config.json: missing "
                                        f"[{_short(missing)}]; unexpected [{_short(unexpected)}]; "
                                        f"shape mismatch [{_short(mismatched)}]")
    model.load_state_dict({k: state[k] for k in expected}, strict=True)
    if torch_dtype is not None:
        model.to(torch_dtype)
        keep = WanTransformer3DModel._keep_in_fp32_modules or []
        for name, tensor in [*model.named_parameters(), *model.named_buffers()]:
            if any(k in name.split(".") for k in keep):
                tensor.data = tensor.data.float()
    return model.eval()


# --------------------------------------------------------------------------------------------------
# The wrapper
# --------------------------------------------------------------------------------------------------
class CameraControlledWan(nn.Module):
    """``base`` (diffusers ``WanTransformer3DModel``) + ``control`` (``CameraControl``).

    ``forward(hidden_states [B, C_in, F, h, w], timestep [B], encoder_hidden_states [B, 512, text_dim],
    encoder_hidden_states_image [B, L_img, image_dim] | None, plucker [B, 6, 4(F-1)+1, 8h, 8w] | None,
    cond [B, cond_channels, F, h, w] | None, lora_scale: scalar tensor | float | None,
    image_reference [B, 16, R, h, w] | None, image_reference_plucker [B, 6, R, 8h, 8w] | None)
    -> noise/flow prediction [B, out_channels, F, h, w]``.
    """

    def __init__(self, base: WanTransformer3DModel, config: CameraControlConfig | None = None) -> None:
        super().__init__()
        self.base = base
        self.config = config or CameraControlConfig()
        self.control = CameraControl(self.config, base.config)
        self.control.to(device=base.device, dtype=base.dtype)
        self.init_reference_embedding_from_base()
        for i, block in enumerate(base.blocks):
            block.attn1.set_processor(CameraControlAttnProcessor(i))
        self._ref_generator = torch.Generator().manual_seed(self.config.reference_seed)
        self.gradient_checkpointing = False

    # ---- construction / weights -------------------------------------------------------------------
    @torch.no_grad()
    def init_reference_embedding_from_base(self) -> None:
        """Reference-token embedding = the base patch embedding of a *known clean frame* (I2V layout:
        noisy channels = clean latent, mask = 1, condition channels = clean latent); for a T2V base the
        first ``latent_channels`` input channels. Only changes ``control.ref_embedding``."""
        w, b = self.base.patch_embedding.weight, self.base.patch_embedding.bias
        c = self.config.latent_channels
        in_ch = w.shape[1]
        if in_ch == 2 * c + 4:  # [noisy | mask(4) | condition]
            weight = w[:, :c] + w[:, c + 4:]
            bias = b + w[:, c:c + 4].sum(dim=(1, 2, 3, 4))
        elif in_ch >= c:
            weight, bias = w[:, :c], b
        else:
            return
        self.control.ref_embedding.weight.copy_(weight)
        self.control.ref_embedding.bias.copy_(bias)

    @classmethod
    def from_pretrained(cls, base_dir: str | os.PathLike, control_dir: str | os.PathLike | None = None,
                        config: CameraControlConfig | None = None, torch_dtype: torch.dtype | None = None,
                        ) -> CameraControlledWan:
        """Base from a diffusers directory (``<base_dir>/transformer`` or ``base_dir`` itself); control
        weights from ``control_dir`` (``save_camera_control``'s files), or fresh zero-initialised ones."""
        base = load_wan_transformer(base_dir, torch_dtype=torch_dtype)
        if control_dir is not None:
            saved = read_camera_control_config(control_dir)
            if config is not None and config.to_dict() != saved.to_dict():
                raise CameraControlWeightsError(
                    f"{Path(control_dir) / CONTROL_CONFIG}: config differs from the one passed "
                    f"({_dict_diff(saved.to_dict(), config.to_dict())}); pass config=None to use the saved one")
            config = saved
        model = cls(base, config)
        if control_dir is not None:
            load_camera_control(model, control_dir)
        return model

    def freeze_base(self) -> None:
        """Train only the camera control: ``requires_grad=False`` on every base parameter."""
        self.base.requires_grad_(False)

    def seed_reference_frames(self, seed: int) -> None:
        """Reseed the training-time reference-frame generator."""
        self._ref_generator = torch.Generator().manual_seed(int(seed))

    def _processors(self) -> list[CameraControlAttnProcessor]:
        procs = [block.attn1.processor for block in self.base.blocks]
        for p in procs:
            if not isinstance(p, CameraControlAttnProcessor):
                raise RuntimeError(f"attn1 processor was replaced by {type(p).__name__}; camera control needs "
                                   f"CameraControlAttnProcessor")
        return procs

    # ---- forward ----------------------------------------------------------------------------------
    def reference_indices(self, num_latent_frames: int,
                          reference_frames: torch.Tensor | Sequence[int] | None = None) -> list[int] | None:
        """Latent frames used as reference frames for this call (see the module docstring), sorted."""
        if reference_frames is not None:
            frames = torch.as_tensor(reference_frames, dtype=torch.long).flatten().tolist()
        elif self.training:
            frames = select_reference_frames(num_latent_frames, self.config.num_reference_frames,
                                             self._ref_generator).tolist()
        else:
            frames = list(self.config.inference_reference_frames)
        frames = sorted(set(int(f) for f in frames))
        bad = [f for f in frames if not 0 <= f < num_latent_frames]
        if bad:
            raise ValueError(f"reference frames {bad} out of range for {num_latent_frames} latent frames")
        return frames or None

    def _reference_rope(self, frames: list[int], pph: int, ppw: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The base rope (``WanRotaryPosEmbed``) evaluated on the token grid of the given latent frames only:
        the same values the base gives those frames' tokens, built from slices (small exported graph)."""
        rope = self.base.rope
        runs = _runs(frames)
        out = []
        for freqs in (rope.freqs_cos, rope.freqs_sin):
            f_t, f_h, f_w = freqs.split([rope.t_dim, rope.h_dim, rope.w_dim], dim=1)
            f_t = torch.cat([f_t[s:s + n] for s, n in runs]) if len(runs) > 1 else f_t[runs[0][0]:sum(runs[0])]
            r = len(frames)
            grid = [f_t.view(r, 1, 1, -1).expand(r, pph, ppw, -1),
                    f_h[:pph].view(1, pph, 1, -1).expand(r, pph, ppw, -1),
                    f_w[:ppw].view(1, 1, ppw, -1).expand(r, pph, ppw, -1)]
            out.append(torch.cat(grid, dim=-1).reshape(1, r * pph * ppw, 1, -1))
        return out[0], out[1]

    def forward(self, hidden_states: torch.Tensor, timestep: torch.Tensor, encoder_hidden_states: torch.Tensor,
                encoder_hidden_states_image: torch.Tensor | None = None, plucker: torch.Tensor | None = None,
                cond: torch.Tensor | None = None, lora_scale: torch.Tensor | float | None = None,
                image_reference: torch.Tensor | None = None, image_reference_plucker: torch.Tensor | None = None, *,
                reference_frames: torch.Tensor | Sequence[int] | None = None,
                reference_latents: torch.Tensor | None = None) -> torch.Tensor:
        """Noise/flow prediction ``[B, out_channels, F, h, w]``.

        ``reference_frames``: latent-frame indices overriding the default selection (random in training,
        ``config.inference_reference_frames`` in eval). ``reference_latents [B, 16, F, h, w]``: clean latents
        the reference frames are taken from (training: the clean video latents); default: the I2V
        conditioning latents in ``hidden_states`` (channels 20:36).
        ``image_reference [B, 16, R, h, w]`` (R >= 1): clean latents of extra reference frames outside the clip
        (e.g. the scene's input photo, VAE-encoded as a one-frame video), and ``image_reference_plucker
        [B, 6, R, 8h, 8w]`` their rays in the clip's Plücker frame (same convention, origin and scale as
        ``plucker``: ``cameras.clip_relative_rays``), required when ``plucker`` is given (without ``plucker`` the
        call is camera-free and they are unused). They join the reference frames at the rope position of latent
        frame 0 (module docstring).
        """
        base, control, cfg = self.base, self.control, self.config
        batch_size, _, num_frames, height, width = hidden_states.shape
        p_t, p_h, p_w = base.config.patch_size
        st_t, st_h, st_w = cfg.vae_stride
        ppf, pph, ppw = num_frames // p_t, height // p_h, width // p_w
        if plucker is not None:
            expected = (batch_size, 6, (num_frames - 1) * st_t + 1, height * st_h, width * st_w)
            if tuple(plucker.shape) != expected:
                raise ValueError(f"plucker must be [B, 6, 4(F-1)+1, 8h, 8w] = {expected} for hidden_states "
                                 f"{tuple(hidden_states.shape)}, got {tuple(plucker.shape)}")
        if cond is not None and cfg.cond_channels == 0:
            raise ValueError("cond given but the camera-control config has cond_channels = 0")
        if cond is not None and tuple(cond.shape) != (batch_size, cfg.cond_channels, num_frames, height, width):
            raise ValueError(f"cond must be [B, {cfg.cond_channels}, F, h, w] matching hidden_states "
                             f"{tuple(hidden_states.shape)}, got {tuple(cond.shape)}")
        if image_reference is not None:
            R = image_reference.shape[2] if image_reference.ndim == 5 else 0
            want = (batch_size, cfg.latent_channels, R, height, width)
            if tuple(image_reference.shape) != want or R < 1:
                raise ValueError(f"image_reference must be [B, {cfg.latent_channels}, R, h, w] (R >= 1) matching "
                                 f"hidden_states {tuple(hidden_states.shape)}, got {tuple(image_reference.shape)}")
            if image_reference_plucker is None and plucker is not None:
                raise ValueError("image_reference needs image_reference_plucker (the rays of its frames in the "
                                 "clip's Plücker frame, cameras.clip_relative_rays) when plucker is given")
            if image_reference_plucker is not None:
                want = (batch_size, 6, R, height * st_h, width * st_w)
                if tuple(image_reference_plucker.shape) != want:
                    raise ValueError(f"image_reference_plucker must be [B, 6, R, 8h, 8w] = {want} for image_reference "
                                     f"{tuple(image_reference.shape)}, got {tuple(image_reference_plucker.shape)}")
        elif image_reference_plucker is not None:
            raise ValueError("image_reference_plucker given without image_reference (the frames' clean latents)")
        if lora_scale is None:  # the LoRA is trained at full strength and scaled down at inference (paper: 0.7)
            lora_scale = TRAINING_LORA_SCALE if self.training else cfg.lora_scale
        if not torch.is_tensor(lora_scale):
            lora_scale = torch.tensor(float(lora_scale))
        lora_scale = lora_scale.to(device=hidden_states.device, dtype=hidden_states.dtype).reshape(())

        # ---- base prologue (as WanTransformer3DModel.forward) + render condition -------------------
        rotary_emb = base.rope(hidden_states)
        x = base.patch_embedding(hidden_states)
        if cond is not None:
            x = x + control.cond_embedding(cond.to(x.dtype))
        x = x.flatten(2).transpose(1, 2).contiguous()

        if timestep.ndim == 2:
            ts_seq_len = timestep.shape[1]
            timestep = timestep.flatten()
        else:
            ts_seq_len = None
        temb, timestep_proj, encoder_hidden_states, encoder_hidden_states_image = base.condition_embedder(
            timestep, encoder_hidden_states, encoder_hidden_states_image, timestep_seq_len=ts_seq_len)
        if ts_seq_len is not None:
            timestep_proj = timestep_proj.unflatten(2, (6, -1))
        else:
            timestep_proj = timestep_proj.unflatten(1, (6, -1))
        if encoder_hidden_states_image is not None:
            encoder_hidden_states = torch.concat([encoder_hidden_states_image, encoder_hidden_states], dim=1)

        # ---- control tokens -------------------------------------------------------------------------
        x_c = x_l = None
        if plucker is not None:
            plucker = plucker.to(x.dtype)
            x_c = control.adapter(plucker)
            x_l = control.lora_encoder(plucker)

        ref_tokens = ref_x_c = ref_rope = None
        frames = self.reference_indices(ppf, reference_frames)
        if self.training and frames and reference_latents is None:
            raise ValueError("training mode needs reference_latents (the clean video latents [B, 16, F, h, w]) for "
                             f"its reference frames {frames}: without them they would be taken from the I2V "
                             "conditioning latents, which hold black frames after frame 0")
        src = reference_latents
        if src is None and hidden_states.shape[1] == 2 * cfg.latent_channels + 4:
            src = hidden_states[:, cfg.latent_channels + 4:]
        tokens, cams, ropes = [], [], []  # reference tokens, their camera tokens, their rope
        if frames and src is not None:
            ref = control.ref_embedding(_take_frames(src.to(x.dtype), 2, frames, 1))
            tokens.append(ref.flatten(2).transpose(1, 2))
            ropes.append(self._reference_rope(frames, pph, ppw))
            if x_c is not None:
                cams.append(_take_frames(x_c, 1, frames, pph * ppw))
        if image_reference is not None:  # extra reference frames: rope of latent frame 0 (module docstring)
            ref = control.ref_embedding(image_reference.to(x.dtype))  # [B, D, R, pph, ppw]
            n_ref = ref.shape[2]
            tokens.append(ref.flatten(2).transpose(1, 2))
            cos, sin = self._reference_rope([0], pph, ppw)
            ropes.append((cos.repeat(1, n_ref, 1, 1), sin.repeat(1, n_ref, 1, 1)))
            if image_reference_plucker is not None and x_c is not None:  # each frame's rays as a one-frame clip
                rays = image_reference_plucker.to(x.dtype).transpose(1, 2).flatten(0, 1).unsqueeze(2)
                cam = control.adapter(rays)  # [B * R, pph * ppw, D]
                cams.append(cam.reshape(batch_size, -1, cam.shape[-1]))
        if tokens:
            ref_tokens = tokens[0] if len(tokens) == 1 else torch.cat(tokens, dim=1)
            ref_x_c = None if not cams else cams[0] if len(cams) == 1 else torch.cat(cams, dim=1)
            ref_rope = ropes[0] if len(ropes) == 1 else (torch.cat([r[0] for r in ropes], dim=1),
                                                         torch.cat([r[1] for r in ropes], dim=1))

        state = _ControlState(control=control, x_c=x_c, x_l=x_l, lora_scale=lora_scale, ref_tokens=ref_tokens,
                              ref_x_c=ref_x_c, ref_rope=ref_rope, eps=float(base.config.eps))
        procs = self._processors()

        def run_block(i: int, h: torch.Tensor) -> torch.Tensor:
            if x_c is not None:
                h = h + control.blocks[i].pre_proj(x_c)
            procs[i].state = state
            try:
                return base.blocks[i](h, encoder_hidden_states, timestep_proj, rotary_emb)
            finally:
                procs[i].state = None

        for i in range(len(base.blocks)):
            if torch.is_grad_enabled() and self.gradient_checkpointing and self.training:
                x = torch.utils.checkpoint.checkpoint(run_block, i, x, use_reentrant=False)
            else:
                x = run_block(i, x)

        # ---- base epilogue ----------------------------------------------------------------------------
        if temb.ndim == 3:
            shift, scale = (base.scale_shift_table.unsqueeze(0).to(temb.device) + temb.unsqueeze(2)).chunk(2, dim=2)
            shift, scale = shift.squeeze(2), scale.squeeze(2)
        else:
            shift, scale = (base.scale_shift_table.to(temb.device) + temb.unsqueeze(1)).chunk(2, dim=1)
        x = (base.norm_out(x.float()) * (1 + scale) + shift).type_as(x)
        x = base.proj_out(x)
        x = x.reshape(batch_size, ppf, pph, ppw, p_t, p_h, p_w, -1)
        x = x.permute(0, 7, 1, 4, 2, 5, 3, 6)
        return x.flatten(6, 7).flatten(4, 5).flatten(2, 3)


# --------------------------------------------------------------------------------------------------
# Presets
# --------------------------------------------------------------------------------------------------
def build_camera_wan(base_config: dict[str, Any], control_config: CameraControlConfig | None = None,
                     seed: int = 0, device: str | torch.device | None = None,
                     dtype: torch.dtype | None = None) -> CameraControlledWan:
    """A ``CameraControlledWan`` with a randomly initialised base (seeded; the global RNG is untouched)."""
    devices = [torch.device(device)] if device is not None and torch.device(device).type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        with torch.device(device or "cpu"):
            base = WanTransformer3DModel(**base_config)
        if dtype is not None:
            base = base.to(dtype)
        model = CameraControlledWan(base, control_config)
    return model.eval()


def tiny_camera_wan(seed: int = 0) -> CameraControlledWan:
    """Random tiny Wan2.1 I2V base (2 heads × 12, 2 layers) + zero-initialised camera control (eval mode)."""
    return build_camera_wan(TINY_I2V_CONFIG, tiny_camera_config(), seed=seed)


@torch.no_grad()
def randomize_camera_control(model: CameraControlledWan, seed: int = 0, std: float = 0.05) -> CameraControlledWan:
    """Fill every camera-control weight with seeded ``N(0, std²)`` noise (tests and benchmarks: makes every
    control path active, which zero initialisation does not)."""
    g = torch.Generator().manual_seed(seed)
    for p in model.control.parameters():
        p.copy_((torch.randn(p.shape, generator=g) * std).to(p.dtype))
    return model


# --------------------------------------------------------------------------------------------------
# Camera-control weights: safetensors + JSON
# --------------------------------------------------------------------------------------------------
def _base_summary(base: WanTransformer3DModel) -> dict[str, Any]:
    c = base.config
    return {"num_layers": c.num_layers, "num_attention_heads": c.num_attention_heads,
            "attention_head_dim": c.attention_head_dim, "patch_size": list(c.patch_size),
            "in_channels": c.in_channels, "out_channels": c.out_channels}


def _dict_diff(a: dict, b: dict) -> str:
    keys = sorted(set(a) | set(b))
    return ", ".join(f"{k}: {a.get(k)!r} vs {b.get(k)!r}" for k in keys if a.get(k) != b.get(k))


def _short(items: list[str], n: int = 10) -> str:
    return ", ".join(items[:n]) + (f" ... (+{len(items) - n} more)" if len(items) > n else "")


def save_camera_control(model: CameraControlledWan, directory: str | os.PathLike) -> Path:
    """Write ``camera_control.safetensors`` + ``camera_control.json`` (config, base sizes, tensor shapes).

    The JSON is written last (temp file + rename): a directory with it holds a complete save.
    """
    from safetensors.torch import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().contiguous().cpu() for k, v in model.control.state_dict().items()}
    weights = directory / CONTROL_WEIGHTS
    tmp = directory / (CONTROL_WEIGHTS + ".tmp")
    save_file(state, str(tmp), metadata={"format": CONTROL_FORMAT})
    os.replace(tmp, weights)
    meta = {"format": CONTROL_FORMAT, "format_version": CONTROL_FORMAT_VERSION, "config": model.config.to_dict(),
            "base": _base_summary(model.base), "weights": CONTROL_WEIGHTS,
            "tensors": {k: list(v.shape) for k, v in state.items()}}
    tmp = directory / (CONTROL_CONFIG + ".tmp")
    tmp.write_text(json.dumps(meta, indent=2, sort_keys=True))
    os.replace(tmp, directory / CONTROL_CONFIG)
    return directory


def _read_meta(directory: str | os.PathLike) -> dict[str, Any]:
    path = Path(directory) / CONTROL_CONFIG
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no camera-control config (write one with save_camera_control)")
    meta = json.loads(path.read_text())
    version = meta.get("format_version")
    if meta.get("format") != CONTROL_FORMAT or version not in READABLE_FORMAT_VERSIONS:
        raise CameraControlWeightsError(f"{path}: not a {CONTROL_FORMAT} config of a readable version "
                                        f"{list(READABLE_FORMAT_VERSIONS)} (format {meta.get('format')!r}, "
                                        f"version {version!r})")
    if version == 1:  # full D x D projections; the convention it records (v1's default when absent)
        meta["config"] = {**_V1_DEFAULTS, **meta.get("config", {})}
    return meta


def read_camera_control_config(directory: str | os.PathLike) -> CameraControlConfig:
    return CameraControlConfig.from_dict(_read_meta(directory)["config"])


def load_camera_control(model: CameraControlledWan, directory: str | os.PathLike) -> CameraControlledWan:
    """Load ``save_camera_control``'s files into ``model`` (in place; also returns it).

    Checks the base sizes, then every tensor name and shape, and raises ``CameraControlWeightsError``
    naming the file and the offending keys. The saved config (Plücker convention, default α, reference
    frames) replaces ``model.config``: it describes how the weights were trained.
    """
    from safetensors import safe_open

    directory = Path(directory)
    meta = _read_meta(directory)
    saved_cfg = CameraControlConfig.from_dict(meta["config"])
    base_now = _base_summary(model.base)
    if meta.get("base") != base_now:
        raise CameraControlWeightsError(f"{directory / CONTROL_CONFIG}: saved for a different base DiT "
                                        f"({_dict_diff(meta.get('base') or {}, base_now)})")
    path = directory / meta.get("weights", CONTROL_WEIGHTS)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: camera-control weights missing")
    expected = model.control.state_dict()
    with safe_open(str(path), framework="pt") as f:
        keys = set(f.keys())
        missing = sorted(set(expected) - keys)
        unexpected = sorted(keys - set(expected))
        mismatched = [f"{k}: file {list(f.get_slice(k).get_shape())} vs model {list(expected[k].shape)}"
                      for k in sorted(keys & set(expected)) if list(f.get_slice(k).get_shape())
                      != list(expected[k].shape)]
        problems = []
        if missing:
            problems.append(f"missing keys [{_short(missing)}]")
        if unexpected:
            problems.append(f"unexpected keys [{_short(unexpected)}]")
        if mismatched:
            problems.append(f"shape mismatch [{_short(mismatched)}]")
        if problems:
            raise CameraControlWeightsError(f"{path}: camera-control weights do not fit the model: "
                                            + "; ".join(problems))
        state = {k: f.get_tensor(k) for k in keys}
    with torch.no_grad():
        for k, v in expected.items():
            v.copy_(state[k].to(dtype=v.dtype, device=v.device))
    model.config = saved_cfg
    model._ref_generator = torch.Generator().manual_seed(saved_cfg.reference_seed)
    return model


# --------------------------------------------------------------------------------------------------
# ONNX export
# --------------------------------------------------------------------------------------------------
class _ExportWrapper(nn.Module):
    """Positional signature of the exported graph (absent optional inputs are passed as ``None``)."""

    def __init__(self, model: CameraControlledWan) -> None:
        super().__init__()
        self.model = model

    def forward(self, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker, cond,
                lora_scale, image_reference, image_reference_plucker):
        return self.model(hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker,
                          cond, lora_scale, image_reference, image_reference_plucker)


def example_inputs(model: CameraControlledWan, example_shape: Sequence[int], image_tokens: int = 257,
                   seed: int = 0, reference_images: int = 1) -> dict[str, torch.Tensor]:
    """Random inputs named as the exported graph's inputs. ``example_shape = (batch, F, h, w)`` in latent
    units (video frames ``4(F-1)+1``, pixels ``8h × 8w``); ``reference_images`` extra reference frames
    (``image_reference`` / ``image_reference_plucker``; 0: none)."""
    b, f, h, w = (int(v) for v in example_shape)
    c = model.base.config
    st_t, st_h, st_w = model.config.vae_stride
    g = torch.Generator().manual_seed(seed)
    dtype = model.base.dtype

    def r(*shape):
        return torch.randn(*shape, generator=g).to(dtype)

    inputs = {"hidden_states": r(b, c.in_channels, f, h, w),
              "timestep": torch.linspace(100.0, 900.0, b).to(dtype),
              "encoder_hidden_states": r(b, TEXT_TOKENS, c.text_dim)}
    if c.image_dim is not None:
        inputs["encoder_hidden_states_image"] = r(b, image_tokens, c.image_dim)
    inputs["plucker"] = r(b, 6, (f - 1) * st_t + 1, h * st_h, w * st_w)
    if model.config.cond_channels:
        inputs["cond"] = r(b, model.config.cond_channels, f, h, w)
    inputs["lora_scale"] = torch.tensor(model.config.lora_scale, dtype=dtype)
    if reference_images:
        inputs["image_reference"] = r(b, model.config.latent_channels, reference_images, h, w)
        inputs["image_reference_plucker"] = r(b, 6, reference_images, h * st_h, w * st_w)
    return inputs


def export_dit(model: CameraControlledWan, out_path: str | os.PathLike, example_shape: Sequence[int] = (2, 2, 4, 4),
               image_tokens: int = 257, max_latent_frames: int | None = None):
    """Export the whole camera-controlled DiT to ONNX (``out_path`` + ``out_path.data``).

    Inputs (in order; ``encoder_hidden_states_image`` only for an I2V base, ``cond`` only when
    ``cond_channels > 0``): hidden_states [B, C_in, F, h, w], timestep [B] (float), encoder_hidden_states
    [B, 512, text_dim], encoder_hidden_states_image [B, L_img, image_dim], plucker [B, 6, 4F-3, 8h, 8w],
    cond [B, cond_channels, F, h, w], lora_scale [], image_reference [B, 16, R, h, w], image_reference_plucker
    [B, 6, R, 8h, 8w] -> noise_pred [B, out_channels, F, h, w].
    Dynamic: batch, F (``latent_frames``), h = 2·``half_height``, w = 2·``half_width``, L_img, R
    (``reference_images``, >= 1); the text length is fixed at 512. ``example_shape = (batch, F, h, w)`` (batch 2 =
    one CFG pair; F ≥ 2; the example has R = 2 so that R stays dynamic).
    Reference frames are ``config.inference_reference_frames`` (constant in the graph).
    """
    from torch.export import Dim

    from navcrafter.models.runtime.onnxio import export_graph

    b, f, h, w = (int(v) for v in example_shape)
    p_t, p_h, p_w = model.base.config.patch_size
    if p_t != 1 or h % p_h or w % p_w or f < 2 or b < 2:
        raise ValueError(f"example_shape (batch, F, h, w) needs batch >= 2, F >= 2 and h, w multiples of the "
                         f"patch ({p_h}, {p_w}); got {tuple(example_shape)}")
    rope_max = model.base.config.rope_max_seq_len
    st_t, st_h, st_w = model.config.vae_stride
    inputs = example_inputs(model, example_shape, image_tokens, reference_images=2)
    names = [n for n in DIT_INPUTS if n in inputs]

    batch = Dim("batch", min=1, max=1024)
    frames = Dim("latent_frames", min=2, max=max_latent_frames or rope_max)
    hh = Dim("half_height", min=1, max=rope_max)
    hw = Dim("half_width", min=1, max=rope_max)
    refs = Dim("reference_images", min=1, max=64)
    shapes: dict[str, dict[int, Any]] = {
        "hidden_states": {0: batch, 2: frames, 3: p_h * hh, 4: p_w * hw},
        "timestep": {0: batch},
        "encoder_hidden_states": {0: batch},
        "encoder_hidden_states_image": {0: batch, 1: Dim("image_tokens", min=2, max=4096)},
        "plucker": {0: batch, 2: st_t * frames - (st_t - 1), 3: st_h * p_h * hh, 4: st_w * p_w * hw},
        "cond": {0: batch, 2: frames, 3: p_h * hh, 4: p_w * hw},
        "lora_scale": {},
        "image_reference": {0: batch, 2: refs, 3: p_h * hh, 4: p_w * hw},
        "image_reference_plucker": {0: batch, 2: refs, 3: st_h * p_h * hh, 4: st_w * p_w * hw},
    }
    wrapper = _ExportWrapper(model).eval()
    args = tuple(inputs.get(n) for n in DIT_INPUTS)
    dynamic = tuple(shapes[n] if n in inputs else None for n in DIT_INPUTS)
    info = export_graph(wrapper, args, Path(out_path), input_names=names, output_names=list(DIT_OUTPUTS),
                        dynamic_shapes=dynamic)
    info.notes = (f"camera-controlled Wan2.1 DiT; plucker_convention={model.config.plucker_convention}; "
                  f"reference_frames={list(model.config.inference_reference_frames)} + image_reference "
                  f"(rope frame 0); projection_rank={model.config.projection_rank}; "
                  f"text tokens fixed at {TEXT_TOKENS}")
    return info

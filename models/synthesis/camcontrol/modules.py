"""The camera-control modules: Plücker camera adapter, LoRA control encoder and branches, per-block projections
(``CameraControl`` holds them all) and their parameter counts."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F
from diffusers.models.transformers.transformer_wan import WanTransformer3DModel

from navcrafter.models.synthesis.camcontrol.conditioning import _pad_first_frame
from navcrafter.models.synthesis.camcontrol.config import CameraControlConfig


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

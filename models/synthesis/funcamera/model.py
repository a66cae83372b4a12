"""``FunCameraWan``: diffusers' Wan2.1 I2V DiT plus the ``SimpleAdapter`` camera adapter on its patch embedding."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F
from diffusers.models.transformers.transformer_wan import WanTransformer3DModel

from navcrafter.models.synthesis.funcamera.config import MODEL_NAME, PLUCKER_CHANNELS, FunCameraConfig
from navcrafter.models.synthesis.funcamera.plucker import fun_camera_pack


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

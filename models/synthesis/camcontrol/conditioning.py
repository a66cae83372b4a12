"""Shapes of the camera-control inputs: video/latent frame counts, the visibility mask packed like Wan's I2V mask,
the render condition, Plücker rays as tensors and the reference-frame selection."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from navcrafter.models.synthesis.camcontrol.config import VAE_STRIDE


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
    """``models.camera.cameras.plucker_rays`` output ``[T, H, W, 6]`` (numpy or torch) to ``[1, 6, T, H, W]``."""
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

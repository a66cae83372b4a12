"""VGGT building blocks (official parameter names): attention blocks with 2D RoPE, the DINOv2 patch embedding
(transformers' modules) and the alternating frame/global ``Aggregator``."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn
from transformers.models.dinov2_with_registers.configuration_dinov2_with_registers import (
    Dinov2WithRegistersConfig,
)
from transformers.models.dinov2_with_registers.modeling_dinov2_with_registers import (
    Dinov2WithRegistersEmbeddings,
    Dinov2WithRegistersLayer,
)

from navcrafter.models.geometry.vggt.config import _RESNET_MEAN, _RESNET_STD

if TYPE_CHECKING:
    from navcrafter.models.geometry.vggt.config import VGGTConfig


class LayerScale(nn.Module):
    def __init__(self, dim: int, init_values: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(init_values * torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    def __init__(self, dim_in: int, hidden: int, dim_out: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim_in, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim_out or dim_in)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


def rope_rotation(head_dim: int) -> torch.Tensor:
    """Constant ``[head_dim, head_dim]`` matrix ``M`` with ``x @ M`` = rotate-half of each of the two halves
    (y features, x features) of ``x``: ``[a1, a2, b1, b2] -> [-a2, a1, -b2, b1]`` (quarters of ``head_dim``).
    One exact matmul (a single +-1 per column) instead of a chain of slices in the exported graph."""
    q = head_dim // 4
    m = torch.zeros(head_dim, head_dim)
    for base in (0, 2 * q):
        for i in range(q):
            m[base + q + i, base + i] = -1.0  # out[a1 slot] = -a2
            m[base + i, base + q + i] = 1.0  # out[a2 slot] = a1
    return m


def rope_frequencies(head_dim: int, base: float) -> torch.Tensor:
    """Constant ``[2, head_dim]``: row 0 maps a y position to the angles of the first (y) half of the head
    features, row 1 maps x to the second half; per axis ``base^(-2i / (head_dim / 2))``, repeated twice
    (rotate-half pairing)."""
    half = head_dim // 2
    inv = 1.0 / (base ** (torch.arange(0, half, 2).float() / half))  # float32, as the official tables
    inv = torch.cat([inv, inv])
    f = torch.zeros(2, head_dim)
    f[0, :half] = inv
    f[1, half:] = inv
    return f


def rope_tables(grid_h: int, grid_w: int, num_special: int, freqs: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """cos/sin tables ``[P, head_dim]`` (first half: y angles, second half: x angles).

    Special tokens sit at position 0, patch ``(y, x)`` (row-major) at ``(y + 1, x + 1)``. The positions
    come from ``arange`` over the (symbolic) grid size, so the exported graph follows the input size;
    ``positions @ freqs`` is exact (one non-zero term per column).
    """
    idx = torch.arange(grid_h * grid_w, device=freqs.device)
    row = idx // grid_w
    pos = torch.stack([row, idx - row * grid_w], dim=-1).float() + 1.0  # [h*w, 2] (torchlib lacks % by a SymInt)
    pos = torch.cat([pos.new_zeros(num_special, 2), pos], dim=0)
    ang = pos @ freqs
    return ang.cos(), ang.sin()


def apply_rope(t: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """2D RoPE on ``t`` [B, heads, N, head_dim] with tables ``[N, head_dim]`` and the rotation matrix."""
    cos, sin, rot = rope
    return t * cos + (t @ rot) * sin


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int, qk_norm: bool) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)
        q, k = self.q_norm(q), self.k_norm(k)
        if rope is not None:
            q, k = apply_rope(q, rope), apply_rope(k, rope)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(B, N, C))


class Block(nn.Module):
    """Pre-norm transformer block with layer scale (LayerNorm eps 1e-5, GELU MLP)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, init_values: float, qk_norm: bool) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, num_heads, qk_norm)
        self.ls1 = LayerScale(dim, init_values)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, init_values)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), rope))
        return x + self.ls2(self.mlp(self.norm2(x)))


class _DinoEmbeddings(Dinov2WithRegistersEmbeddings):
    """transformers' DINOv2-with-registers embeddings, always resampling the position table.

    The parent skips the resampling when the input matches the table's (square) size; that test on
    the (symbolic) input shape would pin the exported graph to one case. Resampling to the same size
    is exact (bicubic weights at integer offsets are 1, 0, 0, 0), so the result is the same.
    The official VGGT also resamples with antialiased bicubic to ``(H / p, W / p)``.
    """

    def interpolate_pos_encoding(self, embeddings: torch.Tensor, height: int, width: int) -> torch.Tensor:
        table = self.position_embeddings
        num_positions = table.shape[1] - 1
        side = int(round(num_positions ** 0.5))
        dim = table.shape[-1]
        patch = self.patch_size if isinstance(self.patch_size, int) else self.patch_size[0]
        grid = table[:, 1:].reshape(1, side, side, dim).permute(0, 3, 1, 2).float()
        # antialiased bicubic exports as ONNX Resize(cubic, antialias=1, cubic_coeff_a=-0.5, exclude_outside=1)
        grid = F.interpolate(grid, size=(height // patch, width // patch), mode="bicubic", align_corners=False,
                             antialias=True).to(table.dtype)
        grid = grid.permute(0, 2, 3, 1).reshape(1, -1, dim)
        return torch.cat([table[:, :1], grid], dim=1)


class DinoPatchEmbed(nn.Module):
    """DINOv2 ViT with registers; returns the final-norm patch tokens ``[N, P, C]``."""

    def __init__(self, config: VGGTConfig) -> None:
        super().__init__()
        hf = Dinov2WithRegistersConfig(
            hidden_size=config.embed_dim, num_hidden_layers=config.encoder_depth,
            num_attention_heads=config.encoder_heads, mlp_ratio=int(config.encoder_mlp_ratio),
            image_size=config.img_size, patch_size=config.patch_size,
            num_register_tokens=config.num_register_tokens, layerscale_value=1.0, layer_norm_eps=1e-6,
            qkv_bias=True, hidden_act="gelu")
        hf._attn_implementation = "sdpa"
        self.hf_config = hf
        self.num_register_tokens = config.num_register_tokens
        self.embeddings = _DinoEmbeddings(hf)
        self.layer = nn.ModuleList([Dinov2WithRegistersLayer(hf) for _ in range(config.encoder_depth)])
        self.layernorm = nn.LayerNorm(config.embed_dim, eps=1e-6)
        nn.init.normal_(self.embeddings.position_embeddings, std=0.02)
        nn.init.normal_(self.embeddings.cls_token, std=1e-6)
        nn.init.normal_(self.embeddings.register_tokens, std=1e-6)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        x = self.embeddings(pixels)
        for layer in self.layer:
            x = layer(x)
        return self.layernorm(x)[:, 1 + self.num_register_tokens:]


def _first_and_rest(token: torch.Tensor, B: int, S: int) -> torch.Tensor:
    """``token`` [1, 2, X, C] → [B * S, X, C]: entry 0 for the first frame, entry 1 for the others.
    (A gather instead of ``cat([.., expand(S - 1)])``, so S = 1 needs no special case in the graph.)"""
    index = (torch.arange(S, device=token.device) > 0).long()
    picked = token[0].index_select(0, index)  # [S, X, C]
    return picked.unsqueeze(0).expand(B, -1, -1, -1).reshape(B * S, token.shape[2], token.shape[3])


class Aggregator(nn.Module):
    def __init__(self, config: VGGTConfig) -> None:
        super().__init__()
        c = config
        # parameters first, then children: the official registration order (state-dict order)
        self.camera_token = nn.Parameter(torch.randn(1, 2, 1, c.embed_dim) * 1e-6)
        self.register_token = nn.Parameter(torch.randn(1, 2, c.num_register_tokens, c.embed_dim) * 1e-6)
        self.patch_embed = DinoPatchEmbed(c)
        self.frame_blocks = nn.ModuleList(
            [Block(c.embed_dim, c.num_heads, c.mlp_ratio, c.init_values, qk_norm=True) for _ in range(c.depth)])
        self.global_blocks = nn.ModuleList(
            [Block(c.embed_dim, c.num_heads, c.mlp_ratio, c.init_values, qk_norm=True) for _ in range(c.depth)])
        self.patch_size = c.patch_size
        self.patch_start_idx = 1 + c.num_register_tokens
        self.head_dim = c.embed_dim // c.num_heads
        self.rope_freq = c.rope_freq
        self.register_buffer("_mean", torch.tensor(_RESNET_MEAN).view(1, 1, 3, 1, 1), persistent=False)
        self.register_buffer("_std", torch.tensor(_RESNET_STD).view(1, 1, 3, 1, 1), persistent=False)
        self.register_buffer("_rope_rot", rope_rotation(self.head_dim), persistent=False)
        self.register_buffer("_rope_freqs", rope_frequencies(self.head_dim, max(c.rope_freq, 1.0)), persistent=False)

    def forward(self, images: torch.Tensor, keep: tuple[int, ...]) -> dict[int, torch.Tensor]:
        """Tokens ``[B, S, P, 2C]`` of the rounds listed in ``keep`` (only those are kept in memory)."""
        B, S, _, H, W = images.shape
        x = ((images - self._mean) / self._std).reshape(B * S, 3, H, W)
        patches = self.patch_embed(x)
        C = patches.shape[-1]
        special = _first_and_rest(torch.cat([self.camera_token, self.register_token], dim=2), B, S)
        tokens = torch.cat([special, patches], dim=1)
        P = tokens.shape[1]
        frame_rope = global_rope = None
        if self.rope_freq > 0:
            cos, sin = rope_tables(H // self.patch_size, W // self.patch_size, self.patch_start_idx,
                                   self._rope_freqs)
            frame_rope = (cos, sin, self._rope_rot)
            # global attention: every frame's tokens at the same positions
            global_rope = (cos.repeat(S, 1), sin.repeat(S, 1), self._rope_rot)
        out: dict[int, torch.Tensor] = {}
        for i, (frame_block, global_block) in enumerate(zip(self.frame_blocks, self.global_blocks)):
            tokens = frame_block(tokens.reshape(B * S, P, C), frame_rope)
            frame_out = tokens.reshape(B, S, P, C)
            tokens = global_block(tokens.reshape(B, S * P, C), global_rope)
            if i in keep:
                out[i] = torch.cat([frame_out, tokens.reshape(B, S, P, C)], dim=-1)
        return out

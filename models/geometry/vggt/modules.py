"""VGGT (Visual Geometry Grounded Transformer) geometry network: torch module, checkpoint I/O, ONNX export.

Architecture of facebookresearch/vggt (VGGT-1B), re-implemented here from its published description and
checkpoint layout:

* **Patch embedding**: a DINOv2 ViT-L/14 with 4 registers (transformers' ``Dinov2WithRegisters*``
  modules), whose final-norm patch tokens start the sequence of every frame.
* **Aggregator**: per frame, one camera token and 4 register tokens (the first frame has its own
  learned pair, all other frames share a second pair) are prepended to the patch tokens; then
  ``depth`` rounds of *frame* attention (tokens of one frame) followed by *global* attention (tokens of
  all frames). Both use 2D rotary position embeddings (special tokens at position 0, patch ``(y, x)``
  at ``(y + 1, x + 1)``) and LayerNorm qk-normalisation. The output of round ``i`` is the concatenation
  ``[frame_i, global_i]`` (width ``2 * embed_dim``).
* **Camera head**: the camera tokens of the last round go through a 4-block trunk four times
  (adaLN-modulated by the embedding of the previous estimate) and predict ``pose_enc`` [B, S, 9] =
  translation (3), quaternion ``xyzw`` (4), field of view ``(fov_h, fov_w)`` in radians (2): the
  world-to-camera pose in the first camera's frame (``absT_quaR_FoV``). The FoV goes through a ReLU.
* **DPT heads** on rounds ``dpt_layers``: depth (``exp``) + confidence (``1 + exp``), and world points
  (``sign(x) * expm1(|x|)``) + confidence (``1 + exp``), at the input resolution.

The track head of the official model is not built; its checkpoint entries are ignored (and reported).

Our module tree mirrors the official one (same parameter names), except for

* the DINOv2 encoder (``aggregator.patch_embed``), which uses transformers' module names with separate
  q/k/v projections, and
* the two DPT heads, evaluated as one module ``dpt_heads`` with their weights stacked along the channel
  axis and grouped convolutions (half the ONNX graph, the same arithmetic per head).

``vggt_state_dict_official`` and ``vggt_state_dict_from_official`` translate between the layouts
(fusing/splitting ``qkv``, splitting/stacking the heads); the loader checks every name and shape first.

Export notes (``torch.onnx.export(dynamo=True)`` with dynamic S, H, W): RoPE positions and the DPT
sin/cos embeddings are built from ``arange`` over the symbolic sizes (no Python floats of sizes, no
shape-dependent branches); the DINOv2 position table is always resampled (antialiased bicubic, which
exports as ONNX ``Resize(cubic, antialias=1)``); the first/other-frame special tokens are gathered with
an index instead of an ``S - 1`` expand.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

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

from navcrafter.models.runtime.onnxio import sha256_file

_RESNET_MEAN = (0.485, 0.456, 0.406)
_RESNET_STD = (0.229, 0.224, 0.225)

OUTPUT_NAMES = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")
IGNORED_PREFIXES = ("track_head.",)  # official checkpoint parts we do not build
KEY_LIST_1B = Path(__file__).parents[1] / "keys" / "vggt_1b.txt"


# --------------------------------------------------------------------------------------------------
# Config
# --------------------------------------------------------------------------------------------------
@dataclass
class VGGTConfig:
    """Sizes of a VGGT network. ``vggt_1b()`` is the published model, ``tiny()`` a test-sized one."""

    img_size: int = 518  # training resolution: sets the DINOv2 position table ((img_size / patch)^2 + 1)
    patch_size: int = 14
    embed_dim: int = 1024
    depth: int = 24  # alternating-attention rounds (frame + global block each)
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    rope_freq: float = 100.0
    init_values: float = 0.01  # layer-scale init of aggregator and camera-head blocks
    # DINOv2 patch embedding (ViT-L/14 with registers; its width is embed_dim)
    encoder_depth: int = 24
    encoder_heads: int = 16
    encoder_mlp_ratio: int = 4
    # camera head
    camera_trunk_depth: int = 4
    camera_heads: int = 16
    camera_iterations: int = 4
    # DPT heads
    dpt_features: int = 256
    dpt_out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024)
    dpt_layers: tuple[int, int, int, int] = (4, 11, 17, 23)
    extra: dict = field(default_factory=dict)  # free-form notes (kept in manifests)

    def __post_init__(self) -> None:
        self.dpt_out_channels = tuple(int(c) for c in self.dpt_out_channels)
        self.dpt_layers = tuple(int(i) for i in self.dpt_layers)
        if len(self.dpt_out_channels) != 4 or len(self.dpt_layers) != 4:
            raise ValueError("dpt_out_channels and dpt_layers need 4 entries each")
        if any(not 0 <= i < self.depth for i in self.dpt_layers):
            raise ValueError(f"dpt_layers {self.dpt_layers} must index the {self.depth} aggregator rounds")
        if self.embed_dim % self.num_heads or (self.embed_dim // self.num_heads) % 4:
            raise ValueError("embed_dim / num_heads must be a multiple of 4 (2D RoPE)")
        if self.img_size % self.patch_size:
            raise ValueError(f"img_size {self.img_size} must be a multiple of patch_size {self.patch_size}")

    @classmethod
    def vggt_1b(cls) -> VGGTConfig:
        return cls()

    @classmethod
    def tiny(cls) -> VGGTConfig:
        # one aggregator round (every DPT branch reads it) keeps the test export small; two refinement
        # iterations keep the camera head's feedback path in the graph
        return cls(img_size=56, patch_size=14, embed_dim=32, depth=1, num_heads=2, num_register_tokens=4,
                   encoder_depth=1, encoder_heads=2, camera_trunk_depth=1, camera_heads=2, camera_iterations=2,
                   dpt_features=16, dpt_out_channels=(8, 16, 32, 32), dpt_layers=(0, 0, 0, 0))

    @classmethod
    def from_dict(cls, d: dict) -> VGGTConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# --------------------------------------------------------------------------------------------------
# Building blocks (official parameter names: norm1, attn.qkv, attn.q_norm/k_norm, attn.proj, ls1, ...)
# --------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------
# DINOv2 patch embedding (transformers modules)
# --------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------
# Aggregator
# --------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------
# Camera head
# --------------------------------------------------------------------------------------------------
class CameraHead(nn.Module):
    def __init__(self, config: VGGTConfig) -> None:
        super().__init__()
        dim = 2 * config.embed_dim
        self.target_dim = 9
        self.iterations = config.camera_iterations
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, self.target_dim))
        self.trunk = nn.Sequential(*[Block(dim, config.camera_heads, 4.0, config.init_values, qk_norm=False)
                                     for _ in range(config.camera_trunk_depth)])
        self.token_norm = nn.LayerNorm(dim)
        self.trunk_norm = nn.LayerNorm(dim)
        self.embed_pose = nn.Linear(self.target_dim, dim)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim, 3 * dim))
        self.adaln_norm = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.pose_branch = Mlp(dim, dim // 2, self.target_dim)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """``tokens`` [B, S, P, 2C] of the last round → activated ``pose_enc`` [B, S, 9] of the last iteration."""
        pose_tokens = self.token_norm(tokens[:, :, 0])
        B, S, _ = pose_tokens.shape
        raw = None
        normed = self.adaln_norm(pose_tokens)
        for _ in range(self.iterations):
            # the refinement feeds back the raw (pre-activation) estimate
            cond = self.embed_pose(self.empty_pose_tokens.expand(B, S, -1) if raw is None else raw)
            shift, scale, gate = self.poseLN_modulation(cond).chunk(3, dim=-1)
            h = gate * (normed * (1 + scale) + shift) + pose_tokens
            delta = self.pose_branch(self.trunk_norm(self.trunk(h)))
            raw = delta if raw is None else raw + delta
        # translation and quaternion linear, field of view through a ReLU (only the last estimate is returned)
        return torch.cat([raw[..., :7], F.relu(raw[..., 7:])], dim=-1)


# --------------------------------------------------------------------------------------------------
# DPT head
# --------------------------------------------------------------------------------------------------
def _centred_uv(grid_h: int, grid_w: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``u [w]``, ``v [h]`` of a centred grid normalised by its diagonal: ``u_j = (2j + 1 - w) / sqrt(w^2 + h^2)``.

    The closed form of the official ``linspace`` construction (its aspect ratio W / H equals w / h, the
    grids being patch- or pixel-aligned). ``arange`` with symbolic bounds and a scalar built from the
    symbolic sizes: the exported graph follows the input size.
    """
    diag = torch.scalar_tensor(grid_w * grid_w + grid_h * grid_h, dtype=torch.float32, device=device).sqrt()
    u = torch.arange(1 - grid_w, grid_w, 2, dtype=torch.float32, device=device) / diag
    v = torch.arange(1 - grid_h, grid_h, 2, dtype=torch.float32, device=device) / diag
    return u, v


def sincos_constants(channels: int, omega_0: float = 100.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Frequencies and phases ``[channels / 2, 1, 1]`` of ``uv_sincos_embed``: ``w_k = omega_0^(-k / (C / 4))``
    for ``k < C / 4``, twice; phase 0 (sin) then pi / 2 (cos)."""
    quarter = channels // 4
    omega = [omega_0 ** (-k / quarter) for k in range(quarter)]
    freq = torch.tensor(omega + omega, dtype=torch.float32).view(-1, 1, 1)
    phase = torch.tensor([0.0] * quarter + [math.pi / 2] * quarter, dtype=torch.float32).view(-1, 1, 1)
    return freq, phase


def uv_sincos_embed(u: torch.Tensor, v: torch.Tensor, freq: torch.Tensor, phase: torch.Tensor,
                    ratio: float = 0.1) -> torch.Tensor:
    """``ratio`` x sin/cos embedding ``[C, h, w]`` of ``u [w]``, ``v [h]``: channels ``[sin(u w_k), cos(u w_k),
    sin(v w_k), cos(v w_k)]`` (constants from ``sincos_constants(C)``).

    ``cos(a)`` is computed as ``sin(a + pi / 2)`` (one op for both; |a| <= 1, so the difference is at
    float32 rounding level).
    """
    h, w = v.shape[0], u.shape[0]
    eu = torch.sin(freq * u.view(1, 1, w) + phase)  # [C/2, 1, w]
    ev = torch.sin(freq * v.view(1, h, 1) + phase)  # [C/2, h, 1]
    return torch.cat([eu.expand(-1, h, w), ev.expand(-1, h, w)], dim=0) * ratio


def _interp(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return F.interpolate(x, size=size, mode="bilinear", align_corners=True)


class ResidualConvUnit(nn.Module):
    def __init__(self, features: int, groups: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, groups=groups)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1, groups=groups)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # The official unit applies an in-place ReLU to its input before the skip connection, so the skip
        # carries relu(x), not x (the published weights were trained that way).
        x = F.relu(x)
        return self.conv2(F.relu(self.conv1(x))) + x


class FeatureFusionBlock(nn.Module):
    def __init__(self, features: int, groups: int, has_residual: bool = True) -> None:
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1, groups=groups)
        if has_residual:
            self.resConfUnit1 = ResidualConvUnit(features, groups)
        self.has_residual = has_residual
        self.resConfUnit2 = ResidualConvUnit(features, groups)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None,
                size: tuple[int, int] | None = None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            size = (x.shape[-2] * 2, x.shape[-1] * 2)
        return self.out_conv(_interp(x, size))


# the official heads, in our channel order: (name, output channels, value activation)
DPT_HEADS = (("depth", 2, "exp"), ("point", 4, "inv_log"))


class DPTHeads(nn.Module):
    """The official depth and point DPT heads, evaluated together.

    Both heads have the same structure, so their weights are stacked along the channel axis (depth
    first) and every convolution runs with ``groups=2``: one pass computes both heads exactly as two
    separate ones would (each group only sees its own channels), with half the graph. The two
    LayerNorms share their normalisation and keep their own affine parameters ``norm_weight``/
    ``norm_bias`` ``[2, 2C]``; the last 1x1 convolution, whose output widths differ (2 and 4), is one
    block-diagonal convolution. ``vggt_state_dict_official`` splits all of this back into the official
    ``depth_head.*`` / ``point_head.*`` tensors.
    """

    def __init__(self, config: VGGTConfig) -> None:
        super().__init__()
        G = len(DPT_HEADS)
        dim_in = 2 * config.embed_dim
        oc = config.dpt_out_channels
        feats = config.dpt_features
        self.groups = G
        self.patch_size = config.patch_size
        self.layers = config.dpt_layers
        self.dim_in = dim_in
        self.norm_weight = nn.Parameter(torch.ones(G, dim_in))
        self.norm_bias = nn.Parameter(torch.zeros(G, dim_in))
        self.projects = nn.ModuleList([nn.Conv2d(G * dim_in, G * c, 1, groups=G) for c in oc])
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(G * oc[0], G * oc[0], kernel_size=4, stride=4, groups=G),
            nn.ConvTranspose2d(G * oc[1], G * oc[1], kernel_size=2, stride=2, groups=G),
            nn.Identity(),
            nn.Conv2d(G * oc[3], G * oc[3], kernel_size=3, stride=2, padding=1, groups=G),
        ])
        scratch = nn.Module()
        for i, c in enumerate(oc, start=1):
            setattr(scratch, f"layer{i}_rn", nn.Conv2d(G * c, G * feats, 3, padding=1, bias=False, groups=G))
        scratch.refinenet1 = FeatureFusionBlock(G * feats, G)
        scratch.refinenet2 = FeatureFusionBlock(G * feats, G)
        scratch.refinenet3 = FeatureFusionBlock(G * feats, G)
        scratch.refinenet4 = FeatureFusionBlock(G * feats, G, has_residual=False)
        scratch.output_conv1 = nn.Conv2d(G * feats, G * (feats // 2), 3, padding=1, groups=G)
        out_dims = sum(d for _, d, _ in DPT_HEADS)
        scratch.output_conv2 = nn.Sequential(nn.Conv2d(G * (feats // 2), G * 32, 3, padding=1, groups=G), nn.ReLU(),
                                             nn.Conv2d(G * 32, out_dims, 1))
        self.scratch = scratch
        for c in sorted(set(oc) | {feats // 2}):  # sin/cos embedding constants per width (not in the state dict)
            freq, phase = sincos_constants(c)
            self.register_buffer(f"_freq_{c}", freq, persistent=False)
            self.register_buffer(f"_phase_{c}", phase, persistent=False)
        with torch.no_grad():  # block-diagonal last layer: each head's outputs see only its own 32 channels
            self.scratch.output_conv2[2].weight.mul_(self.block_mask())

    def block_mask(self) -> torch.Tensor:
        w = self.scratch.output_conv2[2].weight
        mask = torch.zeros(w.shape[0], w.shape[1], 1, 1, device=w.device, dtype=w.dtype)
        row = 0
        for g, (_, d, _) in enumerate(DPT_HEADS):
            mask[row:row + d, 32 * g:32 * (g + 1)] = 1
            row += d
        return mask

    def _pos(self, cache: dict, kind: str, gh: int, gw: int, channels: int, device: torch.device) -> torch.Tensor:
        """The embedding for ``channels`` per head, repeated for each head: ``[G * channels, gh, gw]`` (cached)."""
        if kind not in cache:
            cache[kind] = _centred_uv(gh, gw, device)
        if (kind, channels) not in cache:
            emb = uv_sincos_embed(*cache[kind], getattr(self, f"_freq_{channels}"), getattr(self, f"_phase_{channels}"))
            cache[kind, channels] = emb.repeat(self.groups, 1, 1)
        return cache[kind, channels]

    def forward(self, tokens: dict[int, torch.Tensor], patch_start_idx: int, H: int, W: int
                ) -> dict[str, torch.Tensor]:
        G = self.groups
        ph, pw = H // self.patch_size, W // self.patch_size
        cache: dict = {}
        maps: dict[int, torch.Tensor] = {}  # normalised token map per aggregator round (shared by branches)
        B, S = tokens[self.layers[0]].shape[:2]
        feats = []
        for i, layer in enumerate(self.layers):
            if layer not in maps:
                x = tokens[layer][:, :, patch_start_idx:].reshape(B * S, ph * pw, self.dim_in)
                x = F.layer_norm(x, (self.dim_in,))  # eps 1e-5 as nn.LayerNorm; affine per head below
                x = x[:, :, None, :] * self.norm_weight + self.norm_bias  # [BS, P, G, 2C]
                maps[layer] = x.permute(0, 2, 3, 1).reshape(B * S, G * self.dim_in, ph, pw)
            x = self.projects[i](maps[layer])
            x = x + self._pos(cache, "patch", ph, pw, x.shape[1] // G, x.device)
            feats.append(self.resize_layers[i](x))
        s = self.scratch
        l1, l2, l3, l4 = (s.layer1_rn(feats[0]), s.layer2_rn(feats[1]), s.layer3_rn(feats[2]),
                          s.layer4_rn(feats[3]))
        out = s.refinenet4(l4, size=l3.shape[2:])
        out = s.refinenet3(out, l3, size=l2.shape[2:])
        out = s.refinenet2(out, l2, size=l1.shape[2:])
        out = s.refinenet1(out, l1)
        out = s.output_conv1(out)
        out = _interp(out, (ph * self.patch_size, pw * self.patch_size))
        out = out + self._pos(cache, "pixel", out.shape[-2], out.shape[-1], out.shape[1] // G, out.device)
        out = s.output_conv2(out).permute(0, 2, 3, 1)  # [B*S, H, W, 2 + 4]
        out = out.reshape(B, S, out.shape[1], out.shape[2], out.shape[3])
        result = {}
        start = 0
        for name, d, activation in DPT_HEADS:
            values, conf = out[..., start:start + d - 1], out[..., start + d - 1]
            start += d
            if activation == "exp":
                values = torch.exp(values)
            else:  # "inv_log"
                values = torch.sign(values) * torch.expm1(values.abs())
            result[name] = values
            result[name + "_conf"] = 1.0 + torch.exp(conf)
        return result


# --------------------------------------------------------------------------------------------------
# VGGT
# --------------------------------------------------------------------------------------------------
class VGGT(nn.Module):
    """VGGT without the track head. ``forward(images [B, S, 3, H, W] in [0, 1])`` → dict of
    ``pose_enc`` [B, S, 9], ``depth`` [B, S, H, W, 1], ``depth_conf`` [B, S, H, W],
    ``world_points`` [B, S, H, W, 3], ``world_points_conf`` [B, S, H, W] (H, W multiples of the patch)."""

    def __init__(self, config: VGGTConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or VGGTConfig()
        self.aggregator = Aggregator(config)
        self.camera_head = CameraHead(config)
        self.dpt_heads = DPTHeads(config)  # official point_head + depth_head
        self._keep = tuple(sorted(set(config.dpt_layers) | {config.depth - 1}))

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        if images.dim() == 4:
            images = images.unsqueeze(0)
        H, W = images.shape[-2], images.shape[-1]
        tokens = self.aggregator(images, self._keep)
        start = self.aggregator.patch_start_idx
        pose_enc = self.camera_head(tokens[self.config.depth - 1])
        dense = self.dpt_heads(tokens, start, H, W)
        return {"pose_enc": pose_enc, "depth": dense["depth"], "depth_conf": dense["depth_conf"],
                "world_points": dense["point"], "world_points_conf": dense["point_conf"]}


class VGGTExportWrapper(nn.Module):
    """``images`` → the outputs as a tuple in ``OUTPUT_NAMES`` order (what the ONNX graph returns)."""

    def __init__(self, model: VGGT) -> None:
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor):
        out = self.model(images)
        return tuple(out[name] for name in OUTPUT_NAMES)


# --------------------------------------------------------------------------------------------------
# Official checkpoint layout
# --------------------------------------------------------------------------------------------------
class VGGTWeightsError(ValueError):
    """A checkpoint does not match the official VGGT layout for this config."""


_ENC = "aggregator.patch_embed."
# ours (transformers DINOv2) -> official (DinoVisionTransformer), outside the blocks
_ENC_TOP = [
    ("embeddings.cls_token", "cls_token"),
    ("embeddings.position_embeddings", "pos_embed"),
    ("embeddings.register_tokens", "register_tokens"),
    ("embeddings.mask_token", "mask_token"),
    ("embeddings.patch_embeddings.projection.weight", "patch_embed.proj.weight"),
    ("embeddings.patch_embeddings.projection.bias", "patch_embed.proj.bias"),
]
# within block i: ours -> official (q/k/v handled separately)
_ENC_BLOCK = [
    ("norm1.weight", "norm1.weight"), ("norm1.bias", "norm1.bias"),
    ("attention.o_proj.weight", "attn.proj.weight"), ("attention.o_proj.bias", "attn.proj.bias"),
    ("layer_scale1.lambda1", "ls1.gamma"),
    ("norm2.weight", "norm2.weight"), ("norm2.bias", "norm2.bias"),
    ("mlp.fc1.weight", "mlp.fc1.weight"), ("mlp.fc1.bias", "mlp.fc1.bias"),
    ("mlp.fc2.weight", "mlp.fc2.weight"), ("mlp.fc2.bias", "mlp.fc2.bias"),
    ("layer_scale2.lambda1", "ls2.gamma"),
]


def _encoder_depth(sd: dict, prefix: str, block_key: str) -> int:
    n = 0
    while f"{prefix}{n}.{block_key}" in sd:
        n += 1
    return n


def vggt_state_dict_official(model_or_sd: VGGT | dict) -> dict[str, torch.Tensor]:
    """Our weights in the official layout (key names, fused ``qkv``, separate DPT heads, official order).
    Works on meta tensors."""
    ours = model_or_sd.state_dict() if isinstance(model_or_sd, nn.Module) else dict(model_or_sd)
    out: dict[str, torch.Tensor] = {}
    agg_tokens = ["aggregator.camera_token", "aggregator.register_token"]
    for k in agg_tokens:
        out[k] = ours[k]
    for mine, theirs in _ENC_TOP:
        out[_ENC + theirs] = ours[_ENC + mine]
    n = _encoder_depth(ours, _ENC + "layer.", "norm1.weight")
    for i in range(n):
        src, dst = f"{_ENC}layer.{i}.", f"{_ENC}blocks.{i}."
        for mine, theirs in _ENC_BLOCK[:2]:
            out[dst + theirs] = ours[src + mine]
        for part in ("weight", "bias"):
            out[f"{dst}attn.qkv.{part}"] = torch.cat(
                [ours[f"{src}attention.{p}_proj.{part}"] for p in ("q", "k", "v")], dim=0)
        for mine, theirs in _ENC_BLOCK[2:]:
            out[dst + theirs] = ours[src + mine]
    out[_ENC + "norm.weight"] = ours[_ENC + "layernorm.weight"]
    out[_ENC + "norm.bias"] = ours[_ENC + "layernorm.bias"]
    for k, v in ours.items():  # the rest has the official name already (module order = official order)
        if not k.startswith((_ENC, _DPT)) and k not in agg_tokens:
            out[k] = v
    split = {name: {} for name, _, _ in DPT_HEADS}
    for k, v in ours.items():
        if k.startswith(_DPT):
            for name, part in _split_dpt(k[len(_DPT):], v).items():
                split[name].update(part)
    for name in ("point", "depth"):  # official order: point_head before depth_head
        out.update(split[name])
    return out


_DPT = "dpt_heads."
_DPT_LAST = "scratch.output_conv2.2."


def _split_dpt(suffix: str, v: torch.Tensor) -> dict[str, dict[str, torch.Tensor]]:
    """One stacked ``dpt_heads`` tensor → ``{head: {official key: tensor}}``."""
    out: dict[str, dict[str, torch.Tensor]] = {}
    row = 0
    for g, (name, d, _) in enumerate(DPT_HEADS):
        prefix = f"{name}_head."
        if suffix in ("norm_weight", "norm_bias"):
            part = {prefix + suffix.replace("_", "."): v[g]}
        elif suffix == _DPT_LAST + "weight":
            part = {prefix + suffix: v[row:row + d, 32 * g:32 * (g + 1)]}
        elif suffix == _DPT_LAST + "bias":
            part = {prefix + suffix: v[row:row + d]}
        else:
            part = {prefix + suffix: v.chunk(len(DPT_HEADS), dim=0)[g]}
        out[name] = part
        row += d
    return out


def _stack_dpt(official: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The official ``depth_head.*`` / ``point_head.*`` tensors → stacked ``dpt_heads.*`` tensors."""
    out: dict[str, torch.Tensor] = {}
    first = f"{DPT_HEADS[0][0]}_head."
    for key in [k for k in official if k.startswith(first)]:
        suffix = key[len(first):]
        parts = [official[f"{name}_head.{suffix}"] for name, _, _ in DPT_HEADS]
        if suffix in ("norm.weight", "norm.bias"):
            out[_DPT + suffix.replace(".", "_")] = torch.stack(parts)
        elif suffix == _DPT_LAST + "weight":
            rows = sum(p.shape[0] for p in parts)
            w = torch.zeros(rows, sum(p.shape[1] for p in parts), *parts[0].shape[2:], dtype=parts[0].dtype,
                            device=parts[0].device)
            row = col = 0
            for p in parts:
                w[row:row + p.shape[0], col:col + p.shape[1]] = p
                row, col = row + p.shape[0], col + p.shape[1]
            out[_DPT + suffix] = w
        else:
            out[_DPT + suffix] = torch.cat(parts, dim=0)
    return out


def vggt_state_dict_from_official(official: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Official-layout weights (without ``track_head.*``) → our module's state dict (splits ``qkv``,
    stacks the two DPT heads)."""
    out: dict[str, torch.Tensor] = {}
    for mine, theirs in _ENC_TOP:
        out[_ENC + mine] = official[_ENC + theirs]
    n = _encoder_depth(official, _ENC + "blocks.", "norm1.weight")
    for i in range(n):
        src, dst = f"{_ENC}blocks.{i}.", f"{_ENC}layer.{i}."
        for part in ("weight", "bias"):
            q, k, v = official[f"{src}attn.qkv.{part}"].chunk(3, dim=0)
            out[f"{dst}attention.q_proj.{part}"] = q
            out[f"{dst}attention.k_proj.{part}"] = k
            out[f"{dst}attention.v_proj.{part}"] = v
        for mine, theirs in _ENC_BLOCK:
            out[dst + mine] = official[src + theirs]
    out[_ENC + "layernorm.weight"] = official[_ENC + "norm.weight"]
    out[_ENC + "layernorm.bias"] = official[_ENC + "norm.bias"]
    heads = tuple(f"{name}_head." for name, _, _ in DPT_HEADS)
    for k, v in official.items():
        if not k.startswith((_ENC,) + heads):
            out[k] = v
    out.update(_stack_dpt(official))
    return out


def official_layout(model: VGGT) -> dict[str, tuple[int, ...]]:
    """Official key → shape expected for ``model``'s config (in the official order)."""
    return {k: tuple(v.shape) for k, v in vggt_state_dict_official(model).items()}


def read_key_list(path: Path = KEY_LIST_1B) -> tuple[dict[str, tuple[int, ...]], dict[str, tuple[int, ...]]]:
    """The committed official key list: (used keys → shape, ignored keys → shape), in file order."""
    used: dict[str, tuple[int, ...]] = {}
    ignored: dict[str, tuple[int, ...]] = {}
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        shape = tuple(int(s) for s in parts[1].split("x")) if parts[1] != "-" else ()
        (ignored if len(parts) > 2 and parts[2] == "ignored" else used)[parts[0]] = shape
    return used, ignored


def read_checkpoint(path: Path) -> dict[str, torch.Tensor]:
    """A state dict from ``.safetensors`` or a ``.pt``/``.pth``/``.bin`` (``torch.load(weights_only=True)``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"VGGT checkpoint {path} does not exist")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        try:
            return load_file(str(path), device="cpu")
        except Exception as exc:  # safetensors raises its own error types
            raise VGGTWeightsError(f"{path}: not a readable safetensors file ({exc})") from exc
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise VGGTWeightsError(f"{path}: cannot be read as a tensor-only torch checkpoint "
                               f"(torch.load(weights_only=True): {exc})") from exc
    if isinstance(sd, dict) and "model" in sd and isinstance(sd["model"], dict):
        sd = sd["model"]
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise VGGTWeightsError(f"{path}: expected a state dict (name -> tensor), got {type(sd).__name__}")
    return sd


def _first(items, n: int = 5) -> str:
    items = list(items)
    return ", ".join(items[:n]) + (f", ... ({len(items)} in all)" if len(items) > n else "")


def check_official_layout(sd: dict[str, torch.Tensor], model: VGGT, source: str = "checkpoint") -> list[str]:
    """Raise ``VGGTWeightsError`` unless ``sd`` has exactly the official keys and shapes for ``model``'s
    config (``track_head.*`` excepted). Returns the ignored keys."""
    expected = official_layout(model)
    ignored = [k for k in sd if k.startswith(IGNORED_PREFIXES)]
    present = {k: tuple(v.shape) for k, v in sd.items() if not k.startswith(IGNORED_PREFIXES)}
    missing = [k for k in expected if k not in present]
    unexpected = [k for k in present if k not in expected]
    wrong = [f"{k} (file {list(present[k])}, expected {list(expected[k])})"
             for k in expected if k in present and present[k] != expected[k]]
    if missing or unexpected or wrong:
        parts = [f"{source} does not match the official VGGT layout for this config "
                 f"(embed_dim={model.config.embed_dim}, depth={model.config.depth})"]
        if missing:
            parts.append(f"missing keys: {_first(missing)}")
        if unexpected:
            parts.append(f"unexpected keys: {_first(unexpected)}")
        if wrong:
            parts.append(f"wrong shapes: {_first(wrong)}")
        raise VGGTWeightsError("; ".join(parts))
    return ignored


def load_vggt_weights(model: VGGT, path: Path) -> dict:
    """Load an official-layout checkpoint (``.safetensors`` preferred, or a tensor-only ``.pt``) into ``model``.

    Names and shapes are verified first (clear error naming the file and the first offending keys);
    ``track_head.*`` entries are ignored and listed in the returned report
    ``{"path", "loaded", "ignored", "sha256"}``.
    """
    path = Path(path)
    sd = read_checkpoint(path)
    ignored = check_official_layout(sd, model, source=f"checkpoint {path}")
    ours = vggt_state_dict_from_official({k: v for k, v in sd.items() if not k.startswith(IGNORED_PREFIXES)})
    on_meta = any(p.is_meta for p in model.parameters())
    model.load_state_dict(ours, strict=True, assign=on_meta)
    return {"path": str(path), "loaded": len(sd) - len(ignored), "ignored": ignored, "sha256": sha256_file(path)}


def save_official_safetensors(model: VGGT, path: Path) -> Path:
    """Write ``model``'s weights in the official layout as safetensors."""
    from safetensors.torch import save_file

    sd = {k: v.detach().contiguous().cpu() for k, v in vggt_state_dict_official(model).items()}
    save_file(sd, str(path))
    return Path(path)


# --------------------------------------------------------------------------------------------------
# ONNX export
# --------------------------------------------------------------------------------------------------
def export_geometry(out_dir: Path, config: VGGTConfig, weights: Path | None = None, seed: int = 0) -> Path:
    """Export VGGT to ``out_dir/geometry.onnx`` (+ ``.data``) and write its manifest; returns ``out_dir``.

    Input ``images`` [1, S, 3, H, W] float32 in [0, 1] with dynamic S, H, W (H, W multiples of the
    patch size); outputs as in ``OUTPUT_NAMES``. Random weights (``torch.manual_seed(seed)``) unless
    ``weights`` names an official checkpoint.
    """
    from torch.export import Dim

    from navcrafter.models.runtime import onnxio

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    model = VGGT(config).eval()
    if weights is None:
        weights_info = {"source": "random", "seed": int(seed)}
    else:
        report = load_vggt_weights(model, Path(weights))
        weights_info = {"source": "checkpoint", "path": str(weights), "sha256": report["sha256"],
                        "ignored_keys": len(report["ignored"])}
    p = config.patch_size
    example = torch.rand(1, 2, 3, 2 * p, 3 * p)
    s = Dim("S", min=1, max=1024)
    h = Dim("h", min=1, max=256)
    w = Dim("w", min=1, max=256)
    dynamic = ({1: s, 3: p * h, 4: p * w},)
    info = onnxio.export_graph(VGGTExportWrapper(model), (example,), out_dir / "geometry.onnx",
                               input_names=["images"], output_names=list(OUTPUT_NAMES), dynamic_shapes=dynamic)
    info.notes = ("images [1,S,3,H,W] float32 in [0,1], H and W multiples of patch_size; pose_enc [1,S,9] = "
                  "w2c translation, quaternion xyzw, fov_h, fov_w (absT_quaR_FoV); depth [1,S,H,W,1]; "
                  "*_conf = 1 + exp(.) >= 1")
    cfg = config.to_dict()
    cfg.update({"img_size": config.img_size, "patch_size": config.patch_size, "input_range": [0.0, 1.0],
                "pose_encoding": "absT_quaR_FoV", "track_head": "not exported"})
    onnxio.write_manifest(out_dir, kind="geometry", architecture="vggt", config=cfg, weights=weights_info,
                          graphs={"geometry": info})
    return out_dir

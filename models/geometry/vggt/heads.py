"""VGGT heads: the camera head (iterative, adaLN-modulated trunk) and both DPT heads evaluated as one stacked module."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from navcrafter.models.geometry.vggt.modules import Block, Mlp

if TYPE_CHECKING:
    from navcrafter.models.geometry.vggt.config import VGGTConfig


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

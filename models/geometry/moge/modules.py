"""MoGe-2 building blocks: the convolutional neck and heads, the DINOv2 encoder with its intermediate-layer features,
the traceable bicubic position-embedding resampling and the view-plane UV channels."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from navcrafter.models.geometry.moge.config import _ACTIVATIONS, IMAGENET_MEAN, IMAGENET_STD

if TYPE_CHECKING:
    from navcrafter.models.geometry.moge.config import MoGe2Config


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "group_norm":
        return nn.GroupNorm(channels // 32, channels)
    if kind == "layer_norm":
        return nn.GroupNorm(1, channels)
    if kind == "instance_norm":
        return nn.InstanceNorm2d(channels)
    return nn.Identity()


def _conv3(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel_size=3, padding=1, padding_mode="replicate")


class _ResBlock(nn.Module):
    """Pre-activation residual block; ``layers`` = [norm, act, conv3, norm, act, conv3] (official indices)."""

    def __init__(self, channels: int, hidden: int, config: MoGe2Config) -> None:
        super().__init__()
        act = _ACTIVATIONS[config.activation]
        self.layers = nn.Sequential(_norm(config.res_block_in_norm, channels), act(), _conv3(channels, hidden),
                                    _norm(config.res_block_hidden_norm, hidden), act(), _conv3(hidden, channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.layers(x)


def _resampler(kind: str, cin: int, cout: int) -> nn.Sequential:
    """x2 upsampling followed by a 3x3 convolution (official ``Resampler`` layouts)."""
    if kind == "conv_transpose":
        return nn.Sequential(nn.ConvTranspose2d(cin, cout, kernel_size=2, stride=2), _conv3(cout, cout))
    mode = {"bilinear": dict(mode="bilinear", align_corners=False), "nearest": dict(mode="nearest")}[kind]
    return nn.Sequential(nn.Upsample(scale_factor=2, **mode), _conv3(cin, cout))


class _ConvStack(nn.Module):
    """A coarse-to-fine pyramid: per level, add the (1x1-projected) input, run residual blocks, emit an
    (optionally 1x1-projected) output, upsample into the next level."""

    def __init__(self, dim_in: list[int | None], dims: tuple[int, ...], blocks: tuple[int, ...],
                 dim_out: list[int | None], config: MoGe2Config) -> None:
        super().__init__()
        mult = config.res_block_hidden_mult
        self.input_blocks = nn.ModuleList(nn.Conv2d(i, d, 1) if i is not None else nn.Identity()
                                          for i, d in zip(dim_in, dims))
        self.resamplers = nn.ModuleList(_resampler(kind, a, b)
                                        for kind, a, b in zip(config.resamplers, dims[:-1], dims[1:]))
        self.res_blocks = nn.ModuleList(nn.Sequential(*(_ResBlock(d, d * mult, config) for _ in range(n)))
                                        for d, n in zip(dims, blocks))
        self.output_blocks = nn.ModuleList(nn.Conv2d(d, o, 1) if o is not None else nn.Identity()
                                           for d, o in zip(dims, dim_out))

    def forward(self, inputs: list[torch.Tensor]) -> list[torch.Tensor]:
        outputs = []
        x = None
        for level, (feature, blocks, out) in enumerate(zip(inputs, self.res_blocks, self.output_blocks)):
            feature = self.input_blocks[level](feature)
            x = feature if x is None else x + feature
            x = blocks(x)
            outputs.append(out(x))
            if level < len(self.resamplers):
                x = self.resamplers[level](x)
        return outputs


class _MLP(nn.Sequential):
    """Linear/ReLU stack (official ``MLP``: indices 0, 2, 4, ... are the linear layers)."""

    def __init__(self, dims: tuple[int, ...]) -> None:
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
            layers.append(nn.Linear(a, b))
            if i < len(dims) - 2:
                layers.append(nn.ReLU())
        super().__init__(*layers)


def _bicubic_fold(n_in: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Constants of ``_bicubic_matrices``: the input columns -2 .. n_in + 1 and the [n_in + 4, n_in] matrix
    folding the four virtual border columns onto the first and last ones (torch clamps tap indices)."""
    eye = torch.eye(n_in)
    return torch.arange(-2.0, n_in + 2.0), torch.cat([eye[:1], eye[:1], eye, eye[-1:], eye[-1:]])


def _bicubic_matrices(h, w, n_in: int, offset: float, columns: torch.Tensor,
                      fold: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The [h, n_in] and [w, n_in] weights of torch's bicubic resampling (A = -0.75, align_corners=False,
    clamped taps) with ``scale_factor = (n_out + offset) / n_in`` (DINOv2's positional-embedding
    interpolation), for both axes in one pass of graph-friendly ops. At h = w = n_in the offset is 0 (the
    matrices are then exactly the identity: DINOv2 uses its embedding as is at the pretraining grid)."""
    rows = torch.arange(h, dtype=columns.dtype, device=columns.device)
    cols = torch.arange(w, dtype=columns.dtype, device=columns.device)
    nh, nw = rows[-1:] + 1, cols[-1:] + 1
    offset = torch.where((nh == n_in) & (nw == n_in), 0.0, offset)
    step = torch.cat([(n_in / (nh + offset)).expand(h), (n_in / (nw + offset)).expand(w)])
    src = (torch.cat([rows, cols]) + 0.5) * step - 0.5
    d = (src[:, None] - columns).abs()
    a = -0.75
    near = ((a + 2) * d - (a + 3)) * d * d + 1  # |d| <= 1
    far = d.clamp(max=2.0)
    far = ((a * far - 5 * a) * far + 8 * a) * far - 4 * a  # 1 < |d| < 2, and 0 at |d| >= 2
    matrix = torch.where(d <= 1, near, far) @ fold
    return matrix[:h], matrix[h:]


def _view_plane_uv(h, w, levels: int, like: torch.Tensor, aspect: torch.Tensor | None = None) -> list[torch.Tensor]:
    """[B, 2, h * 2**l, w * 2**l] for l < levels: the official ``normalized_view_plane_uv`` of each grid (pixel
    centres; ``u`` spans +-aspect / sqrt(1 + aspect**2), ``v`` +-1 / sqrt(1 + aspect**2), each times
    (n - 1) / n) for ``aspect`` [B] = the original image's width / height (B = 1 and the grid's own aspect
    when None). The finest grid is computed, coarser ones are its 2x2 means (exact: the coordinates are
    linear in the index)."""
    scale = 2 ** (levels - 1)
    ys = torch.arange(h * scale, dtype=like.dtype, device=like.device)
    xs = torch.arange(w * scale, dtype=like.dtype, device=like.device)
    ht, wt = ys[-1:] + 1, xs[-1:] + 1
    if aspect is None:
        aspect = wt / ht
    aspect = aspect.to(like.dtype).reshape(-1, 1, 1)
    norm = torch.sqrt(1 + aspect * aspect)
    u = (aspect / norm) * ((2 * xs + 1 - wt) / wt)[None, None, :]
    v = (1 / norm) * ((2 * ys + 1 - ht) / ht)[None, :, None]
    shape = (aspect.shape[0], h * scale, w * scale)
    out = [torch.stack([u.expand(shape), v.expand(shape)], dim=1)]
    for _ in range(levels - 1):
        out.append(F.avg_pool2d(out[-1], 2))
    return out[::-1]


class _Encoder(nn.Module):
    """DINOv2 with intermediate-layer features (official ``DINOv2Encoder`` minus the internal resize)."""

    def __init__(self, config: MoGe2Config) -> None:
        super().__init__()
        from transformers import Dinov2Config, Dinov2Model

        self.config = config
        self.register_buffer("image_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))
        columns, fold = _bicubic_fold(config.pos_grid)  # constants, not checkpoint entries
        self.register_buffer("pos_columns", columns, persistent=False)
        self.register_buffer("pos_fold", fold, persistent=False)
        hf = Dinov2Config(hidden_size=config.embed_dim, num_hidden_layers=config.depth,
                          num_attention_heads=config.num_heads, mlp_ratio=config.mlp_ratio,
                          patch_size=config.patch_size, image_size=config.pos_grid * config.patch_size,
                          layer_norm_eps=config.layer_norm_eps, hidden_act="gelu", qkv_bias=True,
                          layerscale_value=1.0, use_swiglu_ffn=False, use_mask_token=True,
                          hidden_dropout_prob=0.0, attention_probs_dropout_prob=0.0, drop_path_rate=0.0)
        self.backbone = Dinov2Model(hf)
        self.output_projections = nn.ModuleList(nn.Conv2d(config.embed_dim, config.dim_proj, 1)
                                                for _ in config.intermediate_layers)

    def position_embedding(self, h, w, like: torch.Tensor) -> torch.Tensor:
        """[1, 1 + h*w, D]: class position + bicubically resampled patch positions (DINOv2, offset 0.1).
        At the pretraining grid (h = w = pos_grid) the stored embedding is used as is, as official (with
        offset 0 the resampling matrices are exactly the identity there)."""
        pos = self.backbone.embeddings.position_embeddings
        m, dim = self.config.pos_grid, pos.shape[-1]
        mh, mw = _bicubic_matrices(h, w, m, self.config.pos_interp_offset, self.pos_columns, self.pos_fold)
        grid = pos[0, 1:].reshape(m, m * dim)
        patch = torch.matmul(mw, torch.matmul(mh, grid).reshape(h, m, dim))  # [h, w, D]
        out = torch.cat([pos[:, :1], patch.reshape(1, h * w, dim)], dim=1)
        return out if out.dtype == like.dtype else out.to(like.dtype)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        batch, _, height, width = image.shape
        p = self.config.patch_size
        h, w = height // p, width // p
        emb = self.backbone.embeddings
        x = (image - self.image_mean) / self.image_std
        tokens = emb.patch_embeddings.projection(x).flatten(2).transpose(1, 2)
        x = torch.cat([emb.cls_token.expand(batch, -1, -1), tokens], dim=1)
        x = x + self.position_embedding(h, w, x)
        taken = []
        wanted = set(self.config.intermediate_layers)
        for i, layer in enumerate(self.backbone.encoder.layer[: self.config.intermediate_layers[-1] + 1]):
            x = layer(x)
            if i in wanted:
                taken.append(self.backbone.layernorm(x))
        features = None
        for proj, t in zip(self.output_projections, taken):
            f = proj(t[:, 1:].transpose(1, 2).reshape(batch, -1, h, w))
            features = f if features is None else features + f
        return features, taken[-1][:, 0]

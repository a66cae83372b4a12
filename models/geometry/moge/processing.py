"""MoGe-2-architecture monocular geometry network (torch), checkpoint I/O, pre/postprocessing, ONNX export.

The network follows the published MoGe-2 model (microsoft/MoGe, ``moge/model/v2.py``; preset
``MoGe2Config.vitl_normal()`` = ``Ruicheng/moge-2-vitl-normal``):

- a DINOv2 ViT encoder (transformers' ``Dinov2Model`` modules). The patch tokens of a few intermediate
  blocks are layer-normed, projected by 1x1 convolutions and summed into one feature map at the token grid
  (H/14, W/14); the layer-normed class token of the last of those blocks feeds the metric scale head;
- a convolutional neck over a 5-level pyramid (token grid x1, x2, x4, x8, x16): level 0 is the encoder
  feature map plus 2 UV channels, levels 1-4 are UV channels only (the normalised view-plane coordinates);
- heads sharing the neck's pyramid: points (3), normal (3, optional) and mask (1), each read at the finest
  level and bilinearly resized to the input size, and an MLP on the class token for the metric scale.

Output remaps (as official): points use ``remap_output`` ("exp" for MoGe-2: ``z = exp(z')``, ``xy = xy' z``),
normals are L2-normalised, the mask is a probability (``sigmoid``), ``metric_scale = exp(mlp(cls))``.

**The input resize is outside the graph.** The official ``forward(image, num_tokens)`` resizes the input
(bilinear, antialiased) to a token grid chosen from ``num_tokens`` inside the network. Here the caller does
it: ``preprocess_image`` picks the grid exactly like the official code (``token_grid``) and resizes; the graph
takes the already-resized image (H, W multiples of 14, any size, float RGB in [0, 1]) and the ORIGINAL
image's aspect ratio (width / height), from which the UV channels are built as official
(``normalized_view_plane_uv(..., aspect_ratio)``: the token grid's own aspect differs by its rounding). The
ImageNet mean/std normalisation stays inside the graph, as in the official encoder (buffers
``encoder.image_mean/std``).

**The head maps are resized once, outside the graph.** The graph returns the heads' raw maps at their own
resolution (``2**(levels-1)`` x the token grid) and the metric scale; ``head_maps_to_size`` resizes them
(bilinear, no antialias) straight to the input resolution and only then remaps them (points ``exp``, normal
L2, mask ``sigmoid``), in the official order; ``postprocess`` then does what the official ``infer()`` does
after the network (focal and z-shift recovery, metric scale, mask). ``infer_torch`` and ``OnnxMonoDepth``
run this same pipeline. The positional-embedding interpolation reproduces the official (non-ONNX-mode)
bicubic resampling with DINOv2's 0.1 offset exactly, as a traceable separable matrix product.

Checkpoints use the official key layout (fused ``attn.qkv``, ``ls1.gamma``, ``pos_embed`` ...);
``load_moge2_weights`` / ``moge2_state_dict_official`` map it to and from the modules here. The official
layout of the full-size model is committed in ``keys/moge2_vitl_normal.txt``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from navcrafter.models.runtime.onnxio import config_from_dict, config_to_dict

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
KEYS_DIR = Path(__file__).parents[1] / "keys"
OFFICIAL_KEYS_VITL_NORMAL = KEYS_DIR / "moge2_vitl_normal.txt"
# checkpoint buffers that may be absent from a checkpoint (their values are fixed constants)
_OPTIONAL_KEYS = ("encoder.image_mean", "encoder.image_std")
# official DINOv2 hub backbones: name -> (embed_dim, depth, num_heads)
_BACKBONES = {"dinov2_vits14": (384, 12, 6), "dinov2_vitb14": (768, 12, 12), "dinov2_vitl14": (1024, 24, 16)}


class MoGeWeightsError(ValueError):
    """A checkpoint does not match the MoGe-2 model it is loaded into."""


# ----------------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MoGe2Config:
    """Sizes of a MoGe-2 network. Defaults are the published ``moge-2-vitl-normal`` model."""

    # DINOv2 encoder (official ``encoder``: backbone dinov2_vitl14, intermediate_layers, dim_out)
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: int = 4
    patch_size: int = 14
    pos_grid: int = 37  # pretraining grid: 518 / 14; pos_embed has pos_grid**2 + 1 rows
    pos_interp_offset: float = 0.1  # DINOv2's interpolate_offset (official torch path)
    layer_norm_eps: float = 1e-6
    intermediate_layers: tuple[int, ...] = (5, 11, 17, 23)
    dim_proj: int = 1024  # official encoder.dim_out
    # neck (official ``neck``: dim_in [dim_proj + 2, 2, 2, 2, 2], dim_out None)
    neck_dims: tuple[int, ...] = (1024, 256, 128, 64, 32)
    neck_res_blocks: tuple[int, ...] = (0, 2, 2, 2, 0)
    # heads (official points/normal/mask_head: dim_in = neck_dims, dim_out [None, ..., C])
    head_dims: tuple[int, ...] = (1024, 256, 128, 64, 32)
    head_res_blocks: tuple[int, ...] = (0, 1, 1, 1, 0)
    resamplers: tuple[str, ...] = ("conv_transpose", "conv_transpose", "conv_transpose", "bilinear")
    res_block_in_norm: str = "none"
    res_block_hidden_norm: str = "none"
    res_block_hidden_mult: int = 1
    activation: str = "relu"
    normal_head: bool = True
    scale_head_dims: tuple[int, ...] = (1024, 1024, 1024, 1)  # () = no metric scale head
    remap_output: str = "exp"
    num_tokens_range: tuple[int, int] = (1200, 3600)

    def __post_init__(self) -> None:
        levels = len(self.neck_dims)
        problems = []
        if not (len(self.neck_res_blocks) == len(self.head_dims) == len(self.head_res_blocks) == levels):
            problems.append("neck_dims, neck_res_blocks, head_dims and head_res_blocks need one entry per level")
        if len(self.resamplers) != levels - 1:
            problems.append(f"resamplers needs {levels - 1} entries (one between each pair of levels)")
        if any(r not in _RESAMPLERS for r in self.resamplers):
            problems.append(f"resamplers must be among {sorted(_RESAMPLERS)}")
        if list(self.intermediate_layers) != sorted(set(self.intermediate_layers)) or not self.intermediate_layers \
                or self.intermediate_layers[0] < 0 or self.intermediate_layers[-1] >= self.depth:
            problems.append(f"intermediate_layers must be increasing block indices in [0, {self.depth})")
        if self.embed_dim % self.num_heads:
            problems.append("embed_dim must be divisible by num_heads")
        if self.scale_head_dims and (self.scale_head_dims[0] != self.embed_dim or self.scale_head_dims[-1] != 1
                                     or len(self.scale_head_dims) < 2):
            problems.append("scale_head_dims must run from embed_dim to 1")
        if self.remap_output not in ("linear", "sinh", "exp", "sinh_exp"):
            problems.append("remap_output must be linear, sinh, exp or sinh_exp")
        for norm in (self.res_block_in_norm, self.res_block_hidden_norm):
            if norm not in ("none", "layer_norm", "group_norm", "instance_norm"):
                problems.append(f"unknown norm {norm!r}")
        if self.activation not in _ACTIVATIONS:
            problems.append(f"activation must be among {sorted(_ACTIVATIONS)}")
        if problems:
            raise ValueError("invalid MoGe2Config: " + "; ".join(problems))

    @classmethod
    def vitl_normal(cls) -> MoGe2Config:
        """``Ruicheng/moge-2-vitl-normal`` (the official ``configs/train/v2.json`` model section)."""
        return cls()

    @classmethod
    def tiny(cls) -> MoGe2Config:
        """A few-kB random model for tests (same structure, tiny sizes)."""
        return cls(embed_dim=32, depth=2, num_heads=2, pos_grid=4, intermediate_layers=(0, 1), dim_proj=32,
                   neck_dims=(32, 16, 16, 8, 8), neck_res_blocks=(0, 1, 0, 0, 0),
                   head_dims=(32, 16, 16, 8, 8), head_res_blocks=(0, 1, 0, 0, 0),
                   scale_head_dims=(32, 16, 1), num_tokens_range=(12, 36))

    def to_dict(self) -> dict[str, Any]:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MoGe2Config:
        return config_from_dict(cls, data)

    def to_official(self) -> dict[str, Any]:
        """The official ``model_config`` dict (``MoGeModel(**model_config)``) of this network."""
        backbone = next((name for name, dims in _BACKBONES.items()
                         if dims == (self.embed_dim, self.depth, self.num_heads)), "custom")
        levels = len(self.neck_dims)

        def stack(dim_in, dims, blocks, dim_out):
            return {"dim_in": list(dim_in), "dim_out": dim_out, "dim_res_blocks": list(dims),
                    "num_res_blocks": list(blocks), "res_block_in_norm": self.res_block_in_norm,
                    "res_block_hidden_norm": self.res_block_hidden_norm, "resamplers": list(self.resamplers),
                    "dim_times_res_block_hidden": self.res_block_hidden_mult, "activation": self.activation}

        encoder = {"backbone": backbone, "intermediate_layers": list(self.intermediate_layers),
                   "dim_out": self.dim_proj}
        if backbone == "custom":  # not an official backbone (test sizes): spell the ViT out
            encoder.update(embed_dim=self.embed_dim, depth=self.depth, num_heads=self.num_heads,
                           pos_grid=self.pos_grid)
        out: dict[str, Any] = {
            "encoder": encoder,
            "neck": stack([self.dim_proj + 2] + [2] * (levels - 1), self.neck_dims, self.neck_res_blocks, None),
        }
        for head, channels in (("points_head", 3), ("normal_head", 3), ("mask_head", 1)):
            if head != "normal_head" or self.normal_head:
                out[head] = stack(self.neck_dims, self.head_dims, self.head_res_blocks,
                                  [None] * (levels - 1) + [channels])
        if self.scale_head_dims:
            out["scale_head"] = {"dims": list(self.scale_head_dims)}
        out["remap_output"] = self.remap_output
        out["num_tokens_range"] = list(self.num_tokens_range)
        return out

    @classmethod
    def from_official(cls, model_config: dict[str, Any]) -> MoGe2Config:
        """The config of an official ``model_config`` (raises for structures this module does not build)."""
        mc = dict(model_config)
        enc = mc["encoder"]
        pos_grid = 37  # every official DINOv2 hub backbone is pretrained at 518 x 518
        if enc.get("backbone") == "custom":
            embed_dim, depth, heads, pos_grid = enc["embed_dim"], enc["depth"], enc["num_heads"], enc["pos_grid"]
        elif enc.get("backbone") in _BACKBONES:
            embed_dim, depth, heads = _BACKBONES[enc["backbone"]]
        else:
            raise ValueError(f"unsupported MoGe backbone {enc.get('backbone')!r} (supported: {sorted(_BACKBONES)})")
        layers = enc["intermediate_layers"]
        layers = list(range(depth - layers, depth)) if isinstance(layers, int) else list(layers)
        neck = mc["neck"]
        levels = len(neck["dim_res_blocks"])

        def as_list(value, n):
            return list(value) if isinstance(value, (list, tuple)) else [value] * n

        head_names = ["points_head", "mask_head"] + (["normal_head"] if mc.get("normal_head") else [])
        first = mc[head_names[0]]
        problems = []
        if as_list(neck["dim_in"], levels) != [enc["dim_out"] + 2] + [2] * (levels - 1):
            problems.append("neck.dim_in is not [dim_out + 2, 2, ...]")
        if neck.get("dim_out") is not None and as_list(neck["dim_out"], levels) != [None] * levels:
            problems.append("neck.dim_out must be None")
        for name in head_names:
            head = mc[name]
            for key in ("dim_res_blocks", "num_res_blocks", "resamplers"):
                if as_list(head[key], levels) != as_list(first[key], levels):
                    problems.append(f"{name}.{key} differs from {head_names[0]}")
            if as_list(head["dim_in"], levels) != list(neck["dim_res_blocks"]):
                problems.append(f"{name}.dim_in is not the neck's dim_res_blocks")
            want = 3 if name != "mask_head" else 1
            if as_list(head["dim_out"], levels) != [None] * (levels - 1) + [want]:
                problems.append(f"{name}.dim_out is not [None, ..., {want}]")
        for key, default in (("res_block_in_norm", "layer_norm"), ("res_block_hidden_norm", "group_norm"),
                             ("dim_times_res_block_hidden", 1), ("activation", "relu")):
            if any(mc[n].get(key, default) != neck.get(key, default) for n in head_names):
                problems.append(f"heads and neck differ in {key}")
        if as_list(neck["resamplers"], levels - 1) != as_list(first["resamplers"], levels - 1):
            problems.append("heads and neck differ in resamplers")
        if problems:
            raise ValueError("unsupported MoGe-2 model_config: " + "; ".join(problems))
        return cls(
            embed_dim=embed_dim, depth=depth, num_heads=heads, pos_grid=pos_grid, intermediate_layers=tuple(layers),
            dim_proj=enc["dim_out"], neck_dims=tuple(neck["dim_res_blocks"]),
            neck_res_blocks=tuple(as_list(neck.get("num_res_blocks", 1), levels)),
            head_dims=tuple(first["dim_res_blocks"]),
            head_res_blocks=tuple(as_list(first.get("num_res_blocks", 1), levels)),
            resamplers=tuple(as_list(neck["resamplers"], levels - 1)),
            res_block_in_norm=neck.get("res_block_in_norm", "layer_norm"),
            res_block_hidden_norm=neck.get("res_block_hidden_norm", "group_norm"),
            res_block_hidden_mult=neck.get("dim_times_res_block_hidden", 1),
            activation=neck.get("activation", "relu"), normal_head=bool(mc.get("normal_head")),
            scale_head_dims=tuple(mc["scale_head"]["dims"]) if mc.get("scale_head") else (),
            remap_output=mc.get("remap_output", "linear"),
            num_tokens_range=tuple(mc.get("num_tokens_range", (1200, 3600))),
        )


# ----------------------------------------------------------------------------------------------------
# Modules (names and nesting follow the official checkpoint outside the DINOv2 backbone)
# ----------------------------------------------------------------------------------------------------

_ACTIVATIONS = {"relu": nn.ReLU, "leaky_relu": lambda: nn.LeakyReLU(0.2), "silu": nn.SiLU, "elu": nn.ELU}
_RESAMPLERS = {"conv_transpose", "bilinear", "nearest"}


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


class MoGe2(nn.Module):
    """MoGe-2 network. ``forward(image [B,3,H,W] in [0,1], H, W multiples of 14, already resized by the
    caller; aspect_ratio [B] = the ORIGINAL image's width / height, default the resized image's)`` ->
    ``(points_raw [B,h,w,3], normal_raw [B,h,w,3], mask_logits [B,h,w], metric_scale [B])`` with the head
    maps raw (before the remaps) at the heads' resolution (h, w = 2**(levels-1) x the token grid);
    ``normal_raw`` / ``metric_scale`` are left out when the config has no such head (see ``output_names``).
    ``head_maps_to_size`` resizes them to the input size and remaps them, as the official ``forward``."""

    def __init__(self, config: MoGe2Config) -> None:
        super().__init__()
        self.config = config
        levels = len(config.neck_dims)
        self.encoder = _Encoder(config)
        self.neck = _ConvStack([config.dim_proj + 2] + [2] * (levels - 1), config.neck_dims,
                               config.neck_res_blocks, [None] * levels, config)

        def head(channels):
            return _ConvStack(list(config.neck_dims), config.head_dims, config.head_res_blocks,
                              [None] * (levels - 1) + [channels], config)

        self.points_head = head(3)
        self.mask_head = head(1)
        if config.normal_head:
            self.normal_head = head(3)
        if config.scale_head_dims:
            self.scale_head = _MLP(config.scale_head_dims)

    @property
    def output_names(self) -> list[str]:
        return (["points_raw"] + (["normal_raw"] if self.config.normal_head else []) + ["mask_logits"]
                + (["metric_scale"] if self.config.scale_head_dims else []))

    def forward(self, image: torch.Tensor, aspect_ratio: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        batch = image.shape[0]
        features, cls_token = self.encoder(image)
        h, w = features.shape[-2:]
        if aspect_ratio is not None:
            aspect_ratio = aspect_ratio.reshape(-1).expand(batch)
        pyramid = _view_plane_uv(h, w, len(self.config.neck_dims), image, aspect_ratio)  # batch 1 broadcasts
        pyramid[0] = torch.cat([features, pyramid[0].expand(batch, -1, -1, -1)], dim=1)
        pyramid = self.neck(pyramid)
        heads = [self.points_head, self.normal_head, self.mask_head] if self.config.normal_head \
            else [self.points_head, self.mask_head]
        maps = torch.cat([head(pyramid)[-1] for head in heads], dim=1).permute(0, 2, 3, 1)
        parts = maps.split([3, 3, 1] if self.config.normal_head else [3, 1], dim=-1)
        outputs = list(parts[:-1]) + [parts[-1].squeeze(-1)]
        if self.config.scale_head_dims:
            outputs.append(self.scale_head(cls_token).squeeze(1).exp())
        return tuple(outputs)


# ----------------------------------------------------------------------------------------------------
# Official checkpoint layout
# ----------------------------------------------------------------------------------------------------

_BACKBONE = "encoder.backbone."
_BLOCK_MAP = (  # official block suffix -> ours (under encoder.layer.{i}.)
    ("norm1.weight", "norm1.weight"), ("norm1.bias", "norm1.bias"),
    ("attn.qkv.weight", None), ("attn.qkv.bias", None),
    ("attn.proj.weight", "attention.o_proj.weight"), ("attn.proj.bias", "attention.o_proj.bias"),
    ("ls1.gamma", "layer_scale1.lambda1"),
    ("norm2.weight", "norm2.weight"), ("norm2.bias", "norm2.bias"),
    ("mlp.fc1.weight", "mlp.fc1.weight"), ("mlp.fc1.bias", "mlp.fc1.bias"),
    ("mlp.fc2.weight", "mlp.fc2.weight"), ("mlp.fc2.bias", "mlp.fc2.bias"),
    ("ls2.gamma", "layer_scale2.lambda1"),
)
_TOP_MAP = (  # official backbone key -> ours (under encoder.backbone.)
    ("cls_token", "embeddings.cls_token"), ("pos_embed", "embeddings.position_embeddings"),
    ("mask_token", "embeddings.mask_token"),
    ("patch_embed.proj.weight", "embeddings.patch_embeddings.projection.weight"),
    ("patch_embed.proj.bias", "embeddings.patch_embeddings.projection.bias"),
)


def _backbone_plan(depth: int) -> list[tuple[str, str | tuple[str, str, str]]]:
    """(official key, our key or the three q/k/v keys it fuses), in the official state_dict order."""
    plan: list[tuple[str, Any]] = [(_BACKBONE + a, _BACKBONE + b) for a, b in _TOP_MAP]
    for i in range(depth):
        ours = f"{_BACKBONE}encoder.layer.{i}."
        for a, b in _BLOCK_MAP:
            if b is None:
                kind = a.rsplit(".", 1)[1]
                b = tuple(f"{ours}attention.{p}_proj.{kind}" for p in "qkv")
            else:
                b = ours + b
            plan.append((f"{_BACKBONE}blocks.{i}.{a}", b))
    plan += [(_BACKBONE + "norm.weight", _BACKBONE + "layernorm.weight"),
             (_BACKBONE + "norm.bias", _BACKBONE + "layernorm.bias")]
    return plan


def moge2_state_dict_official(model: MoGe2) -> dict[str, torch.Tensor]:
    """The model's weights under the official checkpoint names and shapes (fused ``qkv`` etc.)."""
    ours = {k: v.detach() for k, v in model.state_dict().items()}
    out: dict[str, torch.Tensor] = {}
    backbone_done = False
    for key, value in ours.items():
        if key.startswith(_BACKBONE):
            if not backbone_done:
                for official, mine in _backbone_plan(model.config.depth):
                    out[official] = torch.cat([ours[k] for k in mine]) if isinstance(mine, tuple) else ours[mine]
                backbone_done = True
            continue
        out[key] = value
    return out


def _official_to_ours(model: MoGe2, official: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    ours: dict[str, torch.Tensor] = {}
    plan = dict(_backbone_plan(model.config.depth))
    for key, value in official.items():
        mine = plan.get(key)
        if mine is None:
            ours[key] = value
        elif isinstance(mine, tuple):
            for name, part in zip(mine, value.chunk(3, dim=0)):
                ours[name] = part
        else:
            ours[mine] = value
    return ours


def official_key_shapes(model: MoGe2) -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in moge2_state_dict_official(model).items()}


def read_official_key_list(path: Path = OFFICIAL_KEYS_VITL_NORMAL) -> dict[str, tuple[int, ...]]:
    """A committed ``name shape`` list (shape as comma-separated ints) in file order."""
    out = {}
    for line in Path(path).read_text().splitlines():
        if line.strip():
            name, shape = line.split()
            out[name] = tuple(int(s) for s in shape.split(","))
    return out


def _read_checkpoint(path: Path) -> tuple[dict[str, torch.Tensor], dict | None]:
    path = Path(path)
    if not path.is_file():
        raise MoGeWeightsError(f"MoGe-2 checkpoint {path} does not exist")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path)), None
    try:
        data = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # weights_only refuses pickled code objects: never fall back to full pickle
        raise MoGeWeightsError(f"{path}: not a tensor-only torch checkpoint ({exc})") from exc
    if isinstance(data, dict) and isinstance(data.get("model"), dict):
        config = data.get("model_config")
        return data["model"], config if isinstance(config, dict) else None
    if isinstance(data, dict) and all(isinstance(v, torch.Tensor) for v in data.values()):
        return data, None
    raise MoGeWeightsError(f"{path}: expected a state dict or a dict with 'model' (and 'model_config')")


def _listing(names, limit: int = 12) -> str:
    names = list(names)
    more = f" ... (+{len(names) - limit} more)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def load_moge2_weights(model: MoGe2, path: Path) -> MoGe2:
    """Load an official-layout checkpoint (``.safetensors``, or ``.pt``/``.pth`` read with
    ``torch.load(weights_only=True)``: either the official ``{"model_config", "model"}`` dict or a bare
    state dict) into ``model``. Every name and shape is checked against the official layout of
    ``model.config`` first; ``encoder.image_mean/std`` may be absent (they are constants). A ``model_config``
    in the file must describe the same network. Raises ``MoGeWeightsError`` naming the file and the
    missing, unexpected and wrong-shape keys."""
    path = Path(path)
    state, file_config = _read_checkpoint(path)
    if file_config is not None:
        try:
            theirs = MoGe2Config.from_official(file_config)
        except (KeyError, TypeError, ValueError) as exc:
            raise MoGeWeightsError(f"{path}: model_config is not a supported MoGe-2 network: {exc}") from exc
        mine = model.config
        # not part of model_config (fixed by the official code) or not about the weights
        fields = ("pos_interp_offset", "layer_norm_eps", "patch_size", "mlp_ratio", "num_tokens_range")
        theirs = dataclasses.replace(theirs, **{f: getattr(mine, f) for f in fields})
        if theirs != mine:
            diff = [f.name for f in dataclasses.fields(mine) if getattr(theirs, f.name) != getattr(mine, f.name)]
            raise MoGeWeightsError(f"{path}: its model_config differs from the model's config in {diff}")
    expected = official_key_shapes(model)
    missing = [k for k in expected if k not in state and k not in _OPTIONAL_KEYS]
    unexpected = [k for k in state if k not in expected]
    wrong = [f"{k} {tuple(state[k].shape)} (expected {expected[k]})"
             for k in expected if k in state and tuple(state[k].shape) != expected[k]]
    if missing or unexpected or wrong:
        parts = [f"{path} does not match the MoGe-2 official layout of this config"]
        if missing:
            parts.append(f"missing {len(missing)}: {_listing(missing)}")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)}: {_listing(unexpected)}")
        if wrong:
            parts.append(f"wrong shape {len(wrong)}: {_listing(wrong)}")
        raise MoGeWeightsError("; ".join(parts))
    current = moge2_state_dict_official(model)
    full = {k: state.get(k, current[k]).to(dtype=current[k].dtype) for k in expected}
    model.load_state_dict(_official_to_ours(model, full), strict=True)
    return model


def save_moge2_weights(model: MoGe2, path: Path) -> Path:
    """Write the model's weights in the official layout as ``.safetensors``."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in moge2_state_dict_official(model).items()}, str(path))
    return path


def load_moge2(path: Path) -> MoGe2:
    """Build the network described by an official ``.pt`` checkpoint's ``model_config`` and load it."""
    state, file_config = _read_checkpoint(Path(path))
    if file_config is None:
        raise MoGeWeightsError(f"{path}: no model_config; build MoGe2(config) and use load_moge2_weights")
    return load_moge2_weights(MoGe2(MoGe2Config.from_official(file_config)), path).eval()


# ----------------------------------------------------------------------------------------------------
# Preprocessing and postprocessing (numpy; shared by the torch and the onnxruntime paths)
# ----------------------------------------------------------------------------------------------------


def num_tokens_for_level(level: int, num_tokens_range: tuple[int, int] = (1200, 3600)) -> int:
    """Official ``resolution_level`` (0..9) -> number of tokens; level 9 (the official default) = the maximum."""
    lo, hi = num_tokens_range
    return int(lo + (level / 9) * (hi - lo))


def token_grid(height: int, width: int, num_tokens: int) -> tuple[int, int]:
    """Token rows and columns for ``num_tokens`` at the image's aspect ratio (official rounding)."""
    aspect = width / height
    return max(1, round((num_tokens / aspect) ** 0.5)), max(1, round((num_tokens * aspect) ** 0.5))


def _resize_antialias(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """[h, w, C] float -> [height, width, C] float32: bilinear with antialiasing when shrinking (PIL's
    triangle filter, the same as torch ``interpolate(bilinear, antialias=True)``)."""
    from PIL import Image

    channels = [np.asarray(Image.fromarray(np.ascontiguousarray(array[..., c], dtype=np.float32), mode="F")
                           .resize((width, height), Image.BILINEAR)) for c in range(array.shape[-1])]
    return np.stack(channels, axis=-1).astype(np.float32)


def preprocess_image(image: np.ndarray, num_tokens: int, patch_size: int = 14) -> np.ndarray:
    """``[H, W, 3]`` uint8 (or float in [0, 1]) -> ``[1, 3, 14*rows, 14*cols]`` float32 in [0, 1], resized
    (bilinear, antialiased, as the official encoder) to the token grid of ``token_grid``. The ImageNet
    mean/std normalisation is part of the network."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"expected an [H, W, 3] image, got shape {image.shape}")
    x = image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else image.astype(np.float32)
    rows, cols = token_grid(image.shape[0], image.shape[1], num_tokens)
    x = _resize_antialias(x, rows * patch_size, cols * patch_size)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


def _view_plane_uv_np(height: int, width: int) -> np.ndarray:
    diagonal = math.hypot(height, width)
    u = (2 * np.arange(width) + 1 - width) / diagonal
    v = (2 * np.arange(height) + 1 - height) / diagonal
    return np.stack(np.meshgrid(u, v, indexing="xy"), axis=-1).astype(np.float32)


def _nearest_index(n_in: int, n_out: int) -> np.ndarray:
    """torch ``interpolate(mode="nearest")`` source indices (float32 arithmetic, as torch)."""
    return np.minimum(np.floor(np.arange(n_out, dtype=np.float32) * np.float32(n_in / n_out)).astype(np.int64),
                      n_in - 1)


def recover_focal_shift(points: np.ndarray, valid: np.ndarray, focal: float | None = None,
                        size: tuple[int, int] = (64, 64)) -> tuple[float, float]:
    """The official focal/z-shift recovery: on a nearest-downsampled (64x64) map, least-squares
    ``min |focal * xy / (z + shift) - uv|`` over the valid pixels (``focal`` relative to half the image
    diagonal). Returns ``(focal, shift)``; ``(1, 0)`` when fewer than 2 pixels are valid."""
    from scipy.optimize import least_squares

    height, width = points.shape[:2]
    ri, ci = _nearest_index(height, size[0]), _nearest_index(width, size[1])
    uv = _view_plane_uv_np(height, width)[ri][:, ci]
    pts = points[ri][:, ci]
    keep = valid[ri][:, ci]
    # float32 maps and float64 shift, as official (``solve_optimal_focal_shift``): with ``ftol=1e-3`` the
    # solver's stopping point depends on the arithmetic, so it is kept the same
    uv, xy, z = uv[keep].astype(np.float32), pts[keep][:, :2].astype(np.float32), pts[keep][:, 2].astype(np.float32)
    if len(z) < 2:
        return 1.0, 0.0

    def focal_of(shift):
        proj = xy / (z + shift)[:, None]
        return (proj * uv).sum() / np.square(proj).sum()

    def residual(shift):
        proj = xy / (z + shift)[:, None]
        f = focal if focal is not None else (proj * uv).sum() / np.square(proj).sum()
        return (f * proj - uv).ravel()

    shift = np.float32(least_squares(residual, x0=0, ftol=1e-3, method="lm").x.squeeze())
    return (float(focal_of(shift)) if focal is None else float(focal)), float(shift)


def remap_points(points: torch.Tensor, kind: str) -> torch.Tensor:
    """The official ``_remap_points`` of the raw points map ``[..., 3]`` (``exp``: ``z = exp(z')``, ``xy = xy' z``)."""
    if kind == "sinh":
        return torch.sinh(points)
    if kind == "exp":
        xy, z = points.split([2, 1], dim=-1)
        z = torch.exp(z)
        return torch.cat([xy * z, z], dim=-1)
    if kind == "sinh_exp":
        xy, z = points.split([2, 1], dim=-1)
        return torch.cat([torch.sinh(xy), torch.exp(z)], dim=-1)
    if kind != "linear":
        raise ValueError(f"unknown remap_output {kind!r}")
    return points


def head_maps_to_size(points_raw: np.ndarray, mask_logits: np.ndarray, normal_raw: np.ndarray | None, *,
                      size: tuple[int, int], remap_output: str = "exp"
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One image's raw head maps (``points_raw [h,w,3]``, ``mask_logits [h,w]``, ``normal_raw [h,w,3]``, at
    the heads' resolution) -> ``(points [H,W,3], mask [H,W] probability, normal [H,W,3] unit)`` at ``size``
    = (H, W), float32: resized once (torch bilinear, ``align_corners=False``, no antialias), then remapped,
    with the official ``forward``'s ops in its order."""
    parts = [np.asarray(points_raw, np.float32), np.asarray(mask_logits, np.float32)[..., None]]
    if normal_raw is not None:
        parts.append(np.asarray(normal_raw, np.float32))
    maps = torch.from_numpy(np.concatenate(parts, axis=-1)).permute(2, 0, 1)[None]
    with torch.no_grad():
        maps = F.interpolate(maps, size=tuple(size), mode="bilinear", align_corners=False, antialias=False)
        maps = maps[0].permute(1, 2, 0)
        points = remap_points(maps[..., :3], remap_output)
        mask = maps[..., 3].sigmoid()
        normal = F.normalize(maps[..., 4:], dim=-1) if normal_raw is not None else None
    return points.numpy(), mask.numpy(), None if normal is None else normal.numpy()


def outputs_to_result(outputs: dict[str, np.ndarray], size: tuple[int, int], config: MoGe2Config,
                      fov_x: float | None = None, index: int = 0) -> MoGe2Result:
    """Batch item ``index`` of the network's outputs (``MoGe2.output_names``) -> ``MoGe2Result`` at ``size``:
    ``head_maps_to_size`` then ``postprocess`` (the torch and onnxruntime paths share this)."""
    points, mask, normal = head_maps_to_size(
        outputs["points_raw"][index], outputs["mask_logits"][index],
        outputs["normal_raw"][index] if "normal_raw" in outputs else None, size=size,
        remap_output=config.remap_output)
    scale = float(outputs["metric_scale"][index]) if "metric_scale" in outputs else None
    return postprocess(points, mask, scale, normal, fov_x=fov_x)


def infer_torch(model: MoGe2, image: np.ndarray, num_tokens: int | None = None,
                fov_x: float | None = None) -> MoGe2Result:
    """The whole MoGe-2 pipeline in torch (float32) for one ``[H, W, 3]`` image (uint8, or float in [0, 1]),
    as the official ``infer(image, num_tokens, fov_x=fov_x, use_fp16=False)``: token-grid resize, network with
    the original aspect ratio, one resize of the head maps to ``H x W``, focal/shift recovery, metric scale."""
    image = np.asarray(image)
    num_tokens = int(num_tokens or num_tokens_for_level(9, model.config.num_tokens_range))
    x = preprocess_image(image, num_tokens, model.config.patch_size)
    aspect = torch.tensor([image.shape[1] / image.shape[0]], dtype=torch.float32)
    param = next(model.parameters())
    with torch.no_grad():
        out = model(torch.from_numpy(x).to(param.device, param.dtype), aspect.to(param.device))
    arrays = {k: v.float().cpu().numpy() for k, v in zip(model.output_names, out)}
    return outputs_to_result(arrays, image.shape[:2], model.config, fov_x=fov_x)


@dataclass
class MoGe2Result:
    """One image's geometry at the input resolution (the official ``infer()`` outputs, plus inverse depth)."""

    depth: np.ndarray  # [H, W] float32 metric z-depth (relative without a scale head); inf = invalid
    inv_depth: np.ndarray  # [H, W] float32 1 / depth; 0 = invalid
    valid: np.ndarray  # [H, W] bool: mask >= 0.5, finite, positive depth; ~valid = sky / no geometry
    points: np.ndarray  # [H, W, 3] float32 camera-space points (OpenCV; re-projected from depth); inf = invalid
    intrinsics: np.ndarray  # [3, 3] float32 normalised (fx, fy in units of width, height; centre 0.5, 0.5)
    normal: np.ndarray | None  # [H, W, 3] float32 unit normals (OpenCV camera frame); 0 = invalid
    metric_scale: float


def postprocess(points: np.ndarray, mask: np.ndarray, metric_scale: float | None = None,
                normal: np.ndarray | None = None, *, size: tuple[int, int] | None = None,
                fov_x: float | None = None) -> MoGe2Result:
    """Remapped maps of one image at the input resolution (``points [H,W,3]``, ``mask [H,W]`` probability,
    ``metric_scale``, ``normal [H,W,3]``; see ``head_maps_to_size``) -> ``MoGe2Result``. ``size``, when
    given, must be the maps' size (the maps are never resized here: the official pipeline resizes the raw
    head maps once, before the remaps).

    As official: ``valid = mask > 0.5``, focal and z-shift are recovered from
    the point map (or only the shift, when ``fov_x`` in degrees is known), ``depth = (z + shift) * scale``,
    pixels with ``depth <= 0`` are invalid. Non-finite values are invalid too. Invalid pixels get
    ``depth = inf``, ``inv_depth = 0``, ``points = inf``, ``normal = 0``.
    """
    height, width = mask.shape[:2]
    if size is not None and tuple(size) != (height, width):
        raise ValueError(f"postprocess: maps are {height}x{width} but size is {tuple(size)}; resize the raw head "
                         f"maps with head_maps_to_size first (one resize, then the remaps, as official)")
    if points.shape[:2] != (height, width) or (normal is not None and normal.shape[:2] != (height, width)):
        raise ValueError(f"postprocess: points {points.shape} / normal maps differ in size from mask {mask.shape}")
    points = points.astype(np.float32)
    valid = (mask > 0.5) & np.isfinite(points).all(axis=-1)
    aspect = width / height
    known = None
    if fov_x is not None:
        known = aspect / math.sqrt(1 + aspect**2) / math.tan(math.radians(fov_x) / 2)
    safe_points = np.where(valid[..., None], points, 0.0)
    focal, shift = recover_focal_shift(safe_points, valid, focal=known)
    fx = focal / 2 * math.sqrt(1 + aspect**2) / aspect
    fy = focal / 2 * math.sqrt(1 + aspect**2)
    intrinsics = np.array([[fx, 0, 0.5], [0, fy, 0.5], [0, 0, 1]], dtype=np.float32)
    scale = 1.0 if metric_scale is None else float(metric_scale)
    with np.errstate(invalid="ignore", over="ignore"):
        depth = (points[..., 2] + np.float32(shift)) * np.float32(scale)
    valid &= np.isfinite(depth) & (depth > 0) & np.isfinite(scale)
    depth = np.where(valid, depth, np.inf).astype(np.float32)
    with np.errstate(divide="ignore"):
        inv_depth = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0).astype(np.float32)
    u = ((np.arange(width) + 0.5) / width - 0.5) / fx
    v = ((np.arange(height) + 0.5) / height - 0.5) / fy
    rays = np.stack([*np.meshgrid(u, v, indexing="xy"), np.ones((height, width))], axis=-1)
    with np.errstate(invalid="ignore"):
        cam = np.where(valid[..., None], rays * np.where(valid, depth, 0.0)[..., None], np.inf).astype(np.float32)
    if normal is not None:
        norm = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = np.where(valid[..., None] & (norm > 0), normal / np.maximum(norm, 1e-12), 0.0).astype(np.float32)
    return MoGe2Result(depth=depth, inv_depth=inv_depth, valid=valid, points=cam, intrinsics=intrinsics,
                       normal=normal, metric_scale=scale)


# ----------------------------------------------------------------------------------------------------
# ONNX export
# ----------------------------------------------------------------------------------------------------


def export_monodepth(out_dir: Path, config: MoGe2Config, weights: Path | None = None, seed: int = 0) -> Path:
    """Export the network as graph ``monodepth`` (inputs ``image`` [B, 3, H, W] float in [0, 1], dynamic B and
    H, W = 14 x token rows/cols, and ``aspect_ratio`` [B] float, the original images' width / height; outputs
    ``points_raw``, ``normal_raw``, ``mask_logits`` (raw head maps at the heads' resolution) and
    ``metric_scale`` as ``MoGe2``; ``head_maps_to_size`` + ``postprocess`` finish them)
    plus the manifest (kind ``monodepth``, architecture ``moge-2``). Random weights from ``seed`` unless a
    checkpoint is given. Returns ``out_dir``."""
    from navcrafter.models.runtime import onnxio

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    model = MoGe2(config).eval()
    if weights is not None:
        load_moge2_weights(model, weights)
        weights_info = {"source": "checkpoint", "path": str(weights), "sha256": onnxio.sha256_file(Path(weights))}
    else:
        weights_info = {"source": "random", "seed": seed}
    p = config.patch_size
    example = (torch.rand(2, 3, 3 * p, 4 * p), torch.tensor([1.25, 1.4]))
    batch = torch.export.Dim("batch", min=1, max=64)
    rows = torch.export.Dim("token_rows", min=2, max=256)
    cols = torch.export.Dim("token_cols", min=2, max=256)
    info = onnxio.export_graph(model, example, out_dir / "monodepth.onnx", input_names=["image", "aspect_ratio"],
                               output_names=model.output_names,
                               dynamic_shapes=({0: batch, 2: p * rows, 3: p * cols}, {0: batch}))
    info.notes = ("image: RGB float in [0, 1], already resized to a token grid (H, W multiples of patch_size); "
                  "mean/std normalisation is inside. aspect_ratio: the original image's width / height. "
                  "points_raw / normal_raw / mask_logits: the heads' raw maps at 2**(levels-1) x the token grid, "
                  "to resize once to the input size and then remap (head_maps_to_size); metric_scale: [B]")
    io = {"input_range": [0.0, 1.0], "patch_size": p, "num_tokens_range": list(config.num_tokens_range),
          "default_num_tokens": num_tokens_for_level(9, config.num_tokens_range),
          "outputs": model.output_names, "head_maps": "raw, resize once to the input size, then remap",
          "remap_output": config.remap_output, "official_model_config": config.to_official()}
    onnxio.write_manifest(out_dir, kind="monodepth", architecture="moge-2", config=config.to_dict(),
                          weights=weights_info, graphs={"monodepth": info}, extra={"io": io})
    return out_dir

"""MoGe-2 configuration (``MoGe2Config``: the official presets, from and to the official ``model_config``), the
committed key list and the weights error."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

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


_ACTIVATIONS = {"relu": nn.ReLU, "leaky_relu": lambda: nn.LeakyReLU(0.2), "silu": nn.SiLU, "elu": nn.ELU}
_RESAMPLERS = {"conv_transpose", "bilinear", "nearest"}

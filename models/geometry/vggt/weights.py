"""The official VGGT checkpoint layout <-> ours (fused qkv, stacked DPT heads), the committed key list, the strict
loader and the official-layout writer; reading and checking files is ``models.checkpoints``'s."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import nn

from navcrafter.models import checkpoints
from navcrafter.models.geometry.vggt.config import IGNORED_PREFIXES, KEY_LIST_1B
from navcrafter.models.geometry.vggt.heads import DPT_HEADS
from navcrafter.models.runtime.onnxio import sha256_file

if TYPE_CHECKING:
    from navcrafter.models.geometry.vggt.model import VGGT


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
_ENC_BLOCK = [(ours, official) for official, ours in checkpoints.DINOV2_BLOCK_NAMES if ours is not None]


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
    return checkpoints.read_state_dict(path, VGGTWeightsError, "VGGT")[0]


def check_official_layout(sd: dict[str, torch.Tensor], model: VGGT, source: str = "checkpoint") -> list[str]:
    """Raise ``VGGTWeightsError`` unless ``sd`` has exactly the official keys and shapes for ``model``'s
    config (``track_head.*`` excepted). Returns the ignored keys."""
    ignored = [k for k in sd if k.startswith(IGNORED_PREFIXES)]
    present = {k: v for k, v in sd.items() if not k.startswith(IGNORED_PREFIXES)}
    checkpoints.check_layout(present, official_layout(model), VGGTWeightsError,
                             f"{source} does not match the official VGGT layout for this config "
                             f"(embed_dim={model.config.embed_dim}, depth={model.config.depth})")
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

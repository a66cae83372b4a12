"""The official MoGe-2 checkpoint layout <-> ours (fused ``attn.qkv``, ``ls1.gamma`` ...), the committed key list,
the strict loader and the writer; reading and checking files is ``models.checkpoints``'s."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from navcrafter.models import checkpoints
from navcrafter.models.geometry.moge.config import (
    _OPTIONAL_KEYS,
    OFFICIAL_KEYS_VITL_NORMAL,
    MoGe2Config,
    MoGeWeightsError,
)
from navcrafter.models.geometry.moge.model import MoGe2

_BACKBONE = "encoder.backbone."
_BLOCK_MAP = checkpoints.DINOV2_BLOCK_NAMES  # official block suffix -> ours (under encoder.layer.{i}.)
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
    """(state dict, the official ``model_config`` or None) of a ``.safetensors`` or tensor-only ``.pt`` file."""
    state, extra = checkpoints.read_state_dict(path, MoGeWeightsError, "MoGe-2")
    config = extra.get("model_config")
    return state, config if isinstance(config, dict) else None


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
    checkpoints.check_layout(state, expected, MoGeWeightsError,
                             f"{path} does not match the MoGe-2 official layout of this config",
                             optional=_OPTIONAL_KEYS)
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

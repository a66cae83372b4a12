"""Official checkpoint layout <-> ours (key mapping, the committed key list), the strict loader and writer of the
official transformer folder, and NavCrafter's camera control initialised from Fun-Camera weights."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from diffusers.models.transformers.transformer_wan import WanTransformer3DModel

from navcrafter.models import checkpoints
from navcrafter.models.synthesis.camcontrol import CameraControlledWan
from navcrafter.models.synthesis.funcamera.config import (
    KEY_LIST_1_3B,
    LATENT_CHANNELS,
    OFFICIAL_CONFIG,
    OFFICIAL_WEIGHTS,
    FunCameraConfig,
    FunCameraWeightsError,
)
from navcrafter.models.synthesis.funcamera.model import FunCameraWan

_TOP = {"patch_embedding": "base.patch_embedding",
        "text_embedding.0": "base.condition_embedder.text_embedder.linear_1",
        "text_embedding.2": "base.condition_embedder.text_embedder.linear_2",
        "time_embedding.0": "base.condition_embedder.time_embedder.linear_1",
        "time_embedding.2": "base.condition_embedder.time_embedder.linear_2",
        "time_projection.1": "base.condition_embedder.time_proj",
        "img_emb.proj.0": "base.condition_embedder.image_embedder.norm1",
        "img_emb.proj.1": "base.condition_embedder.image_embedder.ff.net.0.proj",
        "img_emb.proj.3": "base.condition_embedder.image_embedder.ff.net.2",
        "img_emb.proj.4": "base.condition_embedder.image_embedder.norm2",
        "head.head": "base.proj_out"}


# inside blocks.N. (the official norm3 is the affine cross-attention norm, diffusers' norm2)
_BLOCK = {"self_attn.q": "attn1.to_q", "self_attn.k": "attn1.to_k", "self_attn.v": "attn1.to_v",
          "self_attn.o": "attn1.to_out.0", "self_attn.norm_q": "attn1.norm_q", "self_attn.norm_k": "attn1.norm_k",
          "cross_attn.q": "attn2.to_q", "cross_attn.k": "attn2.to_k", "cross_attn.v": "attn2.to_v",
          "cross_attn.o": "attn2.to_out.0", "cross_attn.norm_q": "attn2.norm_q", "cross_attn.norm_k": "attn2.norm_k",
          "cross_attn.k_img": "attn2.add_k_proj", "cross_attn.v_img": "attn2.add_v_proj",
          "cross_attn.norm_k_img": "attn2.norm_added_k", "norm3": "norm2", "ffn.0": "ffn.net.0.proj",
          "ffn.2": "ffn.net.2"}
_TOP_INV = {v: k for k, v in _TOP.items()}
_BLOCK_INV = {v: k for k, v in _BLOCK.items()}
_BLOCK_RE = re.compile(r"^blocks\.(\d+)\.(.+)\.(weight|bias)$")
_OUR_BLOCK_RE = re.compile(r"^base\.blocks\.(\d+)\.(.+)\.(weight|bias)$")


def official_to_ours(key: str) -> str | None:
    """Our parameter name of an official key (None: not a key of this architecture)."""
    if key.startswith("control_adapter."):
        return key
    if key == "head.modulation":
        return "base.scale_shift_table"
    m = re.match(r"^blocks\.(\d+)\.modulation$", key)
    if m:
        return f"base.blocks.{m.group(1)}.scale_shift_table"
    m = _BLOCK_RE.match(key)
    if m:
        inner = _BLOCK.get(m.group(2))
        return None if inner is None else f"base.blocks.{m.group(1)}.{inner}.{m.group(3)}"
    stem, _, leaf = key.rpartition(".")
    if stem in _TOP and leaf in ("weight", "bias"):
        return f"{_TOP[stem]}.{leaf}"
    return None


def ours_to_official(key: str) -> str:
    if key.startswith("control_adapter."):
        return key
    if key == "base.scale_shift_table":
        return "head.modulation"
    m = re.match(r"^base\.blocks\.(\d+)\.scale_shift_table$", key)
    if m:
        return f"blocks.{m.group(1)}.modulation"
    m = _OUR_BLOCK_RE.match(key)
    if m and m.group(2) in _BLOCK_INV:
        return f"blocks.{m.group(1)}.{_BLOCK_INV[m.group(2)]}.{m.group(3)}"
    stem, _, leaf = key.rpartition(".")
    if stem in _TOP_INV:
        return f"{_TOP_INV[stem]}.{leaf}"
    raise KeyError(f"{key}: no official name (not a parameter of the Fun-Camera layout)")


def _official_order(name: str) -> tuple:
    """The official state_dict order: embeddings, blocks (modulation first, then self_attn, norm3, cross_attn,
    ffn), head, img_emb, control_adapter."""
    top = ["patch_embedding", "text_embedding", "time_embedding", "time_projection", "blocks", "head", "img_emb",
           "control_adapter"]
    parts = name.split(".")
    rank = top.index(parts[0])
    if parts[0] == "blocks":
        stem, leaf = ".".join(parts[2:-1]), parts[-1]
        sub = ["", "self_attn.q", "self_attn.k", "self_attn.v", "self_attn.o", "self_attn.norm_q", "self_attn.norm_k",
               "norm3", "cross_attn.q", "cross_attn.k", "cross_attn.v", "cross_attn.o", "cross_attn.norm_q",
               "cross_attn.norm_k", "cross_attn.k_img", "cross_attn.v_img", "cross_attn.norm_k_img", "ffn.0", "ffn.2"]
        idx = sub.index(stem)  # "" = blocks.N.modulation
        return (rank, int(parts[1]), idx, leaf == "bias")
    if parts[0] == "head":
        return (rank, 0, 0 if parts[1] == "modulation" else 1, parts[-1] == "bias")
    return (rank, 0, 0, 0)


def official_layout(model: FunCameraWan) -> dict[str, tuple[int, ...]]:
    """Official names -> shapes of ``model``'s parameters, in the official state_dict order (works on meta)."""
    names = {ours_to_official(k): tuple(v.shape) for k, v in model.state_dict().items()}
    order = sorted(names, key=lambda n: (_official_order(n), list(names).index(n)))
    return {n: names[n] for n in order}


def read_key_list(path: str | os.PathLike = KEY_LIST_1_3B) -> tuple[dict[str, Any], dict[str, tuple[int, ...]]]:
    """The committed official layout: (its header, official key -> shape in file order)."""
    d = json.loads(Path(path).read_text())
    layout = {k: tuple(int(s) for s in shape) for k, shape in d["keys"]}
    return {k: v for k, v in d.items() if k != "keys"}, layout


def check_layout(found: dict[str, Sequence[int]], expected: dict[str, Sequence[int]], source: str) -> None:
    """Strict key and shape check; ``FunCameraWeightsError`` naming what is missing, unexpected or mis-shaped."""
    checkpoints.check_layout(
        found, expected, FunCameraWeightsError,
        f"{source}: not the Wan2.1-Fun Control-Camera layout its config.json describes",
        hint=". Pass the official transformer folder (config.json + diffusion_pytorch_model*.safetensors of "
        "alibaba-pai/Wan2.1-Fun-V1.1-{1.3B,14B}-Control-Camera), unmodified, with the config.json it came with")


def _transformer_dir(directory: Path) -> Path:
    """The official model folder holds the transformer at its root (``transformer_subpath: ./``); a folder with a
    ``transformer/`` sub-folder is accepted too."""
    if (directory / OFFICIAL_CONFIG).is_file():
        return directory
    if (directory / "transformer" / OFFICIAL_CONFIG).is_file():
        return directory / "transformer"
    raise FileNotFoundError(f"{directory}: no {OFFICIAL_CONFIG} (the official Wan2.1-Fun-V1.1-*-Control-Camera "
                            f"folder has config.json and diffusion_pytorch_model.safetensors at its root)")


def read_fun_camera_config(directory: str | os.PathLike) -> FunCameraConfig:
    d = _transformer_dir(Path(directory))
    return FunCameraConfig.from_official_config(json.loads((d / OFFICIAL_CONFIG).read_text()),
                                                str(d / OFFICIAL_CONFIG))


def load_fun_camera(directory: str | os.PathLike, torch_dtype: torch.dtype | None = None) -> FunCameraWan:
    """``FunCameraWan`` from the official checkpoint folder (``config.json`` + safetensors, single or sharded).

    The architecture is built from ``config.json`` on the meta device, every tensor name and shape of the files is
    checked against it (``check_layout``: missing, unexpected and wrong-shape keys are all refused, unlike the
    official loader, which skips mismatches and initialises missing keys), then the tensors are loaded. Float32 by
    default (what the ONNX export runs); ``torch_dtype`` casts.
    """
    from safetensors import safe_open

    d = _transformer_dir(Path(directory))
    config = read_fun_camera_config(d)
    with torch.device("meta"):
        expected = official_layout(FunCameraWan(config))
    files = checkpoints.safetensors_files(d)
    found = checkpoints.safetensors_layout(files, FunCameraWeightsError)
    check_layout(found, expected, str(d))
    model = FunCameraWan(config)
    state = {}
    for f in files:
        with safe_open(str(f), framework="pt") as sf:
            for k in sf.keys():
                state[official_to_ours(k)] = sf.get_tensor(k).to(torch_dtype or torch.float32)
    model.load_state_dict(state, strict=True)
    if torch_dtype is not None:
        model = model.to(torch_dtype)
    return model.eval()


def fun_camera_state_dict_official(model: FunCameraWan) -> dict[str, torch.Tensor]:
    """``model``'s weights under the official names, in the official order."""
    ours = model.state_dict()
    by_official = {ours_to_official(k): v for k, v in ours.items()}
    return {k: by_official[k].detach().contiguous().cpu() for k in official_layout(model)}


def save_fun_camera(model: FunCameraWan, directory: str | os.PathLike) -> Path:
    """Write the official layout (``config.json`` + ``diffusion_pytorch_model.safetensors``) that
    ``load_fun_camera`` (and the official loader) reads; the config is written last (temp file + rename)."""
    from safetensors.torch import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    tmp = directory / (OFFICIAL_WEIGHTS + ".tmp")
    save_file(fun_camera_state_dict_official(model), str(tmp), metadata={"format": "pt"})
    os.replace(tmp, directory / OFFICIAL_WEIGHTS)
    tmp = directory / (OFFICIAL_CONFIG + ".tmp")
    tmp.write_text(json.dumps(model.config.official_config(), indent=2))
    os.replace(tmp, directory / OFFICIAL_CONFIG)
    return directory


@torch.no_grad()
def init_navcrafter_from_fun_camera(fun: FunCameraWan, control_config=None):
    """A ``camcontrol.CameraControlledWan`` whose **base** is Fun-Camera's DiT and whose control is fresh
    (zero-initialised, so the result equals that base exactly until trained).

    What transfers: every base tensor (embeddings, blocks, head, CLIP ``img_emb``) has the same name and shape
    in both layouts except the patch embedding, whose 32 input channels ``[noisy | start image]`` are placed at
    NavCrafter's 36-channel I2V layout ``[noisy (0:16) | mask (16:20) | condition (20:36)]`` with zero weights on
    the mask channels (Fun-Camera was trained without a mask). What does not: the camera adapter
    (``SimpleAdapter``: one 2D pixel-unshuffle conv added once after the patch embedding, on un-normalised
    ``(o x d, d)`` rays) has no counterpart in NavCrafter's control (3D-conv adapter projected into every block,
    LoRA encoder, reference attention, render embedding), so the control starts from zero. See
    models/synthesis/README.md ("Fun-Camera").
    """
    cfg = fun.config
    kwargs = {**cfg.diffusers_kwargs(), "in_channels": 2 * LATENT_CHANNELS + 4}
    with torch.device(fun.base.device):
        base = WanTransformer3DModel(**kwargs).to(fun.base.dtype)
    src = fun.base.state_dict()
    dst = base.state_dict()
    if set(src) != set(dst):
        raise FunCameraWeightsError(f"the base layouts differ: {checkpoints.listing(sorted(set(src) ^ set(dst)))}")
    for k, v in src.items():
        if k == "patch_embedding.weight":
            w = torch.zeros_like(dst[k])
            w[:, :LATENT_CHANNELS] = v[:, :LATENT_CHANNELS]
            w[:, LATENT_CHANNELS + 4:] = v[:, LATENT_CHANNELS:]
            dst[k].copy_(w)
        else:
            dst[k].copy_(v)
    return CameraControlledWan(base.eval(), control_config).eval()

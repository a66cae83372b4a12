"""ONNX export of the whole camera-controlled DiT (``export_dit``) and the example inputs named as its graph inputs."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
import torch.nn as nn

from navcrafter.models.runtime.onnxio import export_graph
from navcrafter.models.synthesis.camcontrol.config import DIT_INPUTS, DIT_OUTPUTS, TEXT_TOKENS

if TYPE_CHECKING:
    from navcrafter.models.synthesis.camcontrol.model import CameraControlledWan


class _ExportWrapper(nn.Module):
    """Positional signature of the exported graph (absent optional inputs are passed as ``None``)."""

    def __init__(self, model: CameraControlledWan) -> None:
        super().__init__()
        self.model = model

    def forward(self, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker, cond,
                lora_scale, image_reference, image_reference_plucker):
        return self.model(hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker,
                          cond, lora_scale, image_reference, image_reference_plucker)


def example_inputs(model: CameraControlledWan, example_shape: Sequence[int], image_tokens: int = 257,
                   seed: int = 0, reference_images: int = 1) -> dict[str, torch.Tensor]:
    """Random inputs named as the exported graph's inputs. ``example_shape = (batch, F, h, w)`` in latent
    units (video frames ``4(F-1)+1``, pixels ``8h × 8w``); ``reference_images`` extra reference frames
    (``image_reference`` / ``image_reference_plucker``; 0: none)."""
    b, f, h, w = (int(v) for v in example_shape)
    c = model.base.config
    st_t, st_h, st_w = model.config.vae_stride
    g = torch.Generator().manual_seed(seed)
    dtype = model.base.dtype

    def r(*shape):
        return torch.randn(*shape, generator=g).to(dtype)

    inputs = {"hidden_states": r(b, c.in_channels, f, h, w),
              "timestep": torch.linspace(100.0, 900.0, b).to(dtype),
              "encoder_hidden_states": r(b, TEXT_TOKENS, c.text_dim)}
    if c.image_dim is not None:
        inputs["encoder_hidden_states_image"] = r(b, image_tokens, c.image_dim)
    inputs["plucker"] = r(b, 6, (f - 1) * st_t + 1, h * st_h, w * st_w)
    if model.config.cond_channels:
        inputs["cond"] = r(b, model.config.cond_channels, f, h, w)
    inputs["lora_scale"] = torch.tensor(model.config.lora_scale, dtype=dtype)
    if reference_images:
        inputs["image_reference"] = r(b, model.config.latent_channels, reference_images, h, w)
        inputs["image_reference_plucker"] = r(b, 6, reference_images, h * st_h, w * st_w)
    return inputs


def export_dit(model: CameraControlledWan, out_path: str | os.PathLike, example_shape: Sequence[int] = (2, 2, 4, 4),
               image_tokens: int = 257, max_latent_frames: int | None = None):
    """Export the whole camera-controlled DiT to ONNX (``out_path`` + ``out_path.data``).

    Inputs (in order; ``encoder_hidden_states_image`` only for an I2V base, ``cond`` only when
    ``cond_channels > 0``): hidden_states [B, C_in, F, h, w], timestep [B] (float), encoder_hidden_states
    [B, 512, text_dim], encoder_hidden_states_image [B, L_img, image_dim], plucker [B, 6, 4F-3, 8h, 8w],
    cond [B, cond_channels, F, h, w], lora_scale [], image_reference [B, 16, R, h, w], image_reference_plucker
    [B, 6, R, 8h, 8w] -> noise_pred [B, out_channels, F, h, w].
    Dynamic: batch, F (``latent_frames``), h = 2·``half_height``, w = 2·``half_width``, L_img, R
    (``reference_images``, >= 1); the text length is fixed at 512. ``example_shape = (batch, F, h, w)`` (batch 2 =
    one CFG pair; F ≥ 2; the example has R = 2 so that R stays dynamic).
    Reference frames are ``config.inference_reference_frames`` (constant in the graph).
    """
    from torch.export import Dim

    b, f, h, w = (int(v) for v in example_shape)
    p_t, p_h, p_w = model.base.config.patch_size
    if p_t != 1 or h % p_h or w % p_w or f < 2 or b < 2:
        raise ValueError(f"example_shape (batch, F, h, w) needs batch >= 2, F >= 2 and h, w multiples of the "
                         f"patch ({p_h}, {p_w}); got {tuple(example_shape)}")
    rope_max = model.base.config.rope_max_seq_len
    st_t, st_h, st_w = model.config.vae_stride
    inputs = example_inputs(model, example_shape, image_tokens, reference_images=2)
    names = [n for n in DIT_INPUTS if n in inputs]

    batch = Dim("batch", min=1, max=1024)
    frames = Dim("latent_frames", min=2, max=max_latent_frames or rope_max)
    hh = Dim("half_height", min=1, max=rope_max)
    hw = Dim("half_width", min=1, max=rope_max)
    refs = Dim("reference_images", min=1, max=64)
    shapes: dict[str, dict[int, Any]] = {
        "hidden_states": {0: batch, 2: frames, 3: p_h * hh, 4: p_w * hw},
        "timestep": {0: batch},
        "encoder_hidden_states": {0: batch},
        "encoder_hidden_states_image": {0: batch, 1: Dim("image_tokens", min=2, max=4096)},
        "plucker": {0: batch, 2: st_t * frames - (st_t - 1), 3: st_h * p_h * hh, 4: st_w * p_w * hw},
        "cond": {0: batch, 2: frames, 3: p_h * hh, 4: p_w * hw},
        "lora_scale": {},
        "image_reference": {0: batch, 2: refs, 3: p_h * hh, 4: p_w * hw},
        "image_reference_plucker": {0: batch, 2: refs, 3: st_h * p_h * hh, 4: st_w * p_w * hw},
    }
    wrapper = _ExportWrapper(model).eval()
    args = tuple(inputs.get(n) for n in DIT_INPUTS)
    dynamic = tuple(shapes[n] if n in inputs else None for n in DIT_INPUTS)
    info = export_graph(wrapper, args, Path(out_path), input_names=names, output_names=list(DIT_OUTPUTS),
                        dynamic_shapes=dynamic)
    info.notes = (f"camera-controlled Wan2.1 DiT; plucker_convention={model.config.plucker_convention}; "
                  f"reference_frames={list(model.config.inference_reference_frames)} + image_reference "
                  f"(rope frame 0); projection_rank={model.config.projection_rank}; "
                  f"text tokens fixed at {TEXT_TOKENS}")
    return info

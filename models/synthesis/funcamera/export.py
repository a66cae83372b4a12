"""ONNX export of the Fun-Camera DiT (``export_fun_camera_dit``) and example inputs named as its graph inputs."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import torch.nn as nn

from navcrafter.models.runtime.onnxio import export_graph
from navcrafter.models.synthesis.funcamera.config import (
    FUN_DIT_INPUTS,
    FUN_DIT_OUTPUTS,
    PLUCKER_CHANNELS,
    PLUCKER_CONVENTION,
    TEXT_TOKENS,
)

if TYPE_CHECKING:
    from navcrafter.models.synthesis.funcamera.model import FunCameraWan


class _FunExportWrapper(nn.Module):
    def __init__(self, model: FunCameraWan) -> None:
        super().__init__()
        self.model = model

    def forward(self, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker):
        return self.model(hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker)


def fun_example_inputs(model: FunCameraWan, example_shape: Sequence[int], image_tokens: int = 257,
                       seed: int = 0) -> dict[str, torch.Tensor]:
    """Random inputs named as the graph's; ``example_shape = (batch, F, h, w)`` in latent units."""
    b, f, h, w = (int(v) for v in example_shape)
    c = model.config
    st, ds = c.temporal_packing, c.downscale_factor_control_adapter
    g = torch.Generator().manual_seed(seed)
    dtype = model.base.dtype

    def r(*shape):
        return torch.randn(*shape, generator=g).to(dtype)

    return {"hidden_states": r(b, c.in_dim, f, h, w), "timestep": torch.linspace(100.0, 900.0, b).to(dtype),
            "encoder_hidden_states": r(b, TEXT_TOKENS, c.text_dim),
            "encoder_hidden_states_image": r(b, image_tokens, c.image_dim),
            "plucker": r(b, PLUCKER_CHANNELS, (f - 1) * st + 1, h * ds, w * ds)}


def export_fun_camera_dit(model: FunCameraWan, out_path: str | os.PathLike, example_shape: Sequence[int] = (2, 2, 4, 4),
                          image_tokens: int = 257, dynamic: bool = True):
    """Export the Fun-Camera DiT to ONNX (``out_path`` + ``.data``): inputs ``FUN_DIT_INPUTS`` -> ``noise_pred``.

    ``dynamic``: batch, latent frames, height, width and image tokens dynamic (text fixed at 512), else exactly
    ``example_shape``."""
    from torch.export import Dim

    b, f, h, w = (int(v) for v in example_shape)
    p_t, p_h, p_w = model.config.patch_size
    if p_t != 1 or h % p_h or w % p_w or f < 2 or b < 1:
        raise ValueError(f"example_shape (batch, F, h, w) needs F >= 2 and h, w multiples of the patch "
                         f"({p_h}, {p_w}); got {tuple(example_shape)}")
    inputs = fun_example_inputs(model, example_shape, image_tokens)
    st, ds = model.config.temporal_packing, model.config.downscale_factor_control_adapter
    dynamic_shapes = None
    if dynamic:
        rope_max = model.config.rope_max_seq_len
        batch = Dim("batch", min=1, max=1024)
        frames = Dim("latent_frames", min=2, max=rope_max)
        hh, hw = Dim("half_height", min=1, max=rope_max), Dim("half_width", min=1, max=rope_max)
        dynamic_shapes = ({0: batch, 2: frames, 3: p_h * hh, 4: p_w * hw}, {0: batch}, {0: batch},
                          {0: batch, 1: Dim("image_tokens", min=2, max=4096)},
                          {0: batch, 2: st * frames - (st - 1), 3: ds * p_h * hh, 4: ds * p_w * hw})
    info = export_graph(_FunExportWrapper(model).eval(), tuple(inputs[n] for n in FUN_DIT_INPUTS), Path(out_path),
                        input_names=list(FUN_DIT_INPUTS), output_names=list(FUN_DIT_OUTPUTS),
                        dynamic_shapes=dynamic_shapes)
    info.notes = (f"Wan2.1-Fun Control-Camera DiT (VideoX-Fun); plucker_convention={PLUCKER_CONVENTION} "
                  f"(fun_camera_plucker: (o x d, d), first camera = identity, no scale); input "
                  f"[noisy 16 | start-image latents 16]; text tokens fixed at {TEXT_TOKENS}"
                  + ("" if dynamic else f"; static shapes {tuple(example_shape)}"))
    return info

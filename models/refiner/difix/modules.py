"""Difix's additions to diffusers' modules: the VAE LoRA layers, the encoder-decoder skip convolutions and the
reference-mixing attention processor."""

from __future__ import annotations

import torch
from torch import nn

from navcrafter.models.refiner.difix.config import LORA_ADAPTER, LORA_TARGET_SUFFIXES


class LoraLayer(nn.Module):
    """A LoRA adapter around a ``Conv2d`` or ``Linear`` with peft's module layout and arithmetic:
    ``base_layer(x) + lora_B[adapter](lora_A[adapter](x)) * lora_alpha / rank`` (dropout 0). For convolutions
    ``lora_A`` has the base kernel, stride and padding and ``lora_B`` is 1x1, as peft's ``lora.Conv2d``."""

    def __init__(self, base: nn.Module, rank: int, alpha: float, adapter: str = LORA_ADAPTER) -> None:
        super().__init__()
        self.base_layer = base
        if isinstance(base, nn.Conv2d):
            a = nn.Conv2d(base.in_channels, rank, base.kernel_size, base.stride, base.padding, bias=False)
            b = nn.Conv2d(rank, base.out_channels, (1, 1), (1, 1), bias=False)
        elif isinstance(base, nn.Linear):
            a, b = nn.Linear(base.in_features, rank, bias=False), nn.Linear(rank, base.out_features, bias=False)
        else:
            raise TypeError(f"LoRA wraps Conv2d or Linear, not {type(base).__name__}")
        nn.init.zeros_(b.weight)  # peft's initialisation: the adapter starts as a no-op
        self.lora_A = nn.ModuleDict({adapter: a})
        self.lora_B = nn.ModuleDict({adapter: b})
        self.adapter = adapter
        self.scaling = float(alpha) / rank

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.base_layer(x) + self.lora_B[self.adapter](self.lora_A[self.adapter](x)) * self.scaling

    @torch.no_grad()
    def merged(self) -> nn.Module:
        """The base layer with the adapter folded into its weight (exact up to rounding)."""
        a, b = self.lora_A[self.adapter].weight, self.lora_B[self.adapter].weight
        if isinstance(self.base_layer, nn.Conv2d):
            delta = torch.einsum("or,rikl->oikl", b[:, :, 0, 0], a)
        else:
            delta = b @ a
        self.base_layer.weight.add_(delta * self.scaling)
        return self.base_layer


def skip_channels(vae_block_out_channels: tuple[int, ...]) -> list[tuple[int, int]]:
    """(in, out) channels of ``decoder.skip_conv_1..n``: skip ``i`` takes the input of encoder down block
    ``n-1-i`` and feeds decoder up block ``i`` (official: (512, 512), (256, 512), (128, 512), (128, 256))."""
    c = list(vae_block_out_channels)
    encoder_inputs = [c[0]] + c[:-1]  # conv_in output, then each block's output
    rev = c[::-1]
    decoder_inputs = [rev[0]] + rev[:-1]  # mid block output, then each up block's output
    return [(encoder_inputs[len(c) - 1 - i], decoder_inputs[i]) for i in range(len(c))]


def lora_target_modules(vae: nn.Module) -> list[str]:
    """The decoder modules the official code adapts (``'decoder' in name`` and a target suffix), in
    ``named_modules`` order; skip convolutions must already be attached."""
    return [name for name, _ in vae.named_modules()
            if "decoder" in name and any(name.endswith(s) for s in LORA_TARGET_SUFFIXES)]


def _set_submodule(root: nn.Module, name: str, module: nn.Module) -> None:
    parent_name, _, child = name.rpartition(".")
    parent = root.get_submodule(parent_name) if parent_name else root
    setattr(parent, child, module)


class ReferenceMixingAttnProcessor:
    """Self-attention over the tokens of all views of a sample (``mv_unet.py``'s reference mixing): hidden
    states ``[(B V), N, C]`` are folded to ``[B, V N, C]``, attended with diffusers' ``AttnProcessor2_0`` and
    unfolded. Only for ``attn1`` (no encoder states, no mask)."""

    def __init__(self, num_views: int = 2) -> None:
        from diffusers.models.attention_processor import AttnProcessor2_0

        self.num_views = int(num_views)
        self.inner = AttnProcessor2_0()

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states: torch.Tensor | None = None,
                 attention_mask: torch.Tensor | None = None, temb: torch.Tensor | None = None,
                 **kwargs) -> torch.Tensor:
        if encoder_hidden_states is not None or attention_mask is not None or hidden_states.ndim != 3:
            raise ValueError("reference mixing applies to token self-attention without a mask only")
        bv, n, c = hidden_states.shape
        v = self.num_views
        folded = hidden_states.reshape(bv // v, v * n, c)
        out = self.inner(attn, folded)
        return out.reshape(bv, n, out.shape[-1])

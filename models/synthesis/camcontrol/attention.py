"""``CameraControlAttnProcessor``: the Wan self-attention with the camera LoRA on Q/K/V, the adapter's attention
branch and the decoupled reference-frame attention."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from diffusers.models.attention_dispatch import dispatch_attention_fn
from diffusers.models.transformers.transformer_wan import _get_qkv_projections

if TYPE_CHECKING:
    from navcrafter.models.synthesis.camcontrol.modules import CameraControl, CameraControlBlock


@dataclass
class _ControlState:
    control: CameraControl
    x_c: torch.Tensor | None  # [B, L, D]
    x_l: torch.Tensor | None  # [B, L, r_in]
    lora_scale: torch.Tensor  # scalar
    ref_tokens: torch.Tensor | None  # [B, Lr, D]
    ref_x_c: torch.Tensor | None  # [B, Lr, D] (x_c at the reference positions)
    ref_rope: tuple[torch.Tensor, torch.Tensor] | None  # each [1, Lr, 1, head_dim]
    eps: float


def _apply_rotary_emb(x: torch.Tensor, freqs_cos: torch.Tensor, freqs_sin: torch.Tensor) -> torch.Tensor:
    # The same elementwise float ops as diffusers' WanAttnProcessor (so the untrained wrapper is bit-exact),
    # interleaved with stack/flatten instead of strided writes into empty_like (a smaller exported graph).
    x1, x2 = x.unflatten(-1, (-1, 2)).unbind(-1)
    cos = freqs_cos[..., 0::2]
    sin = freqs_sin[..., 1::2]
    out = torch.stack([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1).flatten(-2)
    return out.type_as(x)


class CameraControlAttnProcessor:
    """Self-attention (``attn1``) processor of one ``WanTransformerBlock`` with camera control.

    Computes exactly what diffusers' ``WanAttnProcessor`` computes, plus, when the wrapper has set
    ``state`` for the current forward: LoRA deltas on Q/K/V, the reference-frame attention branch and the
    ``x_c`` projection added to the attention output. With ``state = None`` it is the base processor.
    """

    _attention_backend = None
    _parallel_config = None

    def __init__(self, index: int) -> None:
        self.index = index
        self.state: _ControlState | None = None

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states: torch.Tensor | None = None,
                 attention_mask: torch.Tensor | None = None,
                 rotary_emb: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        if encoder_hidden_states is not None or attn.add_k_proj is not None:
            raise ValueError("CameraControlAttnProcessor is for the self-attention (attn1) only")
        st = self.state
        blk = st.control.blocks[self.index] if st is not None else None

        query, key, value = _get_qkv_projections(attn, hidden_states, None)
        if blk is not None and st.x_l is not None:
            query = query + st.lora_scale * blk.lora_q(st.x_l)
            key = key + st.lora_scale * blk.lora_k(st.x_l)
            value = value + st.lora_scale * blk.lora_v(st.x_l)

        query = attn.norm_q(query)
        key = attn.norm_k(key)
        query = query.unflatten(2, (attn.heads, -1))
        key = key.unflatten(2, (attn.heads, -1))
        value = value.unflatten(2, (attn.heads, -1))
        if rotary_emb is not None:
            query = _apply_rotary_emb(query, *rotary_emb)
            key = _apply_rotary_emb(key, *rotary_emb)

        hidden_states = dispatch_attention_fn(query, key, value, attn_mask=attention_mask, dropout_p=0.0,
                                              is_causal=False, backend=self._attention_backend,
                                              parallel_config=self._parallel_config)
        hidden_states = hidden_states.flatten(2, 3).type_as(query)

        if blk is not None and st.ref_tokens is not None:
            hidden_states = hidden_states + blk.ref_gate * self._reference_attention(attn, st, blk, query)

        hidden_states = attn.to_out[0](hidden_states)
        hidden_states = attn.to_out[1](hidden_states)
        if blk is not None and st.x_c is not None:
            hidden_states = hidden_states + blk.attn_proj(st.x_c)
        return hidden_states

    def _reference_attention(self, attn, st: _ControlState, blk: CameraControlBlock,
                             query: torch.Tensor) -> torch.Tensor:
        ref = st.ref_tokens
        if st.ref_x_c is not None:
            ref = ref + blk.pre_proj(st.ref_x_c)
        ref = F.layer_norm(ref.float(), (ref.shape[-1],), eps=st.eps).type_as(ref)
        if getattr(attn, "fused_projections", False):
            _, key, value = attn.to_qkv(ref).chunk(3, dim=-1)
        else:
            key, value = attn.to_k(ref), attn.to_v(ref)
        key = attn.norm_k(key).unflatten(2, (attn.heads, -1))
        value = value.unflatten(2, (attn.heads, -1))
        if st.ref_rope is not None:
            key = _apply_rotary_emb(key, *st.ref_rope)
        out = dispatch_attention_fn(query, key, value, attn_mask=None, dropout_p=0.0, is_causal=False,
                                    backend=self._attention_backend, parallel_config=None)
        return out.flatten(2, 3).type_as(query)

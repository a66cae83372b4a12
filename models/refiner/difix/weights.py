"""Difix-architecture single-step diffusion refiner (torch), official checkpoint layout, ONNX export.

The network is the one of Difix / Difix3D+ (Wu et al., "Difix3D+: Improving 3D Reconstructions with
Single-Step Diffusion Models", CVPR 2025; code github.com/nv-tlabs/Difix3D, read at commit c76edc5:
``src/model.py``, ``src/mv_unet.py``, ``src/pipeline_difix.py``, ``src/inference_difix.py``,
``examples/gsplat/simple_trainer_difix3d.py``; checkpoints ``nvidia/difix`` and ``nvidia/difix_ref``), built
from diffusers' own modules (``UNet2DConditionModel``, ``AutoencoderKL``, ``AttnProcessor2_0``):

1. **VAE encoder** (SD-Turbo's ``AutoencoderKL``). As the official ``my_vae_encoder_fwd``, the input of every
   encoder down block is kept as a skip activation. The latent is a *sample* of the posterior
   (``latent_dist.sample()`` in ``model.py``, ``retrieve_latents(..., sample_mode="sample")`` in the pipeline):
   ``z = (mean + std * noise) * scaling_factor`` with ``std = exp(0.5 * clamp(logvar, -30, 20))``. The noise is
   an input here (``latent_noise``), so the graph is deterministic and the caller seeds it; zeros give the
   posterior mode.
2. **UNet** (SD-Turbo's ``UNet2DConditionModel`` = the SD 2.1 UNet, epsilon prediction), evaluated once at the
   fixed timestep ``t = 199`` (README, ``train_difix.py``/``inference_difix.py --timestep 199``, the gsplat
   trainer's ``timesteps=[199]``; the ``Difix`` class default of 999 is overridden everywhere), conditioned on
   the CLIP embedding of the fixed prompt ``"remove degradation"`` (no classifier-free guidance:
   ``guidance_scale=0.0``). The text encoder is not part of the graph: the prompt's
   embedding (CLIPTextModel ``last_hidden_state`` of the 77-token padded prompt, as ``model.py`` and the
   pipeline's ``encode_prompt``) is computed once at export and stored in ``prompt_embeds.npy``.
3. **One scheduler step**: ``DDPMScheduler`` (SD-Turbo's scheduler config: scaled-linear betas 0.00085..0.012,
   1000 steps, ``prediction_type="epsilon"``, ``clip_sample=false``) stepping from ``t`` with one inference
   step, so the previous timestep is < 0, ``alpha_prod_prev = 1`` and the step returns the x0 prediction
   ``(z - sqrt(1 - abar_t) eps) / sqrt(abar_t)``. (DDPM still adds ``sqrt(1e-20) * noise`` = 1e-10 noise
   there - its variance clamp - which is below float32 resolution of the latents and is left out.)
4. **VAE decoder with skip connections** (pix2pix-turbo style, ``my_vae_decoder_fwd``): before decoder up
   block ``i`` the encoder's skip activations, reversed, go through ``decoder.skip_conv_{i+1}`` (1x1, no bias)
   and are added (times ``gamma = 1``). For SD-Turbo's VAE: ``skip_conv_1`` 512->512, ``skip_conv_2``
   256->512, ``skip_conv_3`` 128->512, ``skip_conv_4`` 128->256. The decoder also carries **LoRA** adapters
   (peft, adapter name ``vae_skip``, rank ``rank_vae`` = 4) on every decoder ``conv1, conv2, conv_in,
   conv_shortcut, conv, conv_out, skip_conv_1..4, to_k, to_q, to_v, to_out.0`` (43 modules); peft's
   ``LoraConfig`` default ``lora_alpha = 8`` (the official code does not set it) gives scaling ``8 / 4 = 2``.
   The output is clamped to [-1, 1].
5. **Reference mixing** (``nvidia/difix_ref``, ``mv_unet.py``): input view and reference view are encoded as a
   batch of two views, ``(b v)``; in every ``BasicTransformerBlock`` of the UNet the self-attention (``attn1``)
   runs on the tokens of both views folded into one sequence (``"(b v) n d -> b (v n) d"``, ``num_views = 2``)
   and is unfolded afterwards; cross-attention, feed-forward and all convolutions stay per view. It adds no
   parameters. Here it is a custom attention processor on every ``attn1`` (LayerNorm and the residual are per
   token, so folding inside the processor equals the official patched block forward). Only the input view is
   decoded (the pipeline decodes view 0 with view-0 skips). ``DifixConfig.reference_mixing = False`` is the
   plain ``nvidia/difix`` model (one view, no reference).

**Official checkpoint layouts** read by ``load_difix_weights`` (names and shapes are checked before loading):

- the diffusers directory of ``nvidia/difix`` / ``nvidia/difix_ref`` (``model_index.json``: ``DifixPipeline``,
  diffusers ``UNet2DConditionModel``, a custom ``vae/autoencoder_kl.py`` ``AutoencoderKL``, CLIP text encoder
  and tokenizer, ``DDPMScheduler``): ``unet/diffusion_pytorch_model.safetensors`` with diffusers' UNet names
  and ``vae/diffusion_pytorch_model.safetensors`` with diffusers' VAE names plus ``decoder.skip_conv_{1..4}``
  and the unmerged peft LoRA (``<module>.base_layer.weight|bias``, ``<module>.lora_A.vae_skip.weight``,
  ``<module>.lora_B.vae_skip.weight``). The custom VAE class file itself could not be read; the names were
  established by a byte-exact match: a safetensors file with exactly the names and shapes of this module's
  ``DifixConfig.sd_turbo()`` state dict (fp32, metadata ``{"format": "pt"}``) has the published sizes of
  ``nvidia/difix``'s files (VAE 338,717,612 bytes: 338 tensors, 40,344-byte header; UNet 3,463,726,504 bytes:
  686 tensors, which also pins ``use_linear_projection = True``); the sizes were taken from a third-party
  pinned download manifest of ``nvidia/difix`` (size and sha256 of every file, and its ``model_index.json``;
  found through a code search), as the hub cannot be reached from here. The committed list
  ``keys/difix_sd_turbo.txt`` is that layout. ``nvidia/difix_ref`` is assumed to share it (reference mixing
  has no parameters); its LoRA scaling (``lora_alpha``) lives in the unreadable custom class and is assumed
  to be peft's default 8, like the training code's (``DifixConfig.lora_alpha`` changes it);
- the GitHub training checkpoint ``model_*.pkl`` (``save_ckpt`` in ``src/model.py``, read here with
  ``torch.load(weights_only=True)``): ``state_dict_unet`` (the full UNet), ``state_dict_vae`` (only the LoRA
  and skip-conv entries, same names as above), ``rank_vae`` and ``vae_lora_target_modules``. Its base VAE
  weights are SD-Turbo's: pass ``base=`` an ``stabilityai/sd-turbo`` diffusers directory (as the official
  loader, every entry the checkpoint lacks is taken from there).

What is not reproduced: the text encoder is not exported (the fixed prompt is precomputed), the 1e-10 DDPM
variance noise is dropped, and the UNet runs at latent sizes that are multiples of its total downsampling
(``DifixConfig.size_multiple`` = 64 pixels for SD-Turbo) - the official code accepts multiples of 8 and
then resizes UNet features with ``upsample_size``; callers resize images to multiples of 64 instead (the
official ``inference_difix.py`` default, 576x1024, is one). The exported graph takes one view per call (batch
1) of at most ``MAX_SIDE`` = 2048 pixels per side. Training is not implemented.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from navcrafter.models.runtime.onnxio import config_from_dict, config_to_dict

ARCHITECTURE = "difix"
KIND = "refiner"
GRAPH = "refiner"
DEFAULT_PROMPT = "remove degradation"
PROMPT_FILE = "prompt_embeds.npy"
LORA_ADAPTER = "vae_skip"
# the official target_modules_vae suffixes (src/model.py), matched against decoder module names
LORA_TARGET_SUFFIXES = ("conv1", "conv2", "conv_in", "conv_shortcut", "conv", "conv_out", "skip_conv_1",
                        "skip_conv_2", "skip_conv_3", "skip_conv_4", "to_k", "to_q", "to_v", "to_out.0")
UNET_FILE = "unet/diffusion_pytorch_model.safetensors"
VAE_FILE = "vae/diffusion_pytorch_model.safetensors"
KEYS_DIR = Path(__file__).parents[1] / "keys"
OFFICIAL_KEYS_SD_TURBO = KEYS_DIR / "difix_sd_turbo.txt"
INPUTS = ("image", "reference", "prompt_embeds", "latent_noise")
OUTPUT = "refined"
MAX_SIDE = 2048  # largest exported image side


class DifixWeightsError(ValueError):
    """A checkpoint does not match the Difix model it is loaded into."""


# ----------------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DifixConfig:
    """Sizes and constants of a Difix network. Defaults are the published SD-Turbo-based model with reference
    mixing (``nvidia/difix_ref``)."""

    # UNet2DConditionModel (SD-Turbo = SD 2.1 UNet; CrossAttn down blocks except the last, mirrored up blocks)
    unet_block_out_channels: tuple[int, ...] = (320, 640, 1280, 1280)
    unet_layers_per_block: int = 2
    unet_attention_heads: tuple[int, ...] = (5, 10, 20, 20)  # diffusers' (misnamed) ``attention_head_dim``
    cross_attention_dim: int = 1024
    unet_norm_num_groups: int = 32
    use_linear_projection: bool = True
    # AutoencoderKL (SD-Turbo's VAE)
    vae_block_out_channels: tuple[int, ...] = (128, 256, 512, 512)
    vae_layers_per_block: int = 2
    vae_norm_num_groups: int = 32
    latent_channels: int = 4
    scaling_factor: float = 0.18215
    # Difix additions: decoder LoRA (peft) and encoder->decoder skip connections
    lora_rank: int = 4
    lora_alpha: float = 8.0
    skip_gamma: float = 1.0
    reference_mixing: bool = True  # nvidia/difix_ref (True) or nvidia/difix (False)
    # one DDPM step from `timestep` (SD-Turbo's scheduler config)
    timestep: int = 199
    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012
    prediction_type: str = "epsilon"
    # text conditioning: CLIP hidden states of the padded prompt
    text_tokens: int = 77

    def __post_init__(self) -> None:
        problems = []
        if len(self.unet_attention_heads) != len(self.unet_block_out_channels):
            problems.append("unet_attention_heads needs one entry per UNet block")
        if any(c % h for c, h in zip(self.unet_block_out_channels, self.unet_attention_heads)):
            problems.append("UNet block channels must be divisible by their number of heads")
        if len(self.unet_block_out_channels) < 2 or len(self.vae_block_out_channels) < 2:
            problems.append("the UNet and the VAE need at least two blocks")
        if any(c % self.unet_norm_num_groups for c in self.unet_block_out_channels):
            problems.append("UNet channels must be divisible by unet_norm_num_groups")
        if any(c % self.vae_norm_num_groups for c in self.vae_block_out_channels):
            problems.append("VAE channels must be divisible by vae_norm_num_groups")
        if self.lora_rank < 1:
            problems.append("lora_rank must be >= 1")
        if not 0 <= self.timestep < self.num_train_timesteps:
            problems.append("timestep must lie in [0, num_train_timesteps)")
        if self.prediction_type not in ("epsilon", "v_prediction", "sample"):
            problems.append("prediction_type must be epsilon, v_prediction or sample")
        if problems:
            raise ValueError("invalid DifixConfig: " + "; ".join(problems))

    @classmethod
    def sd_turbo(cls, reference_mixing: bool = True) -> DifixConfig:
        """The published model: SD-Turbo UNet and VAE, LoRA rank 4, t = 199; ``reference_mixing`` selects
        ``nvidia/difix_ref`` (True) or ``nvidia/difix`` (False)."""
        return cls(reference_mixing=reference_mixing)

    @classmethod
    def tiny(cls, reference_mixing: bool = True) -> DifixConfig:
        """A few-kB random model for tests (same structure with 2-block UNet and VAE, LoRA rank 2; its dynamic
        ONNX export takes ~40 s on a busy 2-core machine, twice that with the 4-block VAE)."""
        return cls(unet_block_out_channels=(8, 16), unet_layers_per_block=1, unet_attention_heads=(2, 2),
                   cross_attention_dim=8, unet_norm_num_groups=4, vae_block_out_channels=(8, 16),
                   vae_layers_per_block=1, vae_norm_num_groups=4, lora_rank=2, reference_mixing=reference_mixing)

    @property
    def num_views(self) -> int:
        return 2 if self.reference_mixing else 1

    @property
    def vae_scale_factor(self) -> int:
        return 2 ** (len(self.vae_block_out_channels) - 1)

    @property
    def size_multiple(self) -> int:
        """Image sides must be multiples of this: the VAE's factor times the UNet's total downsampling."""
        return self.vae_scale_factor * 2 ** (len(self.unet_block_out_channels) - 1)

    def unet_kwargs(self) -> dict[str, Any]:
        n = len(self.unet_block_out_channels)
        return {"sample_size": 64, "in_channels": self.latent_channels, "out_channels": self.latent_channels,
                "down_block_types": ("CrossAttnDownBlock2D",) * (n - 1) + ("DownBlock2D",),
                "up_block_types": ("UpBlock2D",) + ("CrossAttnUpBlock2D",) * (n - 1),
                "block_out_channels": tuple(self.unet_block_out_channels),
                "layers_per_block": self.unet_layers_per_block,
                "attention_head_dim": tuple(self.unet_attention_heads),
                "cross_attention_dim": self.cross_attention_dim, "norm_num_groups": self.unet_norm_num_groups,
                "use_linear_projection": self.use_linear_projection}

    def vae_kwargs(self) -> dict[str, Any]:
        n = len(self.vae_block_out_channels)
        return {"in_channels": 3, "out_channels": 3, "down_block_types": ("DownEncoderBlock2D",) * n,
                "up_block_types": ("UpDecoderBlock2D",) * n, "block_out_channels": tuple(self.vae_block_out_channels),
                "layers_per_block": self.vae_layers_per_block, "latent_channels": self.latent_channels,
                "norm_num_groups": self.vae_norm_num_groups, "scaling_factor": self.scaling_factor}

    def alpha_cumprod(self) -> float:
        """``alphas_cumprod[timestep]`` of diffusers' scaled-linear DDPM schedule (float32, as the scheduler)."""
        betas = torch.linspace(self.beta_start ** 0.5, self.beta_end ** 0.5, self.num_train_timesteps,
                               dtype=torch.float32, device="cpu") ** 2
        return float(torch.cumprod(1.0 - betas, dim=0)[self.timestep])

    def to_dict(self) -> dict[str, Any]:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DifixConfig:
        return config_from_dict(cls, data)


# ----------------------------------------------------------------------------------------------------
# Difix additions to diffusers' modules
# ----------------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------------
# The network
# ----------------------------------------------------------------------------------------------------


class DifixRefinerModel(nn.Module):
    """Difix: ``forward(image, reference, prompt_embeds, latent_noise) -> refined``.

    - ``image``, ``reference``: ``[B, 3, H, W]`` in [-1, 1], H and W multiples of ``config.size_multiple``
      (``reference`` is ignored - may be None - when ``config.reference_mixing`` is False);
    - ``prompt_embeds``: ``[1, text_tokens, cross_attention_dim]`` (the fixed prompt's CLIP hidden states);
    - ``latent_noise``: ``[B, V, latent_channels, H/8, W/8]`` standard normal noise of the posterior sample
      (V = ``config.num_views``: input view, then reference), or None for the posterior mean;
    - returns the refined input view ``[B, 3, H, W]`` in [-1, 1].

    Submodules ``unet`` (diffusers ``UNet2DConditionModel``) and ``vae`` (diffusers ``AutoencoderKL`` with
    ``decoder.skip_conv_*`` and peft-layout LoRA) have the official parameter names, so their state dicts are
    the checkpoint's ``unet/`` and ``vae/`` files.
    """

    def __init__(self, config: DifixConfig) -> None:
        from diffusers import AutoencoderKL, UNet2DConditionModel

        super().__init__()
        self.config = config
        self.unet = UNet2DConditionModel(**config.unet_kwargs())
        vae = AutoencoderKL(**config.vae_kwargs())
        for i, (cin, cout) in enumerate(skip_channels(config.vae_block_out_channels), start=1):
            setattr(vae.decoder, f"skip_conv_{i}", nn.Conv2d(cin, cout, kernel_size=1, stride=1, bias=False))
        for name in lora_target_modules(vae):
            _set_submodule(vae, name, LoraLayer(vae.get_submodule(name), config.lora_rank, config.lora_alpha))
        self.vae = vae
        if config.reference_mixing:
            from diffusers.models.attention import BasicTransformerBlock

            for module in self.unet.modules():
                if isinstance(module, BasicTransformerBlock):
                    module.attn1.set_processor(ReferenceMixingAttnProcessor(config.num_views))
        abar = config.alpha_cumprod()
        self._sqrt_abar, self._sqrt_one_minus_abar = abar ** 0.5, (1.0 - abar) ** 0.5

    def lora_layers(self) -> dict[str, LoraLayer]:
        return {name: m for name, m in self.vae.named_modules() if isinstance(m, LoraLayer)}

    @torch.no_grad()
    def merge_lora_(self) -> DifixRefinerModel:
        """Fold every LoRA adapter into its base layer (in place; for export). The state dict then no longer
        has the official layout."""
        for name, layer in self.lora_layers().items():
            _set_submodule(self.vae, name, layer.merged())
        return self

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
        """Posterior mean and std of the (unscaled) latents and the skip activations (input of every encoder
        down block), as the official ``my_vae_encoder_fwd`` + ``quant_conv``."""
        enc = self.vae.encoder
        h = enc.conv_in(x)
        skips = []
        for block in enc.down_blocks:
            skips.append(h)
            h = block(h)
        h = enc.conv_out(enc.conv_act(enc.conv_norm_out(enc.mid_block(h))))
        if self.vae.quant_conv is not None:
            h = self.vae.quant_conv(h)
        mean, logvar = h.chunk(2, dim=1)
        return mean, torch.exp(0.5 * logvar.clamp(-30.0, 20.0)), skips

    def decode(self, z: torch.Tensor, skips: list[torch.Tensor]) -> torch.Tensor:
        """Unscaled latents + skip activations -> image, as the official ``my_vae_decoder_fwd``."""
        if self.vae.post_quant_conv is not None:
            z = self.vae.post_quant_conv(z)
        dec = self.vae.decoder
        h = dec.mid_block(dec.conv_in(z), None)
        for i, block in enumerate(dec.up_blocks):
            h = h + getattr(dec, f"skip_conv_{i + 1}")(skips[-1 - i] * self.config.skip_gamma)
            h = block(h, None)
        return dec.conv_out(dec.conv_act(dec.conv_norm_out(h)))

    def forward(self, image: torch.Tensor, reference: torch.Tensor | None, prompt_embeds: torch.Tensor,
                latent_noise: torch.Tensor | None = None) -> torch.Tensor:
        cfg = self.config
        b, v = image.shape[0], cfg.num_views
        if v == 2:
            if reference is None:
                raise ValueError("this Difix model mixes a reference view: pass reference (e.g. the image itself)")
            x = torch.stack([image, reference], dim=1).reshape(b * v, *image.shape[1:])
        else:
            x = image
        mean, std, skips = self.encode(x)
        z = mean if latent_noise is None else mean + std * latent_noise.reshape(mean.shape)
        z = z * cfg.scaling_factor
        eps = self.unet(z, cfg.timestep, encoder_hidden_states=prompt_embeds.expand(b * v, -1, -1)).sample
        if cfg.prediction_type == "epsilon":
            x0 = (z - self._sqrt_one_minus_abar * eps) / self._sqrt_abar
        elif cfg.prediction_type == "v_prediction":
            x0 = self._sqrt_abar * z - self._sqrt_one_minus_abar * eps
        else:
            x0 = eps
        if v > 1:  # decode the input view only, with its own skip activations
            x0 = x0.reshape(b, v, *x0.shape[1:])[:, 0]
            skips = [s.reshape(b, v, *s.shape[1:])[:, 0] for s in skips]
        return self.decode(x0 / cfg.scaling_factor, skips).clamp(-1.0, 1.0)


def randomize_adapters(model: DifixRefinerModel, seed: int, std: float = 0.05) -> None:
    """Give the LoRA ``lora_B`` weights (zero-initialised, as peft) small random values so that every path
    of a random test model is live."""
    g = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for layer in model.lora_layers().values():
            w = layer.lora_B[layer.adapter].weight
            w.copy_(torch.randn(w.shape, generator=g) * std)


# ----------------------------------------------------------------------------------------------------
# Official checkpoint layout
# ----------------------------------------------------------------------------------------------------


def official_state_dicts(model: DifixRefinerModel) -> dict[str, dict[str, torch.Tensor]]:
    """``{"unet": ..., "vae": ...}``: the tensors of ``unet/`` and ``vae/diffusion_pytorch_model.safetensors``."""
    vae = model.vae.state_dict()
    if not any(".lora_A." in k for k in vae) and lora_target_modules(model.vae):
        raise ValueError("the model's LoRA adapters were merged (merge_lora_); it has no official layout any more")
    return {"unet": dict(model.unet.state_dict()), "vae": dict(vae)}


def official_key_shapes(model: DifixRefinerModel) -> dict[str, dict[str, tuple[int, ...]]]:
    return {part: {k: tuple(v.shape) for k, v in sd.items()} for part, sd in official_state_dicts(model).items()}


def read_official_key_list(path: Path = OFFICIAL_KEYS_SD_TURBO) -> dict[str, dict[str, tuple[int, ...]]]:
    """A committed ``part name shape`` list (part ``unet`` or ``vae``, dims joined by 'x'); ``#`` comments."""
    out: dict[str, dict[str, tuple[int, ...]]] = {"unet": {}, "vae": {}}
    for line in Path(path).read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            part, name, shape = line.split()
            out[part][name] = tuple(int(s) for s in shape.split("x")) if shape != "scalar" else ()
    return out


def write_official_key_list(model: DifixRefinerModel, path: Path, header: str = "") -> Path:
    lines = [f"# {h}" for h in header.splitlines()] if header else []
    for part, shapes in official_key_shapes(model).items():
        lines += [f"{part} {k} {'x'.join(map(str, s)) or 'scalar'}" for k, s in shapes.items()]
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


def save_difix_weights(model: DifixRefinerModel, directory: Path) -> Path:
    """Write the model in the official diffusers layout: ``unet/`` and ``vae/`` each with
    ``diffusion_pytorch_model.safetensors`` (fp32, metadata ``{"format": "pt"}``) and diffusers' ``config.json``."""
    from safetensors.torch import save_file

    directory = Path(directory)
    parts = official_state_dicts(model)
    for part, module in (("unet", model.unet), ("vae", model.vae)):
        (directory / part).mkdir(parents=True, exist_ok=True)
        save_file({k: v.contiguous() for k, v in parts[part].items()},
                  str(directory / part / "diffusion_pytorch_model.safetensors"), metadata={"format": "pt"})
        module.to_json_file(str(directory / part / "config.json"))
    return directory


def _listing(names, limit: int = 12) -> str:
    names = list(names)
    more = f" ... (+{len(names) - limit} more)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _load_safetensors(path: Path) -> dict[str, torch.Tensor]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as exc:
        raise DifixWeightsError(f"{path}: not a readable safetensors file ({exc})") from exc


def _read_checkpoint(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor], dict[str, Any]]:
    """(unet, vae, info) from a diffusers directory or a training ``.pkl``; info has "files" (name -> sha256)
    and, for ``.pkl``, "rank_vae" and "vae_lora_target_modules"."""
    from navcrafter.models.runtime.onnxio import sha256_file

    if path.is_dir():
        unet_file, vae_file = path / UNET_FILE, path / VAE_FILE
        if not unet_file.is_file() or not vae_file.is_file():
            raise DifixWeightsError(
                f"{path} is not a Difix diffusers directory: it needs {UNET_FILE} and {VAE_FILE} (download "
                f"nvidia/difix_ref or nvidia/difix with all its folders, or pass a training checkpoint .pkl)")
        files = {UNET_FILE: sha256_file(unet_file), VAE_FILE: sha256_file(vae_file)}
        return _load_safetensors(unet_file), _load_safetensors(vae_file), {"files": files}
    if not path.is_file():
        raise DifixWeightsError(f"Difix checkpoint {path} does not exist")
    if path.suffix == ".safetensors":
        raise DifixWeightsError(
            f"{path}: a single .safetensors file is not a Difix layout; pass the model directory holding "
            f"{UNET_FILE} and {VAE_FILE} (nvidia/difix_ref), or the training checkpoint model_*.pkl")
    try:
        data = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # weights_only refuses pickled code objects: never fall back to full pickle
        raise DifixWeightsError(f"{path}: not a tensor-only torch checkpoint ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("state_dict_unet"), dict):
        raise DifixWeightsError(f"{path}: expected the official training checkpoint (a dict with "
                                f"'state_dict_unet', 'state_dict_vae', 'rank_vae', 'vae_lora_target_modules')")
    info = {"files": {path.name: sha256_file(path)}, "rank_vae": data.get("rank_vae"),
            "vae_lora_target_modules": data.get("vae_lora_target_modules")}
    return dict(data["state_dict_unet"]), dict(data.get("state_dict_vae") or {}), info


def _base_weights(base: Path, model: DifixRefinerModel) -> tuple[dict, dict, dict[str, str]]:
    """SD-Turbo's UNet and VAE (plain diffusers names) with the VAE renamed to the LoRA layout
    (``X.weight`` -> ``X.base_layer.weight`` for adapted modules)."""
    from navcrafter.models.runtime.onnxio import sha256_file

    base = Path(base)
    unet_file, vae_file = base / UNET_FILE, base / VAE_FILE
    if not unet_file.is_file() or not vae_file.is_file():
        raise DifixWeightsError(f"base {base} is not an SD-Turbo diffusers directory (needs {UNET_FILE} and "
                                f"{VAE_FILE}; download stabilityai/sd-turbo)")
    targets = set(model.lora_layers())
    vae = {}
    for k, v in _load_safetensors(vae_file).items():
        module, _, leaf = k.rpartition(".")
        vae[f"{module}.base_layer.{leaf}" if module in targets else k] = v
    files = {f"base/{UNET_FILE}": sha256_file(unet_file), f"base/{VAE_FILE}": sha256_file(vae_file)}
    return _load_safetensors(unet_file), vae, files


def load_difix_weights(model: DifixRefinerModel, path: Path, *, base: Path | None = None) -> dict[str, Any]:
    """Load an official Difix checkpoint into ``model`` (see the module docstring for the layouts):

    - a diffusers directory (``nvidia/difix_ref`` / ``nvidia/difix``) with ``unet/`` and ``vae/`` safetensors;
    - the training checkpoint ``model_*.pkl`` (``torch.load(weights_only=True)``); its rank and LoRA targets
      must match the model's config. Entries it lacks (the base VAE) come from ``base``, an SD-Turbo diffusers
      directory, as in the official loader.

    Every name and shape is checked against the model first; a mismatch raises ``DifixWeightsError`` naming
    the file, the missing, unexpected and wrong-shape entries and the fix. Tensors are converted to float32.
    Returns ``{"path", "files": {name: sha256}}``."""
    path = Path(path)
    unet_sd, vae_sd, info = _read_checkpoint(path)
    cfg = model.config
    rank = info.get("rank_vae")
    if rank is not None and int(rank) != cfg.lora_rank:
        raise DifixWeightsError(f"{path}: rank_vae is {rank}, the model's lora_rank is {cfg.lora_rank}; build "
                                f"the model with DifixConfig(lora_rank={rank})")
    targets = info.get("vae_lora_target_modules")
    if targets is not None and set(targets) != set(model.lora_layers()):
        ours = set(model.lora_layers())
        extra, lacking = sorted(set(targets) - ours), sorted(ours - set(targets))
        raise DifixWeightsError(f"{path}: vae_lora_target_modules differ from the model's LoRA modules "
                                f"(only in the file: {_listing(extra)}; only in the model: {_listing(lacking)})")
    files = dict(info["files"])
    if base is not None:
        base_unet, base_vae, base_files = _base_weights(base, model)
        unet_sd = {**base_unet, **unet_sd}
        vae_sd = {**base_vae, **vae_sd}
        files.update(base_files)
    expected = official_key_shapes(model)
    problems = []
    for part, state in (("unet", unet_sd), ("vae", vae_sd)):
        want = expected[part]
        missing = [k for k in want if k not in state]
        unexpected = [k for k in state if k not in want]
        wrong = [f"{k} {tuple(state[k].shape)} (expected {want[k]})" for k in want
                 if k in state and tuple(state[k].shape) != want[k]]
        if missing:
            problems.append(f"{part}: missing {len(missing)}: {_listing(missing)}")
        if unexpected:
            problems.append(f"{part}: unexpected {len(unexpected)}: {_listing(unexpected)}")
        if wrong:
            problems.append(f"{part}: wrong shape {len(wrong)}: {_listing(wrong)}")
    if problems:
        hint = ("; a training checkpoint holds only the LoRA and skip weights of the VAE: pass base=<SD-Turbo "
                "diffusers directory>" if not path.is_dir() and base is None else
                "; check that the checkpoint and DifixConfig describe the same model (sd_turbo() for nvidia/difix*)")
        raise DifixWeightsError(f"{path} does not match the Difix layout of this config: " + "; ".join(problems)
                                + hint)
    model.unet.load_state_dict({k: v.to(torch.float32) for k, v in unet_sd.items()}, strict=True)
    model.vae.load_state_dict({k: v.to(torch.float32) for k, v in vae_sd.items()}, strict=True)
    return {"path": str(path.resolve()), "files": files}


# ----------------------------------------------------------------------------------------------------
# Prompt embedding
# ----------------------------------------------------------------------------------------------------


def encode_prompt(directory: Path, prompt: str = DEFAULT_PROMPT, text_tokens: int = 77) -> np.ndarray:
    """``[1, text_tokens, D]`` float32: the CLIP ``last_hidden_state`` of ``prompt`` padded to ``text_tokens``
    (``padding="max_length"``, truncated, no attention mask), as Difix's ``model.py`` and ``encode_prompt`` of
    its pipeline, from ``directory/text_encoder`` (CLIPTextModel, safetensors) and ``directory/tokenizer``."""
    from transformers import CLIPTextModel, CLIPTokenizer

    directory = Path(directory)
    for sub in ("text_encoder", "tokenizer"):
        if not (directory / sub).is_dir():
            raise FileNotFoundError(f"{directory}: no {sub}/ folder to encode the prompt with (use the "
                                    f"nvidia/difix_ref or stabilityai/sd-turbo directory, or pass precomputed "
                                    f"prompt embeddings)")
    tokenizer = CLIPTokenizer.from_pretrained(str(directory / "tokenizer"))
    text_encoder = CLIPTextModel.from_pretrained(str(directory / "text_encoder"), dtype=torch.float32,
                                                 use_safetensors=True).eval()
    ids = tokenizer(prompt, max_length=text_tokens, padding="max_length", truncation=True,
                    return_tensors="pt").input_ids
    with torch.no_grad():
        emb = text_encoder(ids)[0]
    return emb.float().numpy().astype(np.float32)


def random_prompt_embeds(config: DifixConfig, seed: int) -> np.ndarray:
    """Seeded standard-normal stand-in for the prompt embedding of random-weight models."""
    rng = np.random.RandomState(seed + 4)
    return rng.standard_normal((1, config.text_tokens, config.cross_attention_dim)).astype(np.float32)


# ----------------------------------------------------------------------------------------------------
# ONNX export
# ----------------------------------------------------------------------------------------------------


class _NoReferenceGraph(nn.Module):
    """Graph signature of the plain (``reference_mixing=False``) model: no reference input."""

    def __init__(self, model: DifixRefinerModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, image, prompt_embeds, latent_noise):
        return self.model(image, None, prompt_embeds, latent_noise)


def graph_inputs(config: DifixConfig) -> list[str]:
    return [n for n in INPUTS if n != "reference" or config.reference_mixing]


def export_refiner(out_dir: Path, config: DifixConfig, weights: Path | None = None, seed: int = 0, *,
                   base: Path | None = None, prompt_embeds: Path | np.ndarray | None = None,
                   prompt: str = DEFAULT_PROMPT) -> Path:
    """Export Difix as graph ``refiner`` plus ``prompt_embeds.npy`` and the manifest (kind ``refiner``,
    architecture ``difix``). Returns ``out_dir``.

    Graph inputs: ``image`` and ``reference`` ``[B, 3, H, W]`` in [-1, 1] (no ``reference`` when
    ``config.reference_mixing`` is False), ``prompt_embeds`` ``[1, text_tokens, D]``, ``latent_noise``
    ``[B, V, latent_channels, H/f, W/f]`` (f = ``vae_scale_factor``); output ``refined`` ``[B, 3, H, W]`` in
    [-1, 1]. B is 1 (the role refines one view per call, as the official pipeline; a dynamic batch makes the
    export much slower); H and W are dynamic multiples of ``config.size_multiple`` up to ``MAX_SIDE`` (2048).
    The LoRA adapters are merged into the decoder weights before export (exact).

    Weights: random from ``seed`` (LoRA ``lora_B`` randomised, see ``randomize_adapters``) unless ``weights``
    is an official checkpoint (``load_difix_weights``, with ``base`` for training checkpoints). Prompt
    embedding: ``prompt_embeds`` (array or ``.npy``) if given, else ``prompt`` encoded with the text encoder of
    the checkpoint directory or of ``base``; random weights get a seeded random embedding."""
    from torch.export import Dim

    from navcrafter.models.runtime import onnxio

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / onnxio.MANIFEST).unlink(missing_ok=True)  # a directory with a manifest is a finished export
    torch.manual_seed(seed)
    model = DifixRefinerModel(config).eval()
    if weights is None:
        randomize_adapters(model, seed)
        weights_info: dict[str, Any] = {"source": "random", "seed": int(seed)}
    else:
        weights = Path(weights)
        report = load_difix_weights(model, weights, base=base)
        weights_info = {"source": "checkpoint", "path": report["path"], "files": report["files"]}
        if weights.is_file():
            weights_info["sha256"] = report["files"][weights.name]
    if prompt_embeds is not None:
        emb = np.load(prompt_embeds) if not isinstance(prompt_embeds, np.ndarray) else prompt_embeds
        text = {"source": "given", "prompt": None}
    elif weights is None:
        emb = random_prompt_embeds(config, seed)
        text = {"source": "random", "prompt": None}
    else:
        holder = next((d for d in (weights if weights.is_dir() else None, base)
                       if d is not None and (Path(d) / "text_encoder").is_dir()), None)
        if holder is None:
            raise FileNotFoundError(f"no text encoder to embed the prompt {prompt!r}: {weights} has no text_encoder/"
                                    f" and no SD-Turbo base directory was given; pass base=... or prompt_embeds=...")
        emb = encode_prompt(Path(holder), prompt, config.text_tokens)
        text = {"source": "text_encoder", "prompt": prompt, "path": str(Path(holder).resolve())}
    emb = np.ascontiguousarray(emb, dtype=np.float32)
    want = (1, config.text_tokens, config.cross_attention_dim)
    if emb.shape != want:
        raise ValueError(f"prompt embeddings have shape {emb.shape}, the model needs {want}")

    model.merge_lora_()
    m, f, v = config.size_multiple, config.vae_scale_factor, config.num_views
    # H = rows * size_multiple <= MAX_SIDE (keeps diffusers' Upsample2D size check `numel * 2 > 2**31` false)
    rows, cols = Dim("rows", min=1, max=MAX_SIDE // m), Dim("cols", min=1, max=MAX_SIDE // m)
    image = torch.rand(1, 3, 2 * m, 3 * m) * 2 - 1
    example = {"image": image, "reference": torch.rand_like(image) * 2 - 1,
               "prompt_embeds": torch.from_numpy(emb),
               "latent_noise": torch.randn(1, v, config.latent_channels, 2 * m // f, 3 * m // f)}
    dims = {"image": {2: m * rows, 3: m * cols}, "reference": {2: m * rows, 3: m * cols}, "prompt_embeds": None,
            "latent_noise": {3: (m // f) * rows, 4: (m // f) * cols}}
    names = graph_inputs(config)
    module = model if config.reference_mixing else _NoReferenceGraph(model)
    info = onnxio.export_graph(module.eval(), tuple(example[n] for n in names), out_dir / f"{GRAPH}.onnx",
                               input_names=names, output_names=[OUTPUT],
                               dynamic_shapes=tuple(dims[n] for n in names))
    info.notes = (f"image/reference: RGB in [-1, 1], H and W multiples of {m}; latent_noise: N(0, 1) of the "
                  f"VAE posterior sample (zeros = mean); refined: input view in [-1, 1]")
    np.save(out_dir / PROMPT_FILE, emb)
    io = {"inputs": names, "output": OUTPUT, "input_range": [-1.0, 1.0], "output_range": [-1.0, 1.0],
          "size_multiple": m, "vae_scale_factor": f, "num_views": v, "latent_channels": config.latent_channels,
          "prompt_file": PROMPT_FILE, "text": text, "timestep": config.timestep, "lora": "merged into the decoder"}
    onnxio.write_manifest(out_dir, kind=KIND, architecture=ARCHITECTURE, config=config.to_dict(),
                          weights=weights_info, graphs={GRAPH: info}, extra_files=[PROMPT_FILE], extra={"io": io})
    return out_dir

"""``DifixRefinerModel``: SD-Turbo's VAE encoder, UNet (one step at t = 199) and VAE decoder with Difix's skips,
LoRA and reference mixing."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from navcrafter.models.refiner.difix.modules import (
    LoraLayer,
    ReferenceMixingAttnProcessor,
    _set_submodule,
    lora_target_modules,
    skip_channels,
)

if TYPE_CHECKING:
    from navcrafter.models.refiner.difix.config import DifixConfig


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

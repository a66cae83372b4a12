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

Modules (the import path ``navcrafter.models.refiner.difix`` re-exports their public names): ``config``
(``DifixConfig``, names), ``modules`` (LoRA layers, skip channels, reference mixing), ``model``
(``DifixRefinerModel``), ``weights`` (official layouts, ``load_difix_weights`` / ``save_difix_weights``; reading and
checking files is ``models.checkpoints``'s), ``prompt`` (``encode_prompt``) and ``export`` (``export_refiner``).
"""

from __future__ import annotations

from navcrafter.models.refiner.difix.config import (
    ARCHITECTURE,
    DEFAULT_PROMPT,
    GRAPH,
    INPUTS,
    KEYS_DIR,
    KIND,
    LORA_ADAPTER,
    LORA_TARGET_SUFFIXES,
    MAX_SIDE,
    OFFICIAL_KEYS_SD_TURBO,
    OUTPUT,
    PROMPT_FILE,
    UNET_FILE,
    VAE_FILE,
    DifixConfig,
    DifixWeightsError,
)
from navcrafter.models.refiner.difix.export import (
    export_refiner,
    graph_inputs,
)
from navcrafter.models.refiner.difix.model import (
    DifixRefinerModel,
    randomize_adapters,
)
from navcrafter.models.refiner.difix.modules import (
    LoraLayer,
    ReferenceMixingAttnProcessor,
    lora_target_modules,
    skip_channels,
)
from navcrafter.models.refiner.difix.prompt import (
    encode_prompt,
    random_prompt_embeds,
)
from navcrafter.models.refiner.difix.weights import (
    load_difix_weights,
    official_key_shapes,
    official_state_dicts,
    read_official_key_list,
    save_difix_weights,
    write_official_key_list,
)

__all__ = [
    "ARCHITECTURE",
    "KIND",
    "GRAPH",
    "DEFAULT_PROMPT",
    "PROMPT_FILE",
    "LORA_ADAPTER",
    "LORA_TARGET_SUFFIXES",
    "UNET_FILE",
    "VAE_FILE",
    "KEYS_DIR",
    "OFFICIAL_KEYS_SD_TURBO",
    "INPUTS",
    "OUTPUT",
    "MAX_SIDE",
    "DifixWeightsError",
    "DifixConfig",
    "LoraLayer",
    "skip_channels",
    "lora_target_modules",
    "ReferenceMixingAttnProcessor",
    "DifixRefinerModel",
    "randomize_adapters",
    "official_state_dicts",
    "official_key_shapes",
    "read_official_key_list",
    "write_official_key_list",
    "save_difix_weights",
    "load_difix_weights",
    "encode_prompt",
    "random_prompt_embeds",
    "graph_inputs",
    "export_refiner",
]

"""Camera-controlled Wan2.1 DiT (NavCrafter's multi-stage camera control) on top of diffusers' Wan.

The base model is diffusers' ``WanTransformer3DModel`` (Wan2.1 I2V layout), used as-is: its rope, patch
embedding, condition embedder, blocks, output norm and projection. ``CameraControlledWan`` wraps it and
adds four zero-initialised control paths, so an untrained wrapper returns exactly the base output:

1. **Camera adapter A (dual-branch injection).** A 3D-conv encoder maps per-pixel Plücker rays
   ``[B, 6, T, 8h, 8w]`` to tokens ``x_c [B, L, D]`` on the DiT's token grid (``L = F * h/2 * w/2``).
   In every block ``i``: ``hidden += P_i(x_c)`` before the block, and inside the block's self-attention
   ``attn_out += S_i(x_c)`` (after ``to_out``, before the block's gate). ``P_i``/``S_i`` (``pre_proj`` /
   ``attn_proj``) are low-rank ``D -> r -> D`` (``projection_rank`` ``r``, capped at ``D``; the down
   projection random, the up projection zero-initialised): a full ``Linear(D, D)`` pair per block is ~2.1 B
   parameters on Wan2.1-I2V-14B, ~13 % of the base (``control_parameter_counts``). ``projection_rank = 0``
   is the full zero-initialised ``Linear(D, D)`` of format-version-1 weights.
2. **LoRA control.** A lightweight 3D-conv encoder maps the same Plücker rays to ``x_l [B, L, r_in]``; in
   every block's self-attention ``Q' = Q + α·U_q(D_q x_l)`` (same for K and V) on the projection outputs,
   before the q/k RMS norms and rope. ``U_*`` are zero-initialised; ``α`` (``lora_scale``) is an input so
   the sampler can choose it (the paper uses 0.7).
3. **Reference-frame attention.** A set of latent frames ``S`` (always including frame 0) are *reference
   frames*: their **clean** latents are patch-embedded (``ref_embedding``, initialised from the base patch
   embedding as "a known clean frame") into reference tokens placed at their frame's rope position, and
   every video token attends to them in a second, decoupled attention inside each self-attention::

       r_i     = ref_tokens + P_i(x_c)[S]                     (camera of the reference frame)
       K_r,V_r = norm_k(W_k LN(r_i)), W_v LN(r_i)             (the block's own projections, rope at S)
       attn    = SDPA(Q, K, V) + [SDPA(Q, K_img, V_img)] + g_i ⊙ SDPA(Q, K_r, V_r)

   with a per-channel gate ``g_i`` initialised to zero (a decoupled branch, like Wan's image branch,
   keeps the base attention's softmax untouched, which concatenating keys would not). During training
   (``model.train()``) ``S`` is ``{0} ∪`` a random subset of ``num_reference_frames - 1`` other latent
   frames drawn from a seeded generator, and the clean latents come from ``reference_latents`` (the
   training loop passes the clean video latents). At inference ``S = inference_reference_frames`` (default
   ``(0,)``, baked into an exported graph) and the clean latents are the I2V conditioning latents
   (channels 20:36 of ``hidden_states``), whose frame 0 is the encoded conditioning image.
   **Extra reference frames** (``image_reference [B, 16, R, h, w]``, clean latents of views outside the clip,
   e.g. the scene's input photo when a clip starts elsewhere, with their rays ``image_reference_plucker
   [B, 6, R, 8h, 8w]`` in the clip's Plücker frame: ``models.camera.cameras.clip_relative_rays``) join the
   same reference set: patch-embedded with ``ref_embedding``, their camera tokens are the adapter run on each
   frame's rays as a one-frame clip (``x_c`` of that frame), and their rope is the one of latent frame 0 (a
   known clean frame at the start of the clip, like the I2V conditioning frame: where the view is comes from
   its camera tokens, not from a time position it does not have).
4. **Render conditioning.** ``cond [B, cond_channels, F, h, w]`` enters through an extended patch
   embedding: ``patch_embedding(hidden_states) + cond_embedding(cond)``, which equals one Conv3d over the
   concatenated channels whose new input channels are zero-initialised. The default ``cond_channels = 20``
   is ``16`` VAE latents of the current point cloud rendered along the trajectory + ``4`` visibility-mask
   channels packed exactly like Wan's I2V mask (``pack_visibility_mask``): channel ``c`` of latent frame
   ``k`` is the (8×8 average-pooled) visibility of video frame ``4k - 3 + c`` (frame 0 for all four
   channels of latent frame 0).

**Plücker convention** (``CameraControlConfig.plucker_convention``, default ``"relative"``): rays are computed
from the clip's poses made relative to its first camera and scale-normalised by the clip's largest translation
(CameraCtrl-style, as RealEstate10K/DL3DV training clips are), then the true Plücker line of each pixel ray;
``"ray"`` and ``"paper"`` (the paper's literal ``d = normalise(RK^-1[u,v,1] + t)``) on absolute world poses stay
selectable (see ``models.camera.cameras.plucker_rays``). The convention is saved with the weights and recorded in
an exported synthesizer's manifest.

Temporal alignment follows the Wan VAE: latent frame 0 is video frame 0, latent frame ``k ≥ 1`` covers video
frames ``4k-3 .. 4k``; so ``T = 4(F - 1) + 1``. Both Plücker encoders repeat frame 0 three times in front
(``4F`` frames) and patchify with stride 4 in time.

Weights: the base comes from a diffusers-format directory; the control weights are one safetensors file
plus a JSON config (``save_camera_control`` / ``load_camera_control``), never pickles. Format version 2 (low-rank
projections, ``projection_rank`` in the config); version-1 files load as ``projection_rank = 0`` with the
convention they record.
The whole wrapper exports to ONNX (``export_dit``) with dynamic batch, frames, height, width and number of extra
reference frames.

Modules (the import path ``navcrafter.models.synthesis.camcontrol`` re-exports their public names):
``config`` (``CameraControlConfig``, base configs, file and graph names), ``conditioning`` (frame counts, the packed
visibility mask, render condition, reference-frame selection), ``modules`` (adapter, LoRA encoder, per-block
projections), ``attention`` (``CameraControlAttnProcessor``), ``model`` (``CameraControlledWan`` and its
constructors), ``weights`` (Wan base loader, camera-control save/load; the strict layout check is
``models.checkpoints``'s) and ``export`` (``export_dit``).
"""

from __future__ import annotations

from navcrafter.models.synthesis.camcontrol.attention import (
    CameraControlAttnProcessor,
)
from navcrafter.models.synthesis.camcontrol.conditioning import (
    latent_frames,
    make_render_condition,
    pack_visibility_mask,
    plucker_to_tensor,
    select_reference_frames,
    video_frames,
)
from navcrafter.models.synthesis.camcontrol.config import (
    CONTROL_CONFIG,
    CONTROL_FORMAT,
    CONTROL_FORMAT_VERSION,
    CONTROL_WEIGHTS,
    DIT_INPUTS,
    DIT_OUTPUTS,
    LATENT_CHANNELS,
    READABLE_FORMAT_VERSIONS,
    TEXT_TOKENS,
    TINY_I2V_CONFIG,
    TRAINING_LORA_SCALE,
    VAE_STRIDE,
    WAN_1_3B_I2V_CONFIG,
    WAN_14B_I2V_CONFIG,
    CameraControlConfig,
    CameraControlWeightsError,
    tiny_camera_config,
    wan_1_3b_camera_config,
    wan_14b_camera_config,
)
from navcrafter.models.synthesis.camcontrol.export import (
    example_inputs,
    export_dit,
)
from navcrafter.models.synthesis.camcontrol.model import (
    CameraControlledWan,
    build_camera_wan,
    randomize_camera_control,
    tiny_camera_wan,
)
from navcrafter.models.synthesis.camcontrol.modules import (
    CameraAdapter,
    CameraControl,
    CameraControlBlock,
    LoRAControlEncoder,
    control_parameter_counts,
)
from navcrafter.models.synthesis.camcontrol.weights import (
    load_camera_control,
    load_wan_transformer,
    read_camera_control_config,
    save_camera_control,
)

__all__ = [
    "VAE_STRIDE",
    "LATENT_CHANNELS",
    "TEXT_TOKENS",
    "CONTROL_WEIGHTS",
    "CONTROL_CONFIG",
    "CONTROL_FORMAT",
    "CONTROL_FORMAT_VERSION",
    "READABLE_FORMAT_VERSIONS",
    "DIT_INPUTS",
    "DIT_OUTPUTS",
    "TINY_I2V_CONFIG",
    "WAN_1_3B_I2V_CONFIG",
    "WAN_14B_I2V_CONFIG",
    "CameraControlWeightsError",
    "TRAINING_LORA_SCALE",
    "CameraControlConfig",
    "tiny_camera_config",
    "wan_1_3b_camera_config",
    "wan_14b_camera_config",
    "latent_frames",
    "video_frames",
    "pack_visibility_mask",
    "make_render_condition",
    "plucker_to_tensor",
    "select_reference_frames",
    "CameraAdapter",
    "LoRAControlEncoder",
    "CameraControlBlock",
    "CameraControl",
    "control_parameter_counts",
    "CameraControlAttnProcessor",
    "load_wan_transformer",
    "save_camera_control",
    "read_camera_control_config",
    "load_camera_control",
    "CameraControlledWan",
    "build_camera_wan",
    "tiny_camera_wan",
    "randomize_camera_control",
    "example_inputs",
    "export_dit",
]

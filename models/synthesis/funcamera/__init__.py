"""``fun-camera``: Wan2.1-Fun-V1.1-Control-Camera (aigc-apps/VideoX-Fun, Apache-2.0) on diffusers' Wan DiT.

A second synthesizer model beside NavCrafter's own camera control (``camcontrol``), built from the official
VideoX-Fun code's definitions (read at upstream commit 804a425, 2026-05-12; file paths below are in that repository):

* **Architecture** (``videox_fun/models/wan_transformer3d.py`` ``WanTransformer3DModel`` with
  ``add_control_adapter=True``; the adapter is ``videox_fun/models/wan_camera_adapter.py`` ``SimpleAdapter``): a
  Wan2.1 I2V DiT (``model_type="i2v"``: CLIP ``img_emb`` and the decoupled image cross-attention) whose patch
  embedding takes ``in_dim = 32`` channels, plus one camera adapter whose output is **added to the patch embedding's
  output** (``x = patch_embedding(x) + control_adapter(y_camera)``, before flattening to tokens) and nowhere else.
  Here the DiT is diffusers' ``WanTransformer3DModel`` (same maths as the official module; the key mapping is
  diffusers' own ``convert_wan_transformer_to_diffusers``) and the adapter is ``FunCameraAdapter``.
* **Adapter** (``SimpleAdapter``): per latent frame, ``PixelUnshuffle(8)`` of the ``24``-channel packed rays
  (``24·64 = 1536`` channels at the latent grid), ``Conv2d(1536, D, kernel 2, stride 2)`` onto the token grid, then
  one residual block ``x + conv2(relu(conv1(x)))`` (3x3 convs, no activation after the sum).
* **Input channels** (``videox_fun/pipeline/pipeline_wan_fun_control.py``, ``scripts/wan2.1_fun/train_control.py``):
  ``hidden_states = [noisy latents (16) | start-image latents (16)]``: the start image VAE-encoded as a one-frame
  video into latent frame 0, **all other latent frames exactly zero** (not VAE latents of black frames), and no
  I2V mask (confirmed by the maintainers in VideoX-Fun issue #409: "control camera uses no mask, only the first
  frame"). The CLIP features of the start image go to ``img_emb`` as in Wan I2V.
* **Temporal packing** (the pipeline's ``control_camera_latents``): rays ``[B, 6, T, H, W]`` at pixel resolution,
  frame 0 repeated 4 times in front (``4F`` frames), grouped by 4 consecutive frames; channel ``4c + j`` of latent
  frame ``k`` is Plücker channel ``c`` of frame ``j`` of group ``k`` (``fun_camera_pack``).
* **Plücker embedding** (``videox_fun/data/utils.py`` ``process_pose_file`` / ``process_pose_params``,
  ``get_relative_pose``, ``ray_condition``, ``Camera``; copied there from CameraCtrl): ``fun_camera_plucker``.

Weights: ``load_fun_camera(directory)`` reads the official transformer folder (``config.json`` +
``diffusion_pytorch_model.safetensors``, or its sharded index) with strict key and shape checks against the
architecture its ``config.json`` describes; ``save_fun_camera`` writes the same layout back. The layout of the
published 1.3B checkpoint is committed in ``keys/fun_camera_1_3b.json`` (generated from the official module, see
its header). ``export_fun_camera_dit`` exports the DiT to ONNX; the sampler is ``pipeline.sample_video`` (manifest
``config.condition_layout = "fun-camera"``).

Modules (the import path ``navcrafter.models.synthesis.funcamera`` re-exports their public names): ``config``
(``FunCameraConfig``, file, manifest and graph names), ``plucker`` (the Plücker embedding and its packing), ``model``
(``FunCameraWan``, its adapter and constructors), ``weights`` (official layout <-> ours, ``load_fun_camera`` /
``save_fun_camera``, ``init_navcrafter_from_fun_camera``; the strict layout check and the safetensors shards are
``models.checkpoints``'s) and ``export`` (``export_fun_camera_dit``).
"""

from __future__ import annotations

from navcrafter.models.synthesis.funcamera.config import (
    ARCHITECTURE,
    CONDITION_LAYOUT,
    FUN_DIT_INPUTS,
    FUN_DIT_OUTPUTS,
    KEY_LIST_1_3B,
    LATENT_CHANNELS,
    MODEL_NAME,
    OFFICIAL_CONFIG,
    OFFICIAL_INDEX,
    OFFICIAL_WEIGHTS,
    PLUCKER_CHANNELS,
    PLUCKER_CONVENTION,
    TEXT_TOKENS,
    VAE_STRIDE,
    FunCameraConfig,
    FunCameraWeightsError,
)
from navcrafter.models.synthesis.funcamera.export import (
    export_fun_camera_dit,
    fun_example_inputs,
)
from navcrafter.models.synthesis.funcamera.model import (
    FunCameraAdapter,
    FunCameraWan,
    build_fun_camera,
    pixel_unshuffle,
    tiny_fun_camera,
)
from navcrafter.models.synthesis.funcamera.plucker import (
    fun_camera_pack,
    fun_camera_plucker,
    fun_camera_plucker_from_re10k,
    fun_camera_relative_poses,
)
from navcrafter.models.synthesis.funcamera.weights import (
    _transformer_dir,
    check_layout,
    fun_camera_state_dict_official,
    init_navcrafter_from_fun_camera,
    load_fun_camera,
    official_layout,
    official_to_ours,
    ours_to_official,
    read_fun_camera_config,
    read_key_list,
    save_fun_camera,
)

__all__ = [
    "MODEL_NAME",
    "ARCHITECTURE",
    "PLUCKER_CONVENTION",
    "CONDITION_LAYOUT",
    "OFFICIAL_CONFIG",
    "OFFICIAL_WEIGHTS",
    "OFFICIAL_INDEX",
    "KEY_LIST_1_3B",
    "VAE_STRIDE",
    "LATENT_CHANNELS",
    "TEXT_TOKENS",
    "PLUCKER_CHANNELS",
    "FUN_DIT_INPUTS",
    "FUN_DIT_OUTPUTS",
    "FunCameraWeightsError",
    "FunCameraConfig",
    "fun_camera_relative_poses",
    "fun_camera_plucker",
    "fun_camera_plucker_from_re10k",
    "fun_camera_pack",
    "pixel_unshuffle",
    "FunCameraAdapter",
    "FunCameraWan",
    "build_fun_camera",
    "tiny_fun_camera",
    "official_to_ours",
    "ours_to_official",
    "official_layout",
    "read_key_list",
    "check_layout",
    "_transformer_dir",
    "read_fun_camera_config",
    "load_fun_camera",
    "fun_camera_state_dict_official",
    "save_fun_camera",
    "init_navcrafter_from_fun_camera",
    "fun_example_inputs",
    "export_fun_camera_dit",
]

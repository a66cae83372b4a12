"""VGGT (Visual Geometry Grounded Transformer) geometry network: torch module, checkpoint I/O, ONNX export.

Architecture of facebookresearch/vggt (VGGT-1B), re-implemented here from its published description and
checkpoint layout:

* **Patch embedding**: a DINOv2 ViT-L/14 with 4 registers (transformers' ``Dinov2WithRegisters*``
  modules), whose final-norm patch tokens start the sequence of every frame.
* **Aggregator**: per frame, one camera token and 4 register tokens (the first frame has its own
  learned pair, all other frames share a second pair) are prepended to the patch tokens; then
  ``depth`` rounds of *frame* attention (tokens of one frame) followed by *global* attention (tokens of
  all frames). Both use 2D rotary position embeddings (special tokens at position 0, patch ``(y, x)``
  at ``(y + 1, x + 1)``) and LayerNorm qk-normalisation. The output of round ``i`` is the concatenation
  ``[frame_i, global_i]`` (width ``2 * embed_dim``).
* **Camera head**: the camera tokens of the last round go through a 4-block trunk four times
  (adaLN-modulated by the embedding of the previous estimate) and predict ``pose_enc`` [B, S, 9] =
  translation (3), quaternion ``xyzw`` (4), field of view ``(fov_h, fov_w)`` in radians (2): the
  world-to-camera pose in the first camera's frame (``absT_quaR_FoV``). The FoV goes through a ReLU.
* **DPT heads** on rounds ``dpt_layers``: depth (``exp``) + confidence (``1 + exp``), and world points
  (``sign(x) * expm1(|x|)``) + confidence (``1 + exp``), at the input resolution.

The track head of the official model is not built; its checkpoint entries are ignored (and reported).

Our module tree mirrors the official one (same parameter names), except for

* the DINOv2 encoder (``aggregator.patch_embed``), which uses transformers' module names with separate
  q/k/v projections, and
* the two DPT heads, evaluated as one module ``dpt_heads`` with their weights stacked along the channel
  axis and grouped convolutions (half the ONNX graph, the same arithmetic per head).

``vggt_state_dict_official`` and ``vggt_state_dict_from_official`` translate between the layouts
(fusing/splitting ``qkv``, splitting/stacking the heads); the loader checks every name and shape first.

Export notes (``torch.onnx.export(dynamo=True)`` with dynamic S, H, W): RoPE positions and the DPT
sin/cos embeddings are built from ``arange`` over the symbolic sizes (no Python floats of sizes, no
shape-dependent branches); the DINOv2 position table is always resampled (antialiased bicubic, which
exports as ONNX ``Resize(cubic, antialias=1)``); the first/other-frame special tokens are gathered with
an index instead of an ``S - 1`` expand.

Modules (the import path ``navcrafter.models.geometry.vggt`` re-exports their public names): ``config``
(``VGGTConfig``), ``modules`` (blocks, RoPE, DINOv2 patch embedding, aggregator), ``heads`` (camera head, DPT heads),
``model`` (``VGGT``), ``weights`` (official layout <-> ours, ``load_vggt_weights``; reading and checking files is
``models.checkpoints``'s) and ``export`` (``VGGTExportWrapper``, ``export_geometry``).
"""

from __future__ import annotations

from navcrafter.models.geometry.vggt.config import (
    IGNORED_PREFIXES,
    KEY_LIST_1B,
    OUTPUT_NAMES,
    VGGTConfig,
)
from navcrafter.models.geometry.vggt.export import (
    VGGTExportWrapper,
    export_geometry,
)
from navcrafter.models.geometry.vggt.heads import (
    DPT_HEADS,
    CameraHead,
    DPTHeads,
    FeatureFusionBlock,
    ResidualConvUnit,
    sincos_constants,
    uv_sincos_embed,
)
from navcrafter.models.geometry.vggt.model import (
    VGGT,
)
from navcrafter.models.geometry.vggt.modules import (
    Aggregator,
    Attention,
    Block,
    DinoPatchEmbed,
    LayerScale,
    Mlp,
    apply_rope,
    rope_frequencies,
    rope_rotation,
    rope_tables,
)
from navcrafter.models.geometry.vggt.weights import (
    VGGTWeightsError,
    check_official_layout,
    load_vggt_weights,
    official_layout,
    read_checkpoint,
    read_key_list,
    save_official_safetensors,
    vggt_state_dict_from_official,
    vggt_state_dict_official,
)

__all__ = [
    "OUTPUT_NAMES",
    "IGNORED_PREFIXES",
    "KEY_LIST_1B",
    "VGGTConfig",
    "LayerScale",
    "Mlp",
    "rope_rotation",
    "rope_frequencies",
    "rope_tables",
    "apply_rope",
    "Attention",
    "Block",
    "DinoPatchEmbed",
    "Aggregator",
    "CameraHead",
    "sincos_constants",
    "uv_sincos_embed",
    "ResidualConvUnit",
    "FeatureFusionBlock",
    "DPT_HEADS",
    "DPTHeads",
    "VGGT",
    "VGGTExportWrapper",
    "export_geometry",
    "VGGTWeightsError",
    "vggt_state_dict_official",
    "vggt_state_dict_from_official",
    "official_layout",
    "read_key_list",
    "read_checkpoint",
    "check_official_layout",
    "load_vggt_weights",
    "save_official_safetensors",
]

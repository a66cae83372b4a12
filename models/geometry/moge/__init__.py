"""MoGe-2-architecture monocular geometry network (torch), checkpoint I/O, pre/postprocessing, ONNX export.

The network follows the published MoGe-2 model (microsoft/MoGe, ``moge/model/v2.py``; preset
``MoGe2Config.vitl_normal()`` = ``Ruicheng/moge-2-vitl-normal``):

- a DINOv2 ViT encoder (transformers' ``Dinov2Model`` modules). The patch tokens of a few intermediate
  blocks are layer-normed, projected by 1x1 convolutions and summed into one feature map at the token grid
  (H/14, W/14); the layer-normed class token of the last of those blocks feeds the metric scale head;
- a convolutional neck over a 5-level pyramid (token grid x1, x2, x4, x8, x16): level 0 is the encoder
  feature map plus 2 UV channels, levels 1-4 are UV channels only (the normalised view-plane coordinates);
- heads sharing the neck's pyramid: points (3), normal (3, optional) and mask (1), each read at the finest
  level and bilinearly resized to the input size, and an MLP on the class token for the metric scale.

Output remaps (as official): points use ``remap_output`` ("exp" for MoGe-2: ``z = exp(z')``, ``xy = xy' z``),
normals are L2-normalised, the mask is a probability (``sigmoid``), ``metric_scale = exp(mlp(cls))``.

**The input resize is outside the graph.** The official ``forward(image, num_tokens)`` resizes the input
(bilinear, antialiased) to a token grid chosen from ``num_tokens`` inside the network. Here the caller does
it: ``preprocess_image`` picks the grid exactly like the official code (``token_grid``) and resizes; the graph
takes the already-resized image (H, W multiples of 14, any size, float RGB in [0, 1]) and the ORIGINAL
image's aspect ratio (width / height), from which the UV channels are built as official
(``normalized_view_plane_uv(..., aspect_ratio)``: the token grid's own aspect differs by its rounding). The
ImageNet mean/std normalisation stays inside the graph, as in the official encoder (buffers
``encoder.image_mean/std``).

**The head maps are resized once, outside the graph.** The graph returns the heads' raw maps at their own
resolution (``2**(levels-1)`` x the token grid) and the metric scale; ``head_maps_to_size`` resizes them
(bilinear, no antialias) straight to the input resolution and only then remaps them (points ``exp``, normal
L2, mask ``sigmoid``), in the official order; ``postprocess`` then does what the official ``infer()`` does
after the network (focal and z-shift recovery, metric scale, mask). ``infer_torch`` and ``OnnxMonoDepth``
run this same pipeline. The positional-embedding interpolation reproduces the official (non-ONNX-mode)
bicubic resampling with DINOv2's 0.1 offset exactly, as a traceable separable matrix product.

Checkpoints use the official key layout (fused ``attn.qkv``, ``ls1.gamma``, ``pos_embed`` ...);
``load_moge2_weights`` / ``moge2_state_dict_official`` map it to and from the modules here. The official
layout of the full-size model is committed in ``keys/moge2_vitl_normal.txt``.

Modules (the import path ``navcrafter.models.geometry.moge`` re-exports their public names): ``config``
(``MoGe2Config``), ``modules`` (neck, heads, encoder, UV channels), ``model`` (``MoGe2``), ``weights`` (official
layout <-> ours, ``load_moge2_weights``; reading and checking files is ``models.checkpoints``'s), ``processing``
(``preprocess_image``, ``head_maps_to_size``, ``postprocess``, ``infer_torch``) and ``export``
(``export_monodepth``).
"""

from __future__ import annotations

from navcrafter.models.geometry.moge.config import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    KEYS_DIR,
    OFFICIAL_KEYS_VITL_NORMAL,
    MoGe2Config,
    MoGeWeightsError,
)
from navcrafter.models.geometry.moge.export import (
    export_monodepth,
)
from navcrafter.models.geometry.moge.model import (
    MoGe2,
)
from navcrafter.models.geometry.moge.modules import (
    _view_plane_uv,
)
from navcrafter.models.geometry.moge.processing import (
    MoGe2Result,
    head_maps_to_size,
    infer_torch,
    num_tokens_for_level,
    outputs_to_result,
    postprocess,
    preprocess_image,
    recover_focal_shift,
    remap_points,
    token_grid,
)
from navcrafter.models.geometry.moge.weights import (
    _read_checkpoint,
    load_moge2,
    load_moge2_weights,
    moge2_state_dict_official,
    official_key_shapes,
    read_official_key_list,
    save_moge2_weights,
)

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "KEYS_DIR",
    "OFFICIAL_KEYS_VITL_NORMAL",
    "MoGeWeightsError",
    "MoGe2Config",
    "_view_plane_uv",
    "MoGe2",
    "moge2_state_dict_official",
    "official_key_shapes",
    "read_official_key_list",
    "_read_checkpoint",
    "load_moge2_weights",
    "save_moge2_weights",
    "load_moge2",
    "num_tokens_for_level",
    "token_grid",
    "preprocess_image",
    "recover_focal_shift",
    "remap_points",
    "head_maps_to_size",
    "outputs_to_result",
    "infer_torch",
    "MoGe2Result",
    "postprocess",
    "export_monodepth",
]

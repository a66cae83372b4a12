"""ONNX export of MoGe-2 into a monodepth model directory (``export_monodepth``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import torch

from navcrafter.models.geometry.moge.model import MoGe2
from navcrafter.models.geometry.moge.processing import num_tokens_for_level
from navcrafter.models.geometry.moge.weights import load_moge2_weights
from navcrafter.models.runtime import onnxio

if TYPE_CHECKING:
    from navcrafter.models.geometry.moge.config import MoGe2Config


def export_monodepth(out_dir: Path, config: MoGe2Config, weights: Path | None = None, seed: int = 0) -> Path:
    """Export the network as graph ``monodepth`` (inputs ``image`` [B, 3, H, W] float in [0, 1], dynamic B and
    H, W = 14 x token rows/cols, and ``aspect_ratio`` [B] float, the original images' width / height; outputs
    ``points_raw``, ``normal_raw``, ``mask_logits`` (raw head maps at the heads' resolution) and
    ``metric_scale`` as ``MoGe2``; ``head_maps_to_size`` + ``postprocess`` finish them)
    plus the manifest (kind ``monodepth``, architecture ``moge-2``). Random weights from ``seed`` unless a
    checkpoint is given. Returns ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    model = MoGe2(config).eval()
    if weights is not None:
        load_moge2_weights(model, weights)
        weights_info = {"source": "checkpoint", "path": str(weights), "sha256": onnxio.sha256_file(Path(weights))}
    else:
        weights_info = {"source": "random", "seed": seed}
    p = config.patch_size
    example = (torch.rand(2, 3, 3 * p, 4 * p), torch.tensor([1.25, 1.4]))
    batch = torch.export.Dim("batch", min=1, max=64)
    rows = torch.export.Dim("token_rows", min=2, max=256)
    cols = torch.export.Dim("token_cols", min=2, max=256)
    info = onnxio.export_graph(model, example, out_dir / "monodepth.onnx", input_names=["image", "aspect_ratio"],
                               output_names=model.output_names,
                               dynamic_shapes=({0: batch, 2: p * rows, 3: p * cols}, {0: batch}))
    info.notes = ("image: RGB float in [0, 1], already resized to a token grid (H, W multiples of patch_size); "
                  "mean/std normalisation is inside. aspect_ratio: the original image's width / height. "
                  "points_raw / normal_raw / mask_logits: the heads' raw maps at 2**(levels-1) x the token grid, "
                  "to resize once to the input size and then remap (head_maps_to_size); metric_scale: [B]")
    io = {"input_range": [0.0, 1.0], "patch_size": p, "num_tokens_range": list(config.num_tokens_range),
          "default_num_tokens": num_tokens_for_level(9, config.num_tokens_range),
          "outputs": model.output_names, "head_maps": "raw, resize once to the input size, then remap",
          "remap_output": config.remap_output, "official_model_config": config.to_official()}
    onnxio.write_manifest(out_dir, kind="monodepth", architecture="moge-2", config=config.to_dict(),
                          weights=weights_info, graphs={"monodepth": info}, extra={"io": io})
    return out_dir

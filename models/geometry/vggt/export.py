"""ONNX export of VGGT into a geometry model directory (``export_geometry``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import nn

from navcrafter.models.geometry.vggt.config import OUTPUT_NAMES
from navcrafter.models.geometry.vggt.model import VGGT
from navcrafter.models.geometry.vggt.weights import load_vggt_weights
from navcrafter.models.runtime import onnxio

if TYPE_CHECKING:
    from navcrafter.models.geometry.vggt.config import VGGTConfig


class VGGTExportWrapper(nn.Module):
    """``images`` → the outputs as a tuple in ``OUTPUT_NAMES`` order (what the ONNX graph returns)."""

    def __init__(self, model: VGGT) -> None:
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor):
        out = self.model(images)
        return tuple(out[name] for name in OUTPUT_NAMES)


def export_geometry(out_dir: Path, config: VGGTConfig, weights: Path | None = None, seed: int = 0) -> Path:
    """Export VGGT to ``out_dir/geometry.onnx`` (+ ``.data``) and write its manifest; returns ``out_dir``.

    Input ``images`` [1, S, 3, H, W] float32 in [0, 1] with dynamic S, H, W (H, W multiples of the
    patch size); outputs as in ``OUTPUT_NAMES``. Random weights (``torch.manual_seed(seed)``) unless
    ``weights`` names an official checkpoint.
    """
    from torch.export import Dim

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    model = VGGT(config).eval()
    if weights is None:
        weights_info = {"source": "random", "seed": int(seed)}
    else:
        report = load_vggt_weights(model, Path(weights))
        weights_info = {"source": "checkpoint", "path": str(weights), "sha256": report["sha256"],
                        "ignored_keys": len(report["ignored"])}
    p = config.patch_size
    example = torch.rand(1, 2, 3, 2 * p, 3 * p)
    s = Dim("S", min=1, max=1024)
    h = Dim("h", min=1, max=256)
    w = Dim("w", min=1, max=256)
    dynamic = ({1: s, 3: p * h, 4: p * w},)
    info = onnxio.export_graph(VGGTExportWrapper(model), (example,), out_dir / "geometry.onnx",
                               input_names=["images"], output_names=list(OUTPUT_NAMES), dynamic_shapes=dynamic)
    info.notes = ("images [1,S,3,H,W] float32 in [0,1], H and W multiples of patch_size; pose_enc [1,S,9] = "
                  "w2c translation, quaternion xyzw, fov_h, fov_w (absT_quaR_FoV); depth [1,S,H,W,1]; "
                  "*_conf = 1 + exp(.) >= 1")
    cfg = config.to_dict()
    cfg.update({"img_size": config.img_size, "patch_size": config.patch_size, "input_range": [0.0, 1.0],
                "pose_encoding": "absT_quaR_FoV", "track_head": "not exported"})
    onnxio.write_manifest(out_dir, kind="geometry", architecture="vggt", config=cfg, weights=weights_info,
                          graphs={"geometry": info})
    return out_dir

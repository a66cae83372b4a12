"""MonoDepth role served by an exported MoGe-2 graph (onnxruntime).

``OnnxMonoDepth(model_dir)`` loads ``model_dir/manifest.json`` (kind ``monodepth``, architecture ``moge-2``,
checksums verified) and runs graph ``monodepth``:

1. the image is resized (bilinear, antialiased) to the token grid of ``num_tokens`` at its aspect ratio
   (``preprocess_image``; default: the official ``resolution_level=9``, the top of the model's
   ``num_tokens_range``), as the official model does internally;
2. the graph takes that image and the original aspect ratio (for the UV channels, as official) and
   returns the heads' raw maps (affine point map, normal, mask logits) at their resolution and the metric
   scale;
3. ``outputs_to_result``: ``head_maps_to_size`` resizes the raw maps once to the input size and remaps them,
   then ``postprocess`` recovers the z-shift (and focal) like the official ``infer()``;
   ``depth = (z + shift) * metric_scale``.

``inv_depth = 1 / depth`` (metric-scaled, which satisfies the role's affine-invariant contract). Pixels
the model marks as having no geometry (mask < 0.5: sky and other infinitely far or undefined regions),
and pixels whose depth is non-finite or not positive, are all reported as ``sky = True`` with
``inv_depth = 0`` (infinitely far). Hints (poses, intrinsics) are ignored, as for every learned backend.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.geometry.moge import (
    MoGe2Config,
    MoGe2Result,
    num_tokens_for_level,
    outputs_to_result,
    preprocess_image,
)
from navcrafter.models.roles import MonoDepthPrediction
from navcrafter.models.runtime.onnxio import GraphRunner, ModelDirError, load_manifest

ARCHITECTURE = "moge-2"
GRAPH = "monodepth"


class OnnxMonoDepth:
    """``MonoDepth`` role backed by an exported MoGe-2 model directory."""

    backend = "onnx"

    def __init__(self, model_dir: Path, providers: list[str] | None = None, num_tokens: int | None = None) -> None:
        self.model_dir = Path(model_dir)
        self.manifest = load_manifest(self.model_dir, "monodepth")
        if self.manifest.get("architecture") != ARCHITECTURE:
            raise ModelDirError(f"{self.model_dir}: holds a {self.manifest.get('architecture')!r} monodepth model, "
                                f"expected {ARCHITECTURE!r}; re-export it with export_monodepth")
        try:
            self.config = MoGe2Config.from_dict(self.manifest["config"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelDirError(f"{self.model_dir}: manifest config is not a MoGe-2 config ({exc}); "
                                f"re-export the model") from exc
        self.num_tokens = int(num_tokens or num_tokens_for_level(9, self.config.num_tokens_range))
        if self.num_tokens < 1:
            raise ValueError(f"num_tokens must be positive, got {self.num_tokens}")
        graph = self.manifest.get("graphs", {}).get(GRAPH, {})
        if graph.get("inputs") != ["image", "aspect_ratio"] or "points_raw" not in graph.get("outputs", []):
            raise ModelDirError(f"{self.model_dir}: graph {GRAPH!r} was exported before the official one-resize "
                                f"pipeline (inputs {graph.get('inputs')}, outputs {graph.get('outputs')}; expected "
                                f"inputs ['image', 'aspect_ratio'] and raw head maps); re-export it with "
                                f"export_monodepth")
        self.runner = GraphRunner(self.model_dir, self.manifest, providers)

    def infer(self, image: np.ndarray) -> MoGe2Result:
        """Full MoGe-2 geometry (depth, points, intrinsics, normals, mask) of one ``[H, W, 3]`` uint8 image."""
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected an [H, W, 3] uint8 image, got {image.dtype} {image.shape}")
        x = preprocess_image(image, self.num_tokens, self.config.patch_size)
        aspect = np.array([image.shape[1] / image.shape[0]], dtype=np.float32)
        out = self.runner.run(GRAPH, {"image": x, "aspect_ratio": aspect})
        return outputs_to_result(out, image.shape[:2], self.config)

    def predict(self, image: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None, hint_depth=None) -> MonoDepthPrediction:
        """Inverse depth (0 where invalid) and sky/invalid mask of one image; deterministic (``seed`` unused)."""
        result = self.infer(image)
        return MonoDepthPrediction(inv_depth=result.inv_depth.astype(np.float32), sky=~result.valid)

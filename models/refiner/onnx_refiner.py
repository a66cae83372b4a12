"""Refiner role served by an exported Difix graph (onnxruntime).

``OnnxRefiner(model_dir)`` loads ``model_dir/manifest.json`` (kind ``refiner``, architecture ``difix``,
checksums verified) and the precomputed prompt embedding, and runs graph ``refiner`` once per call:

1. the rendered view and the reference are resized (PIL Lanczos, as the official ``Difix.sample``) to the
   working size: the input size rounded to the nearest multiples of the model's ``size_multiple`` (64 for
   SD-Turbo; at least one multiple), or a fixed ``size=(H, W)``; and scaled to [-1, 1];
2. the VAE posterior noise ``latent_noise`` is drawn from ``numpy.random.default_rng(seed)`` (Difix samples the
   posterior; ``sample_posterior=False`` feeds zeros, i.e. the posterior mean), so a call is deterministic
   for a given ``seed``;
3. the output in [-1, 1] becomes uint8 as diffusers' ``VaeImageProcessor.postprocess`` (the official pipeline:
   ``(x / 2 + 0.5).clamp(0, 1) * 255``, rounded) and is resized back to the input size (Lanczos).

``reference=None`` uses the rendered view itself as the reference: the ``difix_ref`` network always mixes
two views, and an identical pair gives it no extra information (a model exported with
``reference_mixing=False``, ``nvidia/difix``, ignores the reference in any case). A reference of another size
than the rendered view is resized to the same working size. Hints (camera pose, intrinsics) are ignored, as
for every learned backend.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.refiner.difix import ARCHITECTURE, GRAPH, KIND, OUTPUT, DifixConfig
from navcrafter.models.runtime.onnxio import GraphRunner, ModelDirError, load_manifest


def _resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """uint8 ``[h, w, 3]`` -> ``[height, width, 3]`` with PIL's Lanczos filter (no-op at the same size)."""
    if image.shape[:2] == (height, width):
        return image
    from PIL import Image

    return np.asarray(Image.fromarray(image).resize((width, height), Image.LANCZOS))


def _check_image(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"{name}: expected an [H, W, 3] uint8 image, got {image.dtype} {image.shape}")
    return np.ascontiguousarray(image)


class OnnxRefiner:
    """``Refiner`` role backed by an exported Difix model directory."""

    backend = "onnx"

    def __init__(self, model_dir: Path, providers: list[str] | None = None, size: tuple[int, int] | None = None,
                 sample_posterior: bool = True) -> None:
        self.model_dir = Path(model_dir)
        self.manifest = load_manifest(self.model_dir, KIND)
        if self.manifest.get("architecture") != ARCHITECTURE:
            raise ModelDirError(f"{self.model_dir}: holds a {self.manifest.get('architecture')!r} refiner, expected "
                                f"{ARCHITECTURE!r}; re-export it with `navcrafter models export-refiner`")
        try:
            self.config = DifixConfig.from_dict(self.manifest["config"])
            io = self.manifest["io"]
            self.inputs = list(io["inputs"])
            self.prompt_embeds = np.load(self.model_dir / io["prompt_file"]).astype(np.float32)
        except (KeyError, TypeError, ValueError, OSError) as exc:
            raise ModelDirError(f"{self.model_dir}: manifest or prompt embeddings unreadable as a Difix export "
                                f"({exc}); re-export the model") from exc
        self.size_multiple = self.config.size_multiple
        if size is not None and (size[0] % self.size_multiple or size[1] % self.size_multiple or min(size) < 1):
            raise ValueError(f"size must be positive multiples of {self.size_multiple}, got {size}")
        self.size = size
        self.sample_posterior = bool(sample_posterior)
        self.runner = GraphRunner(self.model_dir, self.manifest, providers)

    def working_size(self, height: int, width: int) -> tuple[int, int]:
        """The size the network runs at for an input of ``height x width``."""
        if self.size is not None:
            return self.size
        m = self.size_multiple
        return max(m, round(height / m) * m), max(m, round(width / m) * m)

    def refine(self, rendered: np.ndarray, reference: np.ndarray | None, *, seed: int,
               hint_c2w: np.ndarray | None = None, hint_intrinsics: Intrinsics | None = None) -> np.ndarray:
        """Refined ``[H, W, 3]`` uint8 version of ``rendered`` guided by ``reference`` (None: ``rendered`` itself)."""
        rendered = _check_image(rendered, "rendered")
        reference = rendered if reference is None else _check_image(reference, "reference")
        h, w = rendered.shape[:2]
        hh, ww = self.working_size(h, w)
        feeds = {"image": _to_model(_resize(rendered, hh, ww)), "prompt_embeds": self.prompt_embeds}
        if "reference" in self.inputs:
            feeds["reference"] = _to_model(_resize(reference, hh, ww))
        f, c = self.config.vae_scale_factor, self.config.latent_channels
        shape = (1, self.config.num_views, c, hh // f, ww // f)
        feeds["latent_noise"] = (np.random.default_rng(seed).standard_normal(shape, dtype=np.float32)
                                 if self.sample_posterior else np.zeros(shape, np.float32))
        out = self.runner.run(GRAPH, feeds)[OUTPUT][0]
        image = np.round(np.clip(out.transpose(1, 2, 0) * 0.5 + 0.5, 0.0, 1.0) * 255.0).astype(np.uint8)
        return _resize(image, h, w)


def _to_model(image: np.ndarray) -> np.ndarray:
    """uint8 ``[H, W, 3]`` -> float32 ``[1, 3, H, W]`` in [-1, 1]."""
    return (image.astype(np.float32).transpose(2, 0, 1)[None] / 127.5 - 1.0).astype(np.float32)

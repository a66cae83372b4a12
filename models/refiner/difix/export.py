"""ONNX export of the Difix refiner into a refiner model directory (``export_refiner``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from navcrafter.models.refiner.difix.config import (
    ARCHITECTURE,
    DEFAULT_PROMPT,
    GRAPH,
    INPUTS,
    KIND,
    MAX_SIDE,
    OUTPUT,
    PROMPT_FILE,
)
from navcrafter.models.refiner.difix.model import DifixRefinerModel, randomize_adapters
from navcrafter.models.refiner.difix.prompt import encode_prompt, random_prompt_embeds
from navcrafter.models.refiner.difix.weights import load_difix_weights
from navcrafter.models.runtime import onnxio

if TYPE_CHECKING:
    from navcrafter.models.refiner.difix.config import DifixConfig


class _NoReferenceGraph(nn.Module):
    """Graph signature of the plain (``reference_mixing=False``) model: no reference input."""

    def __init__(self, model: DifixRefinerModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, image, prompt_embeds, latent_noise):
        return self.model(image, None, prompt_embeds, latent_noise)


def graph_inputs(config: DifixConfig) -> list[str]:
    return [n for n in INPUTS if n != "reference" or config.reference_mixing]


def export_refiner(out_dir: Path, config: DifixConfig, weights: Path | None = None, seed: int = 0, *,
                   base: Path | None = None, prompt_embeds: Path | np.ndarray | None = None,
                   prompt: str = DEFAULT_PROMPT) -> Path:
    """Export Difix as graph ``refiner`` plus ``prompt_embeds.npy`` and the manifest (kind ``refiner``,
    architecture ``difix``). Returns ``out_dir``.

    Graph inputs: ``image`` and ``reference`` ``[B, 3, H, W]`` in [-1, 1] (no ``reference`` when
    ``config.reference_mixing`` is False), ``prompt_embeds`` ``[1, text_tokens, D]``, ``latent_noise``
    ``[B, V, latent_channels, H/f, W/f]`` (f = ``vae_scale_factor``); output ``refined`` ``[B, 3, H, W]`` in
    [-1, 1]. B is 1 (the role refines one view per call, as the official pipeline; a dynamic batch makes the
    export much slower); H and W are dynamic multiples of ``config.size_multiple`` up to ``MAX_SIDE`` (2048).
    The LoRA adapters are merged into the decoder weights before export (exact).

    Weights: random from ``seed`` (LoRA ``lora_B`` randomised, see ``randomize_adapters``) unless ``weights``
    is an official checkpoint (``load_difix_weights``, with ``base`` for training checkpoints). Prompt
    embedding: ``prompt_embeds`` (array or ``.npy``) if given, else ``prompt`` encoded with the text encoder of
    the checkpoint directory or of ``base``; random weights get a seeded random embedding."""
    from torch.export import Dim

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / onnxio.MANIFEST).unlink(missing_ok=True)  # a directory with a manifest is a finished export
    torch.manual_seed(seed)
    model = DifixRefinerModel(config).eval()
    if weights is None:
        randomize_adapters(model, seed)
        weights_info: dict[str, Any] = {"source": "random", "seed": int(seed)}
    else:
        weights = Path(weights)
        report = load_difix_weights(model, weights, base=base)
        weights_info = {"source": "checkpoint", "path": report["path"], "files": report["files"]}
        if weights.is_file():
            weights_info["sha256"] = report["files"][weights.name]
    if prompt_embeds is not None:
        emb = np.load(prompt_embeds) if not isinstance(prompt_embeds, np.ndarray) else prompt_embeds
        text = {"source": "given", "prompt": None}
    elif weights is None:
        emb = random_prompt_embeds(config, seed)
        text = {"source": "random", "prompt": None}
    else:
        holder = next((d for d in (weights if weights.is_dir() else None, base)
                       if d is not None and (Path(d) / "text_encoder").is_dir()), None)
        if holder is None:
            raise FileNotFoundError(f"no text encoder to embed the prompt {prompt!r}: {weights} has no text_encoder/"
                                    f" and no SD-Turbo base directory was given; pass base=... or prompt_embeds=...")
        emb = encode_prompt(Path(holder), prompt, config.text_tokens)
        text = {"source": "text_encoder", "prompt": prompt, "path": str(Path(holder).resolve())}
    emb = np.ascontiguousarray(emb, dtype=np.float32)
    want = (1, config.text_tokens, config.cross_attention_dim)
    if emb.shape != want:
        raise ValueError(f"prompt embeddings have shape {emb.shape}, the model needs {want}")

    model.merge_lora_()
    m, f, v = config.size_multiple, config.vae_scale_factor, config.num_views
    # H = rows * size_multiple <= MAX_SIDE (keeps diffusers' Upsample2D size check `numel * 2 > 2**31` false)
    rows, cols = Dim("rows", min=1, max=MAX_SIDE // m), Dim("cols", min=1, max=MAX_SIDE // m)
    image = torch.rand(1, 3, 2 * m, 3 * m) * 2 - 1
    example = {"image": image, "reference": torch.rand_like(image) * 2 - 1,
               "prompt_embeds": torch.from_numpy(emb),
               "latent_noise": torch.randn(1, v, config.latent_channels, 2 * m // f, 3 * m // f)}
    dims = {"image": {2: m * rows, 3: m * cols}, "reference": {2: m * rows, 3: m * cols}, "prompt_embeds": None,
            "latent_noise": {3: (m // f) * rows, 4: (m // f) * cols}}
    names = graph_inputs(config)
    module = model if config.reference_mixing else _NoReferenceGraph(model)
    info = onnxio.export_graph(module.eval(), tuple(example[n] for n in names), out_dir / f"{GRAPH}.onnx",
                               input_names=names, output_names=[OUTPUT],
                               dynamic_shapes=tuple(dims[n] for n in names))
    info.notes = (f"image/reference: RGB in [-1, 1], H and W multiples of {m}; latent_noise: N(0, 1) of the "
                  f"VAE posterior sample (zeros = mean); refined: input view in [-1, 1]")
    np.save(out_dir / PROMPT_FILE, emb)
    io = {"inputs": names, "output": OUTPUT, "input_range": [-1.0, 1.0], "output_range": [-1.0, 1.0],
          "size_multiple": m, "vae_scale_factor": f, "num_views": v, "latent_channels": config.latent_channels,
          "prompt_file": PROMPT_FILE, "text": text, "timestep": config.timestep, "lora": "merged into the decoder"}
    onnxio.write_manifest(out_dir, kind=KIND, architecture=ARCHITECTURE, config=config.to_dict(),
                          weights=weights_info, graphs={GRAPH: info}, extra_files=[PROMPT_FILE], extra={"io": io})
    return out_dir

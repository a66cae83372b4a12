"""The fixed prompt's CLIP embedding, computed outside the graph (``encode_prompt``), or random for random-weight
runs."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from navcrafter.models.refiner.difix.config import DEFAULT_PROMPT

if TYPE_CHECKING:
    from navcrafter.models.refiner.difix.config import DifixConfig


def encode_prompt(directory: Path, prompt: str = DEFAULT_PROMPT, text_tokens: int = 77) -> np.ndarray:
    """``[1, text_tokens, D]`` float32: the CLIP ``last_hidden_state`` of ``prompt`` padded to ``text_tokens``
    (``padding="max_length"``, truncated, no attention mask), as Difix's ``model.py`` and ``encode_prompt`` of
    its pipeline, from ``directory/text_encoder`` (CLIPTextModel, safetensors) and ``directory/tokenizer``."""
    from transformers import CLIPTextModel, CLIPTokenizer

    directory = Path(directory)
    for sub in ("text_encoder", "tokenizer"):
        if not (directory / sub).is_dir():
            raise FileNotFoundError(f"{directory}: no {sub}/ folder to encode the prompt with (use the "
                                    f"nvidia/difix_ref or stabilityai/sd-turbo directory, or pass precomputed "
                                    f"prompt embeddings)")
    tokenizer = CLIPTokenizer.from_pretrained(str(directory / "tokenizer"))
    text_encoder = CLIPTextModel.from_pretrained(str(directory / "text_encoder"), dtype=torch.float32,
                                                 use_safetensors=True).eval()
    ids = tokenizer(prompt, max_length=text_tokens, padding="max_length", truncation=True,
                    return_tensors="pt").input_ids
    with torch.no_grad():
        emb = text_encoder(ids)[0]
    return emb.float().numpy().astype(np.float32)


def random_prompt_embeds(config: DifixConfig, seed: int) -> np.ndarray:
    """Seeded standard-normal stand-in for the prompt embedding of random-weight models."""
    rng = np.random.RandomState(seed + 4)
    return rng.standard_normal((1, config.text_tokens, config.cross_attention_dim)).astype(np.float32)

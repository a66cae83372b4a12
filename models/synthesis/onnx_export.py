"""Export the synthesizer (camera-controlled Wan2.1 I2V + VAE + CLIP image encoder) to an ONNX model directory.

``export_synthesizer(out_dir, ...)`` writes::

    OUT/manifest.json                 kind "synthesizer", architecture "wan2.1-i2v-camera" (see ``onnxio``)
    OUT/dit.onnx(.data)               CameraControlledWan: dynamic batch, latent frames, height, width
    OUT/vae_encoder.onnx(.data)       AutoencoderKLWan encoder: video [B,3,T,H,W] in [-1,1] -> normalised latents
    OUT/vae_decoder.onnx(.data)       AutoencoderKLWan decoder: normalised latents -> video [B,3,T,H,W] in [-1,1]
    OUT/image_encoder.onnx(.data)     CLIPVisionModel: pixel_values [B,3,S,S] -> penultimate hidden states
    OUT/text_embeddings.npy           float32 [2, 512, text_dim]: UMT5 embeddings of (prompt, negative prompt)

**VAE frame count.** diffusers' Wan VAE encodes/decodes in a Python loop over temporal chunks with a causal
feature cache, so ``torch.export`` unrolls the loop for one frame count: both VAE graphs are exported for the
configured ``num_frames`` only (``config.vae_num_frames``; batch, height and width are dynamic unless
``dynamic=False``). The sampler refuses other frame counts with an error saying to re-export. (A per-chunk
"step" graph with the cache as explicit inputs/outputs would lift this, at the price of ~60 cache tensors per
call; not worth it while a run uses one clip length.)

**Latent normalisation** (``(z - latents_mean) / latents_std``, Wan's) is inside the VAE graphs, so the DiT,
the sampler and the graphs all see normalised latents, and the encoder returns the posterior mode (as Wan I2V's
``retrieve_latents(..., sample_mode="argmax")``).

**CLIP image features**: as diffusers' ``WanImageToVideoPipeline.encode_image``: ``CLIPImageProcessor`` (resize
the shortest edge to ``S`` bicubic, centre crop ``S x S``, scale to [0, 1], normalise with CLIP mean/std; done in
numpy by the sampler, parameters in ``config.image_encoder``), then ``hidden_states[-2]`` of ``CLIPVisionModel``
(the penultimate layer, no post-layernorm): ``[B, 257, 1280]`` for ViT-H/14 at 224.

**Text** is precomputed here (UMT5 is ~11 GB and the prompt is fixed per export): as Wan's
``_get_t5_prompt_embeds``: tokenised to 512 tokens, encoded, positions past the prompt's length zeroed.

**fun-camera** (``export_fun_camera_synthesizer``; ``funcamera/``): the same directory layout with the DiT of
Wan2.1-Fun-V1.1-Control-Camera (architecture ``wan2.1-fun-v1.1-control-camera``; ``config.model = "fun-camera"``,
``config.condition_layout = "fun-camera"``, ``config.plucker_convention = "videox-fun"``; DiT inputs
``funcamera.FUN_DIT_INPUTS``); VAE, CLIP and text from a diffusers-format Wan2.1 I2V directory.

With ``tiny=True`` every module is a tiny random one (seeded), and the camera-control weights - which are
zero-initialised, so an untrained model would ignore the camera - get small random values so that every
control path is live in the graph and tests exercise it. The manifest then says ``{"source": "random"}``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from navcrafter.models.runtime.onnxio import MANIFEST, export_graph, sha256_file, write_manifest
from navcrafter.models.synthesis.config import WAN_FLOW_SHIFT

ARCHITECTURE = "wan2.1-i2v-camera"
KIND = "synthesizer"
TEXT_EMBEDDINGS = "text_embeddings.npy"
TEXT_TOKENS = 512
# Wan2.1's usual negative prompt (English version of the one in the official repository).
DEFAULT_NEGATIVE_PROMPT = (
    "Bright tones, overexposed, static, blurred details, subtitles, style, works, paintings, images, static, "
    "overall gray, worst quality, low quality, JPEG compression residue, ugly, incomplete, extra fingers, poorly "
    "drawn hands, poorly drawn faces, deformed, disfigured, misshapen limbs, fused fingers, still picture, messy "
    "background, three legs, many people in the background, walking backwards")
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
# Scheduler defaults (DPM-solver++ for flow matching, as in NavCrafter; Wan2.1's 480p shift).
SCHEDULER_DEFAULTS = {"name": "DPMSolverMultistepScheduler", "prediction_type": "flow_prediction",
                      "use_flow_sigmas": True, "flow_shift": WAN_FLOW_SHIFT, "num_train_timesteps": 1000,
                      "solver_order": 2, "algorithm_type": "dpmsolver++", "steps": 40, "guidance_scale": 6.5,
                      "lora_scale": 0.7}

# Tiny random VAE / CLIP for tests (the DiT is camcontrol's ``tiny_camera_wan``).
TINY_VAE_CONFIG: dict[str, Any] = {"base_dim": 8, "z_dim": 16, "dim_mult": [1, 2, 2, 2], "num_res_blocks": 1,
                                   "temperal_downsample": [False, True, True]}
TINY_CLIP_IMAGE_SIZE = 32
TINY_CLIP_PATCH = 8


# --------------------------------------------------------------------------------------------------
# The graphs' torch modules (also what TorchRunner runs, so both engines execute the same code)
# --------------------------------------------------------------------------------------------------
def _latent_stats(vae) -> tuple[torch.Tensor, torch.Tensor]:
    z = vae.config.z_dim
    mean = torch.tensor(vae.config.latents_mean, dtype=torch.float32).view(1, z, 1, 1, 1)
    std = torch.tensor(vae.config.latents_std, dtype=torch.float32).view(1, z, 1, 1, 1)
    return mean, std


class VaeEncoder(nn.Module):
    """video ``[B, 3, T, H, W]`` in [-1, 1] -> normalised latents ``[B, 16, (T-1)/4+1, H/8, W/8]`` (mode)."""

    def __init__(self, vae) -> None:
        super().__init__()
        self.vae = vae
        mean, std = _latent_stats(vae)
        self.register_buffer("mean", mean, persistent=False)
        self.register_buffer("std", std, persistent=False)

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        z = self.vae.encode(video).latent_dist.mode()
        return (z - self.mean.to(z.dtype)) / self.std.to(z.dtype)


class VaeDecoder(nn.Module):
    """normalised latents ``[B, 16, F, h, w]`` -> video ``[B, 3, 4(F-1)+1, 8h, 8w]`` in [-1, 1]."""

    def __init__(self, vae) -> None:
        super().__init__()
        self.vae = vae
        mean, std = _latent_stats(vae)
        self.register_buffer("mean", mean, persistent=False)
        self.register_buffer("std", std, persistent=False)

    def forward(self, latents: torch.Tensor) -> torch.Tensor:
        z = latents * self.std.to(latents.dtype) + self.mean.to(latents.dtype)
        return self.vae.decode(z).sample.clamp(-1.0, 1.0)


class ClipImageFeatures(nn.Module):
    """pixel_values ``[B, 3, S, S]`` (CLIP-normalised) -> penultimate hidden states ``[B, L, D]`` (Wan I2V)."""

    def __init__(self, clip) -> None:
        super().__init__()
        self.clip = clip

    def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
        return self.clip(pixel_values=pixel_values, output_hidden_states=True).hidden_states[-2]


# --------------------------------------------------------------------------------------------------
# Components
# --------------------------------------------------------------------------------------------------
@dataclass
class SynthesisComponents:
    """Everything the synthesizer runs, as torch modules (fp32), plus the precomputed text embeddings."""

    dit: nn.Module  # CameraControlledWan
    vae: nn.Module  # AutoencoderKLWan
    image_encoder: nn.Module  # CLIPVisionModel
    text_embeddings: np.ndarray  # float32 [2, 512, text_dim]: (prompt, negative prompt)
    image_preprocess: dict[str, Any]  # CLIPImageProcessor parameters (see module docstring)
    weights: dict[str, Any]  # the manifest's "weights" entry
    prompt: str = ""
    negative_prompt: str = DEFAULT_NEGATIVE_PROMPT
    sources: dict[str, str] = field(default_factory=dict)  # file -> sha256 of checkpoint files read

    def config(self, num_frames: int, height: int, width: int, dynamic: bool = True) -> dict[str, Any]:
        """The manifest ``config``: everything the sampler needs besides the graphs. ``plucker_convention`` is the
        camera control's (``self.dit.config``, the saved config of the loaded weights), which ``OnnxSynthesizer``
        requires and checks against ``synthesis.plucker_convention``."""
        if getattr(self.dit, "model_name", "navcrafter") == "fun-camera":
            return self._fun_camera_config(num_frames, height, width, dynamic)
        control = self.dit.config
        return {
            **self._shared_config(num_frames, height, width, dynamic),
            "control": control.to_dict(),
            # the loaded weights' own (load_camera_control replaces the model's config with the saved one)
            "plucker_convention": control.plucker_convention,
            "cond_layout": "render latents (16) + packed visibility mask (4), camcontrol.make_render_condition",
        }

    def _shared_config(self, num_frames: int, height: int, width: int, dynamic: bool) -> dict[str, Any]:
        """The manifest ``config`` entries both synthesizer models have: sizes, the base DiT's and the VAE's
        configs, the image encoder's preprocessing, the scheduler, the text embeddings."""
        base = self.dit.base.config
        vae = self.vae.config
        return {
            "num_frames": int(num_frames), "height": int(height), "width": int(width),
            "vae_num_frames": int(num_frames), "dynamic_shapes": bool(dynamic),
            "latent_channels": int(vae.z_dim),
            "vae_scale_factor_temporal": int(vae.scale_factor_temporal),
            "vae_scale_factor_spatial": int(vae.scale_factor_spatial),
            "patch_size": [int(p) for p in base.patch_size],
            "in_channels": int(base.in_channels), "text_dim": int(base.text_dim),
            "image_dim": int(base.image_dim) if base.image_dim is not None else None,
            "text_tokens": TEXT_TOKENS,
            "transformer": _jsonable(dict(base)),
            "vae": _jsonable(dict(vae)),
            "image_encoder": {**self.image_preprocess, "hidden_size": int(self.image_encoder.config.hidden_size),
                              "features": "hidden_states[-2]"},
            "scheduler": dict(SCHEDULER_DEFAULTS),
            "text": {"file": TEXT_EMBEDDINGS, "prompt": self.prompt, "negative_prompt": self.negative_prompt,
                     "shape": list(self.text_embeddings.shape), "rows": ["prompt", "negative_prompt"]},
            "cfg_uncond_camera": "on",
        }

    def _fun_camera_config(self, num_frames: int, height: int, width: int, dynamic: bool) -> dict[str, Any]:
        """The manifest ``config`` of a fun-camera synthesizer (``funcamera/``): no render condition, no LoRA, no
        extra reference frames; ``condition_layout`` tells the sampler to build ``[noisy | start-image latents]``."""
        # deferred: diffusers loads with funcamera only for the fun-camera model
        from navcrafter.models.synthesis import funcamera

        fun = self.dit.config
        return {
            **self._shared_config(num_frames, height, width, dynamic),
            "model": funcamera.MODEL_NAME, "condition_layout": funcamera.CONDITION_LAYOUT,
            "official_config": fun.official_config(),
            "control": {"cond_channels": 0, "adapter": "VideoX-Fun SimpleAdapter (control_adapter.*)",
                        "in_dim_control_adapter": fun.in_dim_control_adapter,
                        "downscale_factor_control_adapter": fun.downscale_factor_control_adapter},
            "plucker_convention": funcamera.PLUCKER_CONVENTION,
            "plucker": "funcamera.fun_camera_plucker: (o x d, d), poses relative to the first camera (identity), "
                       "no translation normalisation, pixel centres +0.5; packed 4 frames per latent frame",
            "cond_layout": "[noisy latents (16) | start-image latents (16): frame 0 = the image, others zero]",
        }


def _jsonable(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if k.startswith("_"):
            continue
        if isinstance(v, tuple):
            v = list(v)
        try:
            json.dumps(v)
        except TypeError:
            v = repr(v)
        out[k] = v
    return out


def _randomize_control(dit: nn.Module, seed: int, std: float = 0.05) -> None:
    """Give the zero-initialised control parameters small random values (tiny test models only)."""
    g = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for p in dit.control.parameters():
            if not torch.count_nonzero(p):
                p.copy_(torch.randn(p.shape, generator=g) * std)


def tiny_components(seed: int = 0, prompt: str = "", negative_prompt: str = DEFAULT_NEGATIVE_PROMPT,
                    control_dir: str | Path | None = None) -> SynthesisComponents:
    """Tiny random modules for tests: camcontrol's tiny DiT, a tiny Wan VAE and CLIP, random text embeddings.

    ``control_dir``: camera-control weights trained on this tiny base (``navcrafter train-camera`` with
    ``random_base: tiny`` and the same ``seed``) replace the random control."""
    # deferred: diffusers loads with camcontrol only when the camera-controlled DiT is built or read
    from navcrafter.models.synthesis.camcontrol import (
        TINY_I2V_CONFIG,
        build_camera_wan,
        load_camera_control,
        read_camera_control_config,
        tiny_camera_wan,
    )

    if control_dir is None:
        dit = tiny_camera_wan(seed)
        _randomize_control(dit, seed)
    else:
        dit = build_camera_wan(TINY_I2V_CONFIG, read_camera_control_config(control_dir), seed=seed)
        load_camera_control(dit, control_dir)
    vae, clip, text = _tiny_encoders(seed, dit.base.config.image_dim, dit.base.config.text_dim)
    out = SynthesisComponents(
        dit=dit.eval(), vae=vae, image_encoder=clip, text_embeddings=text,
        image_preprocess=_preprocess_params(TINY_CLIP_IMAGE_SIZE, TINY_CLIP_IMAGE_SIZE, CLIP_MEAN, CLIP_STD),
        weights={"source": "random", "seed": int(seed)}, prompt=prompt, negative_prompt=negative_prompt)
    if control_dir is not None:
        # deferred: diffusers loads with camcontrol only when the camera-controlled DiT is built or read
        from navcrafter.models.synthesis.camcontrol import CONTROL_CONFIG, CONTROL_WEIGHTS

        control_dir = Path(control_dir)
        out.weights["control"] = {"path": str(control_dir.resolve()), "files": {
            name: sha256_file(control_dir / name) for name in (CONTROL_WEIGHTS, CONTROL_CONFIG)}}
    return out


def _tiny_encoders(seed: int, image_dim: int, text_dim: int):
    """Tiny random Wan VAE, CLIP vision model (seeds ``seed + 2``, ``seed + 3``) and text embeddings (``seed + 4``)."""
    from diffusers import AutoencoderKLWan
    from transformers import CLIPVisionConfig, CLIPVisionModel

    with torch.random.fork_rng():
        torch.manual_seed(seed + 2)
        vae = AutoencoderKLWan(**TINY_VAE_CONFIG).eval()
        torch.manual_seed(seed + 3)
        clip_cfg = CLIPVisionConfig(hidden_size=image_dim, intermediate_size=16, num_hidden_layers=2,
                                    num_attention_heads=1, image_size=TINY_CLIP_IMAGE_SIZE,
                                    patch_size=TINY_CLIP_PATCH, projection_dim=8)
        clip = CLIPVisionModel(clip_cfg).eval()
    rng = np.random.RandomState(seed + 4)
    text = rng.standard_normal((2, TEXT_TOKENS, text_dim)).astype(np.float32)
    return vae, clip, text


def tiny_fun_camera_components(seed: int = 0, prompt: str = "",
                               negative_prompt: str = DEFAULT_NEGATIVE_PROMPT) -> SynthesisComponents:
    """Tiny random fun-camera synthesizer (``funcamera.tiny_fun_camera``) with the tiny VAE, CLIP and text."""
    # deferred: diffusers loads with funcamera only for the fun-camera model
    from navcrafter.models.synthesis.funcamera import tiny_fun_camera

    dit = tiny_fun_camera(seed)
    vae, clip, text = _tiny_encoders(seed, dit.config.image_dim, dit.config.text_dim)
    return SynthesisComponents(
        dit=dit, vae=vae, image_encoder=clip, text_embeddings=text,
        image_preprocess=_preprocess_params(TINY_CLIP_IMAGE_SIZE, TINY_CLIP_IMAGE_SIZE, CLIP_MEAN, CLIP_STD),
        weights={"source": "random", "seed": int(seed), "model": "fun-camera"}, prompt=prompt,
        negative_prompt=negative_prompt)


def _preprocess_params(shortest_edge: int, crop: int, mean, std) -> dict[str, Any]:
    return {"shortest_edge": int(shortest_edge), "image_size": int(crop), "image_mean": [float(m) for m in mean],
            "image_std": [float(s) for s in std], "resample": "bicubic", "crop": "center"}


def _hash_dir(directory: Path, root: Path) -> dict[str, str]:
    out = {}
    for f in sorted(Path(directory).rglob("*")):
        if f.is_file() and f.suffix in (".safetensors", ".json", ".model", ".txt"):
            out[str(f.relative_to(root))] = sha256_file(f)
    return out


def encode_prompts(text_encoder, tokenizer, prompts: list[str], max_length: int = TEXT_TOKENS) -> np.ndarray:
    """UMT5 embeddings ``[len(prompts), 512, D]`` exactly as diffusers' ``WanPipeline._get_t5_prompt_embeds``."""
    inputs = tokenizer(prompts, padding="max_length", max_length=max_length, truncation=True,
                       add_special_tokens=True, return_attention_mask=True, return_tensors="pt")
    ids, mask = inputs.input_ids, inputs.attention_mask
    seq_lens = mask.gt(0).sum(dim=1).long()
    with torch.no_grad():
        emb = text_encoder(ids, mask).last_hidden_state.float()
    out = torch.zeros_like(emb)
    for i, n in enumerate(seq_lens.tolist()):
        out[i, :n] = emb[i, :n]
    return out.numpy().astype(np.float32)


def _load_encoders(base_dir: Path, prompt: str, negative_prompt: str):
    """VAE, CLIP image encoder, text embeddings of (prompt, negative prompt), CLIP preprocessing and the sha256 of
    every file read, from a diffusers-format Wan2.1 I2V directory (safetensors only)."""
    from diffusers import AutoencoderKLWan
    from transformers import AutoTokenizer, CLIPVisionModel, UMT5EncoderModel

    vae = AutoencoderKLWan.from_pretrained(base_dir, subfolder="vae", torch_dtype=torch.float32,
                                           use_safetensors=True).eval()
    clip = CLIPVisionModel.from_pretrained(base_dir, subfolder="image_encoder", dtype=torch.float32,
                                           use_safetensors=True).eval()
    # bf16 as Wan runs it (umt5-xxl is 5.7B parameters: 11 GB instead of 23 GB in fp32); only two prompts.
    text_encoder = UMT5EncoderModel.from_pretrained(base_dir, subfolder="text_encoder", dtype=torch.bfloat16,
                                                    use_safetensors=True).eval()
    tokenizer = AutoTokenizer.from_pretrained(base_dir, subfolder="tokenizer")
    text = encode_prompts(text_encoder, tokenizer, [prompt, negative_prompt])
    del text_encoder

    proc = base_dir / "image_processor" / "preprocessor_config.json"
    size = clip.config.image_size
    shortest, crop, mean, std = size, size, CLIP_MEAN, CLIP_STD
    if proc.is_file():
        p = json.loads(proc.read_text())
        s, c = p.get("size", size), p.get("crop_size", size)
        shortest = s.get("shortest_edge", s.get("height", size)) if isinstance(s, dict) else int(s)
        crop = c.get("height", size) if isinstance(c, dict) else int(c)
        mean, std = p.get("image_mean", CLIP_MEAN), p.get("image_std", CLIP_STD)
    return vae, clip, text, _preprocess_params(shortest, crop, mean, std)


def _check_base_dir(base_dir: Path, subs: tuple[str, ...]) -> None:
    for sub in subs:
        if not (base_dir / sub).is_dir():
            raise FileNotFoundError(f"{base_dir}: no {sub}/ folder; expected a diffusers-format Wan2.1 I2V "
                                    f"directory ({', '.join(subs)})")


def load_components(base_dir: str | Path, control_dir: str | Path | None = None, prompt: str = "",
                    negative_prompt: str = DEFAULT_NEGATIVE_PROMPT) -> SynthesisComponents:
    """Real components from a diffusers-format Wan2.1 I2V directory (+ camera-control weights).

    ``base_dir`` holds ``transformer/``, ``vae/``, ``image_encoder/``, ``text_encoder/``, ``tokenizer/`` and
    optionally ``image_processor/`` (CLIPImageProcessor config). Only safetensors weights are read.
    """
    # deferred: diffusers loads with camcontrol only when the camera-controlled DiT is built or read
    from navcrafter.models.synthesis.camcontrol import CONTROL_CONFIG, CONTROL_WEIGHTS, CameraControlledWan

    base_dir = Path(base_dir)
    _check_base_dir(base_dir, ("transformer", "vae", "image_encoder", "text_encoder", "tokenizer"))
    dit = CameraControlledWan.from_pretrained(base_dir, control_dir, torch_dtype=torch.float32).eval()
    vae, clip, text, preprocess = _load_encoders(base_dir, prompt, negative_prompt)

    sources = {}
    for sub in ("transformer", "vae", "image_encoder", "text_encoder", "tokenizer", "image_processor"):
        if (base_dir / sub).is_dir():
            sources.update(_hash_dir(base_dir / sub, base_dir))
    weights: dict[str, Any] = {"source": "checkpoint", "path": str(base_dir.resolve()), "files": sources}
    if control_dir is not None:
        control_dir = Path(control_dir)
        weights["control"] = {"path": str(control_dir.resolve()), "files": {
            name: sha256_file(control_dir / name) for name in (CONTROL_WEIGHTS, CONTROL_CONFIG)
            if (control_dir / name).is_file()}}
    else:
        weights["control"] = {"source": "zero-init (no control_dir given: the camera is ignored)"}
    return SynthesisComponents(dit=dit, vae=vae, image_encoder=clip, text_embeddings=text,
                               image_preprocess=preprocess, weights=weights,
                               prompt=prompt, negative_prompt=negative_prompt, sources=sources)


def load_fun_camera_components(checkpoint_dir: str | Path, base_dir: str | Path, prompt: str = "",
                               negative_prompt: str = DEFAULT_NEGATIVE_PROMPT) -> SynthesisComponents:
    """A fun-camera synthesizer: the DiT from the official Wan2.1-Fun-V1.1-*-Control-Camera folder
    (``funcamera.load_fun_camera``: ``config.json`` + ``diffusion_pytorch_model*.safetensors``), the VAE, CLIP image
    encoder and UMT5 from a diffusers-format Wan2.1 I2V directory ``base_dir`` (the Fun folder ships the same
    Wan2.1 VAE, open-clip ViT-H/14 and umt5-xxl as ``.pth`` pickles in Wan's original format, which are not read)."""
    # deferred: diffusers loads with funcamera only for the fun-camera model
    from navcrafter.models.synthesis.funcamera import _transformer_dir, load_fun_camera

    checkpoint_dir, base_dir = Path(checkpoint_dir), Path(base_dir)
    _check_base_dir(base_dir, ("vae", "image_encoder", "text_encoder", "tokenizer"))
    dit = load_fun_camera(checkpoint_dir)
    vae, clip, text, preprocess = _load_encoders(base_dir, prompt, negative_prompt)
    tdir = _transformer_dir(checkpoint_dir)
    sources = {f"transformer/{f.name}": sha256_file(f) for f in sorted(tdir.iterdir())
               if f.is_file() and f.suffix in (".safetensors", ".json")}
    encoders = {}
    for sub in ("vae", "image_encoder", "text_encoder", "tokenizer", "image_processor"):
        if (base_dir / sub).is_dir():
            encoders.update(_hash_dir(base_dir / sub, base_dir))
    weights: dict[str, Any] = {
        "source": "checkpoint", "model": "fun-camera", "path": str(tdir.resolve()), "files": sources,
        "encoders": {"path": str(base_dir.resolve()), "files": encoders},
        # the camera control is the checkpoint's own trained adapter (not flagged CAMERA CONTROL UNTRAINED)
        "control": {"source": "checkpoint (control_adapter.*, trained by VideoX-Fun)", "path": str(tdir.resolve())}}
    return SynthesisComponents(dit=dit, vae=vae, image_encoder=clip, text_embeddings=text,
                               image_preprocess=preprocess, weights=weights, prompt=prompt,
                               negative_prompt=negative_prompt, sources={**sources, **encoders})


# --------------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------------
def check_video_shape(num_frames: int, height: int, width: int, patch: tuple[int, int] = (2, 2),
                      spatial: int = 8, temporal: int = 4) -> None:
    if num_frames < temporal + 1 or (num_frames - 1) % temporal:
        raise ValueError(f"num_frames must be {temporal}k+1 with k >= 1 (Wan VAE), got {num_frames}")
    mh, mw = spatial * patch[0], spatial * patch[1]
    if height % mh or width % mw:
        raise ValueError(f"height and width must be multiples of {mh}x{mw} (VAE x patch), got {height}x{width}")


class _DitGraph(nn.Module):
    """Positional signature of the DiT graph (``camcontrol.DIT_INPUTS``)."""

    def __init__(self, dit: nn.Module) -> None:
        super().__init__()
        self.dit = dit

    def forward(self, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker, cond,
                lora_scale, image_reference, image_reference_plucker):
        return self.dit(hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker, cond,
                        lora_scale, image_reference, image_reference_plucker)


@dataclass(frozen=True)
class _Shapes:
    num_frames: int
    height: int
    width: int
    latent_frames: int
    latent_height: int
    latent_width: int
    spatial: int
    image_tokens: int
    image_size: int
    dynamic: bool


def _export_one(name: str, module: nn.Module, out: Path, sh: _Shapes):
    """Export one graph."""
    from torch.export import Dim

    # deferred: diffusers loads with camcontrol only when the camera-controlled DiT is built or read
    from navcrafter.models.synthesis.camcontrol import DIT_INPUTS, DIT_OUTPUTS, example_inputs, export_dit

    dyn = sh.dynamic
    batch = Dim("batch", min=1, max=64)
    hh, ww = Dim("latent_height", min=1, max=1024), Dim("latent_width", min=1, max=1024)
    if name == "dit" and getattr(module, "model_name", "navcrafter") == "fun-camera":
        # deferred: diffusers loads with funcamera only for the fun-camera model
        from navcrafter.models.synthesis.funcamera import export_fun_camera_dit

        p_h, p_w = module.config.patch_size[1:]
        example = ((2, 2, min(sh.latent_height, 2 * p_h), min(sh.latent_width, 2 * p_w)) if dyn
                   else (2, sh.latent_frames, sh.latent_height, sh.latent_width))
        return export_fun_camera_dit(module, out / "dit.onnx", example_shape=example, image_tokens=sh.image_tokens,
                                     dynamic=dyn)
    if name == "dit":
        if dyn:  # camcontrol's exporter; example = one CFG pair at a small size
            p_h, p_w = module.base.config.patch_size[1:]
            example = (2, 2, min(sh.latent_height, 2 * p_h), min(sh.latent_width, 2 * p_w))
            return export_dit(module, out / "dit.onnx", example_shape=example, image_tokens=sh.image_tokens)
        inputs = example_inputs(module, (2, sh.latent_frames, sh.latent_height, sh.latent_width), sh.image_tokens,
                                reference_images=1)  # the sampler's one extra reference frame
        info = export_graph(_DitGraph(module).eval(), tuple(inputs.get(n) for n in DIT_INPUTS), out / "dit.onnx",
                            input_names=[n for n in DIT_INPUTS if n in inputs], output_names=list(DIT_OUTPUTS))
        info.notes = (f"static shapes: batch 2, {sh.latent_frames} latent frames, "
                      f"{sh.latent_height}x{sh.latent_width} latents, 1 extra reference frame")
        return info
    if name == "vae_encoder":
        video = torch.zeros(2, 3, sh.num_frames, sh.height, sh.width)
        info = export_graph(VaeEncoder(module).eval(), (video,), out / "vae_encoder.onnx", input_names=["video"],
                            output_names=["latents"],
                            dynamic_shapes=({0: batch, 3: sh.spatial * hh, 4: sh.spatial * ww},) if dyn else None)
        info.notes = f"fixed frame count {sh.num_frames} (unrolled causal chunks)"
        return info
    if name == "vae_decoder":
        lat = torch.zeros(2 if dyn else 1, module.config.z_dim, sh.latent_frames, sh.latent_height, sh.latent_width)
        info = export_graph(VaeDecoder(module).eval(), (lat,), out / "vae_decoder.onnx", input_names=["latents"],
                            output_names=["video"], dynamic_shapes=({0: batch, 3: hh, 4: ww},) if dyn else None)
        info.notes = f"fixed latent frame count {sh.latent_frames} (video frames {sh.num_frames})"
        return info
    if name == "image_encoder":
        pix = torch.zeros(2 if dyn else 1, 3, sh.image_size, sh.image_size)
        info = export_graph(ClipImageFeatures(module).eval(), (pix,), out / "image_encoder.onnx",
                            input_names=["pixel_values"], output_names=["image_embeds"],
                            dynamic_shapes=({0: batch},) if dyn else None)
        info.notes = "CLIPVisionModel hidden_states[-2] (Wan I2V image features)"
        return info
    raise ValueError(f"unknown graph {name!r}")


def export_components(components: SynthesisComponents, out_dir: str | Path, *, num_frames: int, height: int,
                      width: int, dynamic: bool = True) -> Path:
    """Export ``components`` into ``out_dir`` (graphs, text embeddings, manifest last).

    ``dynamic=True``: the DiT has dynamic batch, latent frames, height and width (``camcontrol.export_dit``), the
    VAE graphs dynamic batch, height and width (frames fixed, see the module docstring), CLIP dynamic batch.
    ``dynamic=False``: every graph is exported for exactly the sampler's shapes at ``num_frames x height x
    width`` (DiT batch 2 = one CFG pair, VAE encoder batch 2, decoder and CLIP batch 1); several times faster to
    export (tests), but the model then only runs at that size.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / MANIFEST).unlink(missing_ok=True)  # a directory with a manifest is a finished export (written last)
    patch = tuple(components.dit.base.config.patch_size)
    st = int(components.vae.config.scale_factor_temporal)
    ss = int(components.vae.config.scale_factor_spatial)
    check_video_shape(num_frames, height, width, patch[1:], ss, st)
    sh = _Shapes(num_frames, height, width, (num_frames - 1) // st + 1, height // ss, width // ss, ss,
                 _image_tokens(components), int(components.image_preprocess["image_size"]), bool(dynamic))
    tasks = [("dit", components.dit), ("vae_encoder", components.vae), ("vae_decoder", components.vae),
             ("image_encoder", components.image_encoder)]
    graphs = {name: _export_one(name, module, out, sh) for name, module in tasks}
    np.save(out / TEXT_EMBEDDINGS, np.ascontiguousarray(components.text_embeddings, dtype=np.float32))
    config = components.config(num_frames, height, width, dynamic)
    architecture = ARCHITECTURE
    if getattr(components.dit, "model_name", "navcrafter") == "fun-camera":
        # deferred: diffusers loads with funcamera only for the fun-camera model
        from navcrafter.models.synthesis.funcamera import ARCHITECTURE as architecture
    write_manifest(out, kind=KIND, architecture=architecture, config=config, weights=components.weights,
                   graphs=graphs, extra_files=[TEXT_EMBEDDINGS])
    return out


def _image_tokens(components: SynthesisComponents) -> int:
    c = components.image_encoder.config
    return (c.image_size // c.patch_size) ** 2 + 1


def export_synthesizer(out_dir: str | Path, *, base_dir: str | Path | None = None,
                       control_dir: str | Path | None = None, tiny: bool = False, num_frames: int, height: int,
                       width: int, prompt: str = "", negative_prompt: str = DEFAULT_NEGATIVE_PROMPT, seed: int = 0,
                       dynamic: bool | None = None) -> Path:
    """Build (tiny random or from ``base_dir``/``control_dir``) and export the synthesizer to ``out_dir``.

    ``num_frames`` (4k+1), ``height`` and ``width`` (multiples of 16) are what the VAE graphs are exported for
    and what ``OnnxSynthesizer`` accepts (``synthesis.num_frames/height/width`` of the run config must match).
    ``dynamic``: dynamic-shape graphs (see ``export_components``); default True for checkpoints and False for
    ``tiny`` (tiny models serve tests, which only run at the exported size, and static graphs export ~3x faster:
    ~70 s instead of ~3 min of CPU time for 5 frames at 32x32 on a 2-core machine).
    """
    if tiny == (base_dir is not None):
        raise ValueError("export_synthesizer: pass exactly one of tiny=True or base_dir=...")
    if tiny:
        components = tiny_components(seed, prompt, negative_prompt, control_dir=control_dir)
    else:
        components = load_components(base_dir, control_dir, prompt, negative_prompt)
    return export_components(components, out_dir, num_frames=num_frames, height=height, width=width,
                             dynamic=(not tiny) if dynamic is None else bool(dynamic))


def export_fun_camera_synthesizer(out_dir: str | Path, *, checkpoint_dir: str | Path | None = None,
                                  base_dir: str | Path | None = None, tiny: bool = False, num_frames: int,
                                  height: int, width: int, prompt: str = "",
                                  negative_prompt: str = DEFAULT_NEGATIVE_PROMPT, seed: int = 0,
                                  dynamic: bool | None = None) -> Path:
    """The fun-camera synthesizer (``funcamera/``) exported to ``out_dir`` like ``export_synthesizer``: tiny random
    (``tiny=True``) or the official DiT in ``checkpoint_dir`` with the encoders of the diffusers Wan2.1 I2V
    ``base_dir``. Manifest architecture ``wan2.1-fun-v1.1-control-camera``, ``config.model = "fun-camera"``."""
    if tiny == (checkpoint_dir is not None):
        raise ValueError("export_fun_camera_synthesizer: pass exactly one of tiny=True or checkpoint_dir=...")
    if tiny:
        components = tiny_fun_camera_components(seed, prompt, negative_prompt)
    else:
        if base_dir is None:
            raise ValueError("export_fun_camera_synthesizer: checkpoint_dir needs base_dir, a diffusers-format "
                             "Wan2.1 I2V directory for the VAE, CLIP image encoder and UMT5 text encoder")
        components = load_fun_camera_components(checkpoint_dir, base_dir, prompt, negative_prompt)
    return export_components(components, out_dir, num_frames=num_frames, height=height, width=width,
                             dynamic=(not tiny) if dynamic is None else bool(dynamic))

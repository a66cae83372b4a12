"""Difix configuration (``DifixConfig``: the SD-Turbo preset and tiny test configs), file, graph and manifest names."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from navcrafter.models.runtime.onnxio import config_from_dict, config_to_dict

ARCHITECTURE = "difix"
KIND = "refiner"
GRAPH = "refiner"
DEFAULT_PROMPT = "remove degradation"
PROMPT_FILE = "prompt_embeds.npy"
LORA_ADAPTER = "vae_skip"


# the official target_modules_vae suffixes (src/model.py), matched against decoder module names
LORA_TARGET_SUFFIXES = ("conv1", "conv2", "conv_in", "conv_shortcut", "conv", "conv_out", "skip_conv_1",
                        "skip_conv_2", "skip_conv_3", "skip_conv_4", "to_k", "to_q", "to_v", "to_out.0")
UNET_FILE = "unet/diffusion_pytorch_model.safetensors"
VAE_FILE = "vae/diffusion_pytorch_model.safetensors"
KEYS_DIR = Path(__file__).parents[1] / "keys"
OFFICIAL_KEYS_SD_TURBO = KEYS_DIR / "difix_sd_turbo.txt"
INPUTS = ("image", "reference", "prompt_embeds", "latent_noise")
OUTPUT = "refined"
MAX_SIDE = 2048  # largest exported image side


class DifixWeightsError(ValueError):
    """A checkpoint does not match the Difix model it is loaded into."""


@dataclass(frozen=True)
class DifixConfig:
    """Sizes and constants of a Difix network. Defaults are the published SD-Turbo-based model with reference
    mixing (``nvidia/difix_ref``)."""

    # UNet2DConditionModel (SD-Turbo = SD 2.1 UNet; CrossAttn down blocks except the last, mirrored up blocks)
    unet_block_out_channels: tuple[int, ...] = (320, 640, 1280, 1280)
    unet_layers_per_block: int = 2
    unet_attention_heads: tuple[int, ...] = (5, 10, 20, 20)  # diffusers' (misnamed) ``attention_head_dim``
    cross_attention_dim: int = 1024
    unet_norm_num_groups: int = 32
    use_linear_projection: bool = True
    # AutoencoderKL (SD-Turbo's VAE)
    vae_block_out_channels: tuple[int, ...] = (128, 256, 512, 512)
    vae_layers_per_block: int = 2
    vae_norm_num_groups: int = 32
    latent_channels: int = 4
    scaling_factor: float = 0.18215
    # Difix additions: decoder LoRA (peft) and encoder->decoder skip connections
    lora_rank: int = 4
    lora_alpha: float = 8.0
    skip_gamma: float = 1.0
    reference_mixing: bool = True  # nvidia/difix_ref (True) or nvidia/difix (False)
    # one DDPM step from `timestep` (SD-Turbo's scheduler config)
    timestep: int = 199
    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012
    prediction_type: str = "epsilon"
    # text conditioning: CLIP hidden states of the padded prompt
    text_tokens: int = 77

    def __post_init__(self) -> None:
        problems = []
        if len(self.unet_attention_heads) != len(self.unet_block_out_channels):
            problems.append("unet_attention_heads needs one entry per UNet block")
        if any(c % h for c, h in zip(self.unet_block_out_channels, self.unet_attention_heads)):
            problems.append("UNet block channels must be divisible by their number of heads")
        if len(self.unet_block_out_channels) < 2 or len(self.vae_block_out_channels) < 2:
            problems.append("the UNet and the VAE need at least two blocks")
        if any(c % self.unet_norm_num_groups for c in self.unet_block_out_channels):
            problems.append("UNet channels must be divisible by unet_norm_num_groups")
        if any(c % self.vae_norm_num_groups for c in self.vae_block_out_channels):
            problems.append("VAE channels must be divisible by vae_norm_num_groups")
        if self.lora_rank < 1:
            problems.append("lora_rank must be >= 1")
        if not 0 <= self.timestep < self.num_train_timesteps:
            problems.append("timestep must lie in [0, num_train_timesteps)")
        if self.prediction_type not in ("epsilon", "v_prediction", "sample"):
            problems.append("prediction_type must be epsilon, v_prediction or sample")
        if problems:
            raise ValueError("invalid DifixConfig: " + "; ".join(problems))

    @classmethod
    def sd_turbo(cls, reference_mixing: bool = True) -> DifixConfig:
        """The published model: SD-Turbo UNet and VAE, LoRA rank 4, t = 199; ``reference_mixing`` selects
        ``nvidia/difix_ref`` (True) or ``nvidia/difix`` (False)."""
        return cls(reference_mixing=reference_mixing)

    @classmethod
    def tiny(cls, reference_mixing: bool = True) -> DifixConfig:
        """A few-kB random model for tests (same structure with 2-block UNet and VAE, LoRA rank 2; its dynamic
        ONNX export takes ~40 s on a busy 2-core machine, twice that with the 4-block VAE)."""
        return cls(unet_block_out_channels=(8, 16), unet_layers_per_block=1, unet_attention_heads=(2, 2),
                   cross_attention_dim=8, unet_norm_num_groups=4, vae_block_out_channels=(8, 16),
                   vae_layers_per_block=1, vae_norm_num_groups=4, lora_rank=2, reference_mixing=reference_mixing)

    @property
    def num_views(self) -> int:
        return 2 if self.reference_mixing else 1

    @property
    def vae_scale_factor(self) -> int:
        return 2 ** (len(self.vae_block_out_channels) - 1)

    @property
    def size_multiple(self) -> int:
        """Image sides must be multiples of this: the VAE's factor times the UNet's total downsampling."""
        return self.vae_scale_factor * 2 ** (len(self.unet_block_out_channels) - 1)

    def unet_kwargs(self) -> dict[str, Any]:
        n = len(self.unet_block_out_channels)
        return {"sample_size": 64, "in_channels": self.latent_channels, "out_channels": self.latent_channels,
                "down_block_types": ("CrossAttnDownBlock2D",) * (n - 1) + ("DownBlock2D",),
                "up_block_types": ("UpBlock2D",) + ("CrossAttnUpBlock2D",) * (n - 1),
                "block_out_channels": tuple(self.unet_block_out_channels),
                "layers_per_block": self.unet_layers_per_block,
                "attention_head_dim": tuple(self.unet_attention_heads),
                "cross_attention_dim": self.cross_attention_dim, "norm_num_groups": self.unet_norm_num_groups,
                "use_linear_projection": self.use_linear_projection}

    def vae_kwargs(self) -> dict[str, Any]:
        n = len(self.vae_block_out_channels)
        return {"in_channels": 3, "out_channels": 3, "down_block_types": ("DownEncoderBlock2D",) * n,
                "up_block_types": ("UpDecoderBlock2D",) * n, "block_out_channels": tuple(self.vae_block_out_channels),
                "layers_per_block": self.vae_layers_per_block, "latent_channels": self.latent_channels,
                "norm_num_groups": self.vae_norm_num_groups, "scaling_factor": self.scaling_factor}

    def alpha_cumprod(self) -> float:
        """``alphas_cumprod[timestep]`` of diffusers' scaled-linear DDPM schedule (float32, as the scheduler)."""
        betas = torch.linspace(self.beta_start ** 0.5, self.beta_end ** 0.5, self.num_train_timesteps,
                               dtype=torch.float32, device="cpu") ** 2
        return float(torch.cumprod(1.0 - betas, dim=0)[self.timestep])

    def to_dict(self) -> dict[str, Any]:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DifixConfig:
        return config_from_dict(cls, data)

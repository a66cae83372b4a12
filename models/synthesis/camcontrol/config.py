"""Camera-control configuration: ``CameraControlConfig``, the Wan2.1 base configs (tiny, 1.3B-width, 14B), file
and graph names."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from navcrafter.models.camera.cameras import PLUCKER_CONVENTIONS, PluckerConvention

VAE_STRIDE = (4, 8, 8)  # Wan2.1 VAE: time, height, width
LATENT_CHANNELS = 16  # Wan2.1 VAE latent channels
TEXT_TOKENS = 512  # diffusers' Wan I2V path splits image/text tokens at `shape[1] - 512`
CONTROL_WEIGHTS = "camera_control.safetensors"
CONTROL_CONFIG = "camera_control.json"
CONTROL_FORMAT = "navcrafter-camera-control"
CONTROL_FORMAT_VERSION = 2  # 2: low-rank pre_proj/attn_proj (projection_rank); 1: full Linear(D, D)
READABLE_FORMAT_VERSIONS = (1, 2)


# what a version-1 config lacks, as version 1 built it
_V1_DEFAULTS: dict[str, Any] = {"projection_rank": 0, "plucker_convention": "paper"}
DIT_INPUTS = ["hidden_states", "timestep", "encoder_hidden_states", "encoder_hidden_states_image", "plucker",
              "cond", "lora_scale", "image_reference", "image_reference_plucker"]
DIT_OUTPUTS = ["noise_pred"]


# Tiny random Wan2.1 I2V config for tests (see shared/FACTS.md): 2 heads x 12 dims, 2 layers.
TINY_I2V_CONFIG: dict[str, Any] = {
    "patch_size": (1, 2, 2), "num_attention_heads": 2, "attention_head_dim": 12, "in_channels": 36,
    "out_channels": 16, "text_dim": 32, "freq_dim": 256, "ffn_dim": 32, "num_layers": 2, "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads", "eps": 1e-6, "image_dim": 4, "added_kv_proj_dim": 24,
    "rope_max_seq_len": 32,
}


# Wan2.1-1.3B width with the I2V input layout (Wan2.1 has no official 1.3B I2V checkpoint; this is what a
# 1.3B-width I2V/camera model looks like). diffusers needs added_kv_proj_dim == inner_dim (12*128 = 1536):
# add_k_proj/add_v_proj act on the CLIP tokens *after* the condition embedder projected them to inner_dim.
WAN_1_3B_I2V_CONFIG: dict[str, Any] = {
    "patch_size": (1, 2, 2), "num_attention_heads": 12, "attention_head_dim": 128, "in_channels": 36,
    "out_channels": 16, "text_dim": 4096, "freq_dim": 256, "ffn_dim": 8960, "num_layers": 30, "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads", "eps": 1e-6, "image_dim": 1280, "added_kv_proj_dim": 1536,
    "rope_max_seq_len": 1024,
}


# Wan2.1-I2V-14B (the diffusers transformer config of Wan-AI/Wan2.1-I2V-14B-*-Diffusers): 40 heads x 128 = 5120,
# 40 layers; added_kv_proj_dim == inner_dim as above.
WAN_14B_I2V_CONFIG: dict[str, Any] = {
    "patch_size": (1, 2, 2), "num_attention_heads": 40, "attention_head_dim": 128, "in_channels": 36,
    "out_channels": 16, "text_dim": 4096, "freq_dim": 256, "ffn_dim": 13824, "num_layers": 40, "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads", "eps": 1e-6, "image_dim": 1280, "added_kv_proj_dim": 5120,
    "rope_max_seq_len": 1024,
}


class CameraControlWeightsError(ValueError):
    """Camera-control weights do not fit the model (file, keys and shapes are named in the message)."""


TRAINING_LORA_SCALE = 1.0  # the camera LoRA's strength while it is trained (inference: CameraControlConfig.lora_scale)


@dataclass
class CameraControlConfig:
    """Hyper-parameters of the camera-control modules (the base DiT's sizes come from the base config).

    ``adapter_channels``/``adapter_res_blocks``: width/depth of the camera adapter A.
    ``lora_in_channels`` (``r_in``) and ``lora_rank``: the LoRA control encoder width and the LoRA rank.
    ``lora_scale``: default ``α`` at inference when the caller passes none (the paper's 0.7; the sampler passes
    ``synthesis.lora_scale`` explicitly); in training mode the default is ``TRAINING_LORA_SCALE`` (1.0).
    ``cond_channels``: extra patch-embedding channels (16 render latents + 4 packed visibility mask).
    ``num_reference_frames``: reference frames drawn per training sample (frame 0 included).
    ``inference_reference_frames``: reference latent frames at inference (baked into an export).
    ``reference_seed``: seed of the training-time reference-frame generator.
    ``projection_rank``: rank ``r`` of the per-block ``pre_proj``/``attn_proj`` (``D -> r -> D``, capped at the
    DiT width ``D``); ``0`` = full ``Linear(D, D)`` (format-version-1 weights; a saved config without the field
    loads as 0).
    ``plucker_convention``: how the Plücker rays were computed (``models.camera.cameras.plucker_rays``:
    ``"relative"`` (default), ``"ray"`` or ``"paper"``); recorded so the weights are always run with the
    convention they were trained with (saved configs keep the one they record).
    """

    adapter_channels: int = 64
    adapter_res_blocks: int = 1
    lora_in_channels: int = 32
    lora_rank: int = 16
    lora_scale: float = 0.7
    cond_channels: int = 20
    num_reference_frames: int = 2
    inference_reference_frames: tuple[int, ...] = (0,)
    reference_seed: int = 0
    projection_rank: int = 64
    plucker_convention: PluckerConvention = "relative"  # models.camera.cameras.plucker_rays default
    latent_channels: int = LATENT_CHANNELS
    vae_stride: tuple[int, int, int] = VAE_STRIDE
    extra: dict[str, Any] = field(default_factory=dict)  # free-form notes (training run, data, ...)

    def __post_init__(self) -> None:
        self.inference_reference_frames = tuple(int(i) for i in self.inference_reference_frames)
        self.vae_stride = tuple(int(s) for s in self.vae_stride)
        if self.plucker_convention not in PLUCKER_CONVENTIONS:
            raise ValueError(f"plucker_convention must be one of {list(PLUCKER_CONVENTIONS)}, "
                             f"got {self.plucker_convention!r}")
        if int(self.projection_rank) < 0:
            raise ValueError(f"projection_rank must be >= 0 (0 = full D x D projections), got {self.projection_rank}")
        for name in ("adapter_channels", "lora_in_channels", "lora_rank", "latent_channels"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.cond_channels < 0 or self.adapter_res_blocks < 0 or self.num_reference_frames < 0:
            raise ValueError("cond_channels, adapter_res_blocks and num_reference_frames must be >= 0")
        if self.inference_reference_frames and min(self.inference_reference_frames) < 0:
            raise ValueError(f"inference_reference_frames must be >= 0, got {self.inference_reference_frames}")
        if len(self.vae_stride) != 3:
            raise ValueError(f"vae_stride must have 3 entries (t, h, w), got {self.vae_stride}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["inference_reference_frames"] = list(self.inference_reference_frames)
        d["vae_stride"] = list(self.vae_stride)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraControlConfig:
        """A saved config. One without ``projection_rank`` predates low-rank projections: it loads as 0."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown CameraControlConfig keys {unknown}; known: {sorted(known)}")
        return cls(**{"projection_rank": 0, **d})


def tiny_camera_config() -> CameraControlConfig:
    """Tiny test control (``projection_rank`` 64, capped at the tiny DiT's width 24)."""
    return CameraControlConfig(adapter_channels=16, adapter_res_blocks=1, lora_in_channels=8, lora_rank=4,
                               num_reference_frames=2)


def wan_1_3b_camera_config() -> tuple[dict[str, Any], CameraControlConfig]:
    """(base ``WanTransformer3DModel`` kwargs at Wan2.1-1.3B width with I2V inputs, control config).

    Build with random weights: ``build_camera_wan(*wan_1_3b_camera_config(), device="cuda")``.
    Rank-128 projections: 47 M control parameters, 3.0 % of the 1.56 B base (full-rank ones are 142 M at D=1536,
    30 layers: 165 M, 10.6 %, with the encoders); see ``control_parameter_counts`` and models/synthesis/README.md.
    """
    return dict(WAN_1_3B_I2V_CONFIG), CameraControlConfig(adapter_channels=320, adapter_res_blocks=2,
                                                          lora_in_channels=128, lora_rank=64,
                                                          projection_rank=128, num_reference_frames=3)


def wan_14b_camera_config() -> tuple[dict[str, Any], CameraControlConfig]:
    """(Wan2.1-I2V-14B base kwargs, control config): rank-256 projections, 266 M control parameters, 1.6 % of the
    16.4 B base (full-rank ones are 2.10 B: 2.15 B, 13.1 %, in all). Counts: ``control_parameter_counts``."""
    return dict(WAN_14B_I2V_CONFIG), CameraControlConfig(adapter_channels=320, adapter_res_blocks=2,
                                                         lora_in_channels=128, lora_rank=64,
                                                         projection_rank=256, num_reference_frames=3)

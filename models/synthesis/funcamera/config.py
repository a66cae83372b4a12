"""Fun-Camera configuration: ``FunCameraConfig`` (from and to the official ``config.json``), names of the files, the
manifest entries and the graph."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MODEL_NAME = "fun-camera"  # synthesis.model
ARCHITECTURE = "wan2.1-fun-v1.1-control-camera"  # manifest architecture
PLUCKER_CONVENTION = "videox-fun"  # manifest config.plucker_convention (fun_camera_plucker)
CONDITION_LAYOUT = "fun-camera"  # manifest config.condition_layout (pipeline.prepare_conditions)
OFFICIAL_CONFIG = "config.json"
OFFICIAL_WEIGHTS = "diffusion_pytorch_model.safetensors"
OFFICIAL_INDEX = "diffusion_pytorch_model.safetensors.index.json"
KEY_LIST_1_3B = Path(__file__).parents[1] / "keys" / "fun_camera_1_3b.json"
VAE_STRIDE = (4, 8, 8)
LATENT_CHANNELS = 16
TEXT_TOKENS = 512
PLUCKER_CHANNELS = 6
FUN_DIT_INPUTS = ["hidden_states", "timestep", "encoder_hidden_states", "encoder_hidden_states_image", "plucker"]
FUN_DIT_OUTPUTS = ["noise_pred"]


class FunCameraWeightsError(ValueError):
    """A Fun-Camera checkpoint does not fit (file, missing / unexpected / wrong-shape keys and the fix are named)."""


@dataclass
class FunCameraConfig:
    """Sizes of a Fun-Camera DiT, named after the official ``config.json`` fields (``official_config``).

    ``image_dim``: CLIP feature width (the official ``MLPProj(1280, dim)`` hard-codes 1280; tiny test configs
    shrink it). ``in_dim_control_adapter``: packed ray channels (6 Plücker x 4 frames); ``downscale_factor``: the
    adapter's ``PixelUnshuffle`` factor (the VAE's spatial stride); ``adapter_residual_blocks``: 1 in the official
    code (``SimpleAdapter``'s default, not exposed in its config).
    """

    dim: int = 1536
    ffn_dim: int = 8960
    num_heads: int = 12
    num_layers: int = 30
    in_dim: int = 32
    out_dim: int = 16
    text_dim: int = 4096
    freq_dim: int = 256
    image_dim: int = 1280
    eps: float = 1e-6
    patch_size: tuple[int, int, int] = (1, 2, 2)
    text_len: int = TEXT_TOKENS
    in_dim_control_adapter: int = 24
    downscale_factor_control_adapter: int = 8
    adapter_residual_blocks: int = 1
    rope_max_seq_len: int = 1024  # the official rope_params(1024, ...)

    def __post_init__(self) -> None:
        self.patch_size = tuple(int(p) for p in self.patch_size)
        if self.dim % self.num_heads or (self.dim // self.num_heads) % 2:
            raise ValueError(f"dim {self.dim} must split into {self.num_heads} heads of even size")
        if self.in_dim_control_adapter % PLUCKER_CHANNELS:
            raise ValueError(f"in_dim_control_adapter must be 6 Plücker channels x frames per latent frame, got "
                             f"{self.in_dim_control_adapter}")
        if self.in_dim != 2 * LATENT_CHANNELS:
            raise ValueError(f"in_dim must be 32 (16 noisy + 16 start-image latents: the Control-Camera layout), "
                             f"got {self.in_dim}")

    @property
    def temporal_packing(self) -> int:
        return self.in_dim_control_adapter // PLUCKER_CHANNELS

    @classmethod
    def tiny(cls) -> FunCameraConfig:
        """Test size: 2 heads x 12, 2 layers (the tiny VAE's spatial stride is 8 as well)."""
        return cls(dim=24, ffn_dim=32, num_heads=2, num_layers=2, text_dim=32, image_dim=4, rope_max_seq_len=32)

    @classmethod
    def wan_1_3b(cls) -> FunCameraConfig:
        """Wan2.1-Fun-V1.1-1.3B-Control-Camera (``keys/fun_camera_1_3b.json``)."""
        return cls()

    @classmethod
    def wan_14b(cls) -> FunCameraConfig:
        """Wan2.1-Fun-V1.1-14B-Control-Camera (Wan2.1-14B sizes: 40 heads x 128, 40 layers, ffn 13824)."""
        return cls(dim=5120, ffn_dim=13824, num_heads=40, num_layers=40)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["patch_size"] = list(self.patch_size)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FunCameraConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown FunCameraConfig keys {unknown}; known: {sorted(known)}")
        return cls(**d)

    def diffusers_kwargs(self) -> dict[str, Any]:
        """``WanTransformer3DModel`` kwargs of the base (I2V: ``added_kv_proj_dim`` = the width, see camcontrol)."""
        return {"patch_size": self.patch_size, "num_attention_heads": self.num_heads,
                "attention_head_dim": self.dim // self.num_heads, "in_channels": self.in_dim,
                "out_channels": self.out_dim, "text_dim": self.text_dim, "freq_dim": self.freq_dim,
                "ffn_dim": self.ffn_dim, "num_layers": self.num_layers, "cross_attn_norm": True,
                "qk_norm": "rms_norm_across_heads", "eps": self.eps, "image_dim": self.image_dim,
                "added_kv_proj_dim": self.dim, "rope_max_seq_len": self.rope_max_seq_len}

    def official_config(self) -> dict[str, Any]:
        """The ``config.json`` of the official transformer folder (fields ``WanTransformer3DModel.__init__`` of
        wan_transformer3d.py reads; ``image_dim`` is a navcrafter extension, written only when it is not 1280)."""
        d: dict[str, Any] = {"_class_name": "WanTransformer3DModel", "model_type": "i2v",
                             "patch_size": list(self.patch_size), "text_len": self.text_len, "in_dim": self.in_dim,
                             "dim": self.dim, "ffn_dim": self.ffn_dim, "freq_dim": self.freq_dim,
                             "text_dim": self.text_dim, "out_dim": self.out_dim, "num_heads": self.num_heads,
                             "num_layers": self.num_layers, "window_size": [-1, -1], "qk_norm": True,
                             "cross_attn_norm": True, "eps": self.eps, "add_control_adapter": True,
                             "in_dim_control_adapter": self.in_dim_control_adapter,
                             "downscale_factor_control_adapter": self.downscale_factor_control_adapter,
                             "add_ref_conv": False}
        if self.image_dim != 1280:
            d["image_dim"] = self.image_dim
        if self.adapter_residual_blocks != 1:
            d["adapter_residual_blocks"] = self.adapter_residual_blocks
        if self.rope_max_seq_len != 1024:
            d["rope_max_seq_len"] = self.rope_max_seq_len
        return d

    @classmethod
    def from_official_config(cls, d: dict[str, Any], source: str = "config.json") -> FunCameraConfig:
        """Parse an official ``config.json`` (defaults as the official constructor's); refuses what this module
        does not build, naming the field."""
        def get(name, default):
            return d.get(name, default)

        problems = []
        if get("model_type", "t2v") != "i2v":
            problems.append(f"model_type {get('model_type', 't2v')!r} (the Control-Camera checkpoints are 'i2v')")
        if not get("add_control_adapter", False):
            problems.append("add_control_adapter is false (no camera adapter: not a Control-Camera checkpoint)")
        if get("add_ref_conv", False):
            problems.append("add_ref_conv is true (the full-reference conv of Fun-Control-Ref is not built)")
        if list(get("window_size", (-1, -1))) != [-1, -1]:
            problems.append(f"window_size {get('window_size', None)} (only global attention is built)")
        if not get("qk_norm", True) or not get("cross_attn_norm", True):
            problems.append("qk_norm / cross_attn_norm false (Wan2.1 uses both)")
        if get("cross_attn_type", None) not in (None, "i2v_cross_attn"):
            problems.append(f"cross_attn_type {get('cross_attn_type', None)!r}")
        if problems:
            raise FunCameraWeightsError(f"{source}: not a Wan2.1-Fun Control-Camera config this module builds: "
                                        + "; ".join(problems))
        try:
            return cls(dim=int(get("dim", 2048)), ffn_dim=int(get("ffn_dim", 8192)),
                       num_heads=int(get("num_heads", 16)), num_layers=int(get("num_layers", 32)),
                       in_dim=int(get("in_dim", 16)), out_dim=int(get("out_dim", 16)),
                       text_dim=int(get("text_dim", 4096)), freq_dim=int(get("freq_dim", 256)),
                       image_dim=int(get("image_dim", 1280)), eps=float(get("eps", 1e-6)),
                       patch_size=tuple(get("patch_size", (1, 2, 2))), text_len=int(get("text_len", 512)),
                       in_dim_control_adapter=int(get("in_dim_control_adapter", 24)),
                       downscale_factor_control_adapter=int(get("downscale_factor_control_adapter", 8)),
                       adapter_residual_blocks=int(get("adapter_residual_blocks", 1)),
                       rope_max_seq_len=int(get("rope_max_seq_len", 1024)))
        except ValueError as exc:
            raise FunCameraWeightsError(f"{source}: {exc}") from exc

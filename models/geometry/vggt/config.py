"""VGGT configuration (``VGGTConfig``: the VGGT-1B preset and tiny test configs), output names and the committed
key list."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

_RESNET_MEAN = (0.485, 0.456, 0.406)
_RESNET_STD = (0.229, 0.224, 0.225)
OUTPUT_NAMES = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")
IGNORED_PREFIXES = ("track_head.",)  # official checkpoint parts we do not build
KEY_LIST_1B = Path(__file__).parents[1] / "keys" / "vggt_1b.txt"


@dataclass
class VGGTConfig:
    """Sizes of a VGGT network. ``vggt_1b()`` is the published model, ``tiny()`` a test-sized one."""

    img_size: int = 518  # training resolution: sets the DINOv2 position table ((img_size / patch)^2 + 1)
    patch_size: int = 14
    embed_dim: int = 1024
    depth: int = 24  # alternating-attention rounds (frame + global block each)
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    rope_freq: float = 100.0
    init_values: float = 0.01  # layer-scale init of aggregator and camera-head blocks
    # DINOv2 patch embedding (ViT-L/14 with registers; its width is embed_dim)
    encoder_depth: int = 24
    encoder_heads: int = 16
    encoder_mlp_ratio: int = 4
    # camera head
    camera_trunk_depth: int = 4
    camera_heads: int = 16
    camera_iterations: int = 4
    # DPT heads
    dpt_features: int = 256
    dpt_out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024)
    dpt_layers: tuple[int, int, int, int] = (4, 11, 17, 23)
    extra: dict = field(default_factory=dict)  # free-form notes (kept in manifests)

    def __post_init__(self) -> None:
        self.dpt_out_channels = tuple(int(c) for c in self.dpt_out_channels)
        self.dpt_layers = tuple(int(i) for i in self.dpt_layers)
        if len(self.dpt_out_channels) != 4 or len(self.dpt_layers) != 4:
            raise ValueError("dpt_out_channels and dpt_layers need 4 entries each")
        if any(not 0 <= i < self.depth for i in self.dpt_layers):
            raise ValueError(f"dpt_layers {self.dpt_layers} must index the {self.depth} aggregator rounds")
        if self.embed_dim % self.num_heads or (self.embed_dim // self.num_heads) % 4:
            raise ValueError("embed_dim / num_heads must be a multiple of 4 (2D RoPE)")
        if self.img_size % self.patch_size:
            raise ValueError(f"img_size {self.img_size} must be a multiple of patch_size {self.patch_size}")

    @classmethod
    def vggt_1b(cls) -> VGGTConfig:
        return cls()

    @classmethod
    def tiny(cls) -> VGGTConfig:
        # one aggregator round (every DPT branch reads it) keeps the test export small; two refinement
        # iterations keep the camera head's feedback path in the graph
        return cls(img_size=56, patch_size=14, embed_dim=32, depth=1, num_heads=2, num_register_tokens=4,
                   encoder_depth=1, encoder_heads=2, camera_trunk_depth=1, camera_heads=2, camera_iterations=2,
                   dpt_features=16, dpt_out_channels=(8, 16, 32, 32), dpt_layers=(0, 0, 0, 0))

    @classmethod
    def from_dict(cls, d: dict) -> VGGTConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

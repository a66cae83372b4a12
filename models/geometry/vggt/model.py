"""``VGGT``: aggregator, camera head and DPT heads, from images ``[B, S, 3, H, W]`` to the official outputs."""

from __future__ import annotations

import torch
from torch import nn

from navcrafter.models.geometry.vggt.config import VGGTConfig
from navcrafter.models.geometry.vggt.heads import CameraHead, DPTHeads
from navcrafter.models.geometry.vggt.modules import Aggregator


class VGGT(nn.Module):
    """VGGT without the track head. ``forward(images [B, S, 3, H, W] in [0, 1])`` → dict of
    ``pose_enc`` [B, S, 9], ``depth`` [B, S, H, W, 1], ``depth_conf`` [B, S, H, W],
    ``world_points`` [B, S, H, W, 3], ``world_points_conf`` [B, S, H, W] (H, W multiples of the patch)."""

    def __init__(self, config: VGGTConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or VGGTConfig()
        self.aggregator = Aggregator(config)
        self.camera_head = CameraHead(config)
        self.dpt_heads = DPTHeads(config)  # official point_head + depth_head
        self._keep = tuple(sorted(set(config.dpt_layers) | {config.depth - 1}))

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        if images.dim() == 4:
            images = images.unsqueeze(0)
        H, W = images.shape[-2], images.shape[-1]
        tokens = self.aggregator(images, self._keep)
        start = self.aggregator.patch_start_idx
        pose_enc = self.camera_head(tokens[self.config.depth - 1])
        dense = self.dpt_heads(tokens, start, H, W)
        return {"pose_enc": pose_enc, "depth": dense["depth"], "depth_conf": dense["depth_conf"],
                "world_points": dense["point"], "world_points_conf": dense["point_conf"]}

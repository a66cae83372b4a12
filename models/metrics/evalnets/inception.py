"""The Inception-v3 network of FID (the TensorFlow graph ``2015-12-05`` used by TTUR and pytorch-fid).

What is implemented: Inception-v3 (Szegedy et al. 2016, "Rethinking the Inception Architecture") in the
variant whose weights FID is defined with: the TF graph ``classify_image_graph_def.pb`` of 2015-12-05 used
by the reference FID code (TTUR, Heusel et al. 2017), as ported to PyTorch by pytorch-fid (M. Seitzer) in
the file ``pt_inception-2015-12-05-6726825d.pth``. It differs from torchvision's Inception-v3:

* 1008 output classes (``fc`` is 2048 -> 1008), no auxiliary classifier;
* the average pools in the A, C and first E blocks (``Mixed_5b``-``5d``, ``Mixed_6b``-``6e``, ``Mixed_7b``)
  exclude the zero padding from the mean (``count_include_pad=False``);
* the pool branch of the last E block (``Mixed_7c``) is a 3x3 *max* pool (stride 1, padding 1).

Every convolution is conv (no bias) -> BatchNorm (eps 0.001) -> ReLU. FID features are the 2048-d
``pool3`` activations: global average of ``Mixed_7c``. Input handling follows pytorch-fid: RGB in [0, 1],
resized to 299x299 (bilinear, ``align_corners=False``, no antialiasing) and scaled to [-1, 1].

Parameter names follow torchvision's ``Inception3`` (which pytorch-fid builds on), so the official file
loads with strict key checking: ``Conv2d_1a_3x3.conv.weight``, ``Mixed_5b.branch1x1.bn.running_mean``,
``fc.weight`` ... Sources for these facts: the pytorch-fid and torchvision Inception-v3 code and the TTUR
FID code (read for facts; this is an independent implementation). The weights are never downloaded here:
``find_weights`` looks them up in the user's weight folder and raises ``MetricUnavailable`` if absent.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from navcrafter.models.metrics.evalnets.weights import MetricUnavailable, WeightFile, find_weights, register

FID_INCEPTION = register(WeightFile(
    key="fid-inception",
    filename="pt_inception-2015-12-05-6726825d.pth",
    source="https://github.com/mseitzer/pytorch-fid/releases/download/fid_weights/pt_inception-2015-12-05-6726825d.pth",
    used_by="FID",
))

FID_INPUT_SIZE = 299
FID_FEATURE_DIM = 2048
FID_NUM_CLASSES = 1008
BN_EPS = 1e-3


# --------------------------------------------------------------------------------------------------
# Loading official state dicts (shared with i3d.py)
# --------------------------------------------------------------------------------------------------
def load_official_state_dict(model: nn.Module, path: str | os.PathLike, what: str) -> None:
    """Load the state dict in ``path`` into ``model`` with strict key and shape checking.

    The only tolerated difference is absent BatchNorm ``num_batches_tracked`` counters (files saved by old
    PyTorch versions lack them; they do not affect inference). Anything else (a missing or unexpected
    tensor, a wrong shape, a file that is not a state dict) raises ``MetricUnavailable``: a metric is never
    computed with partly random weights.
    """
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file makes the metric unavailable
        raise MetricUnavailable(f"{what} is unavailable: cannot read weight file {path}: {e}") from e
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise MetricUnavailable(f"{what} is unavailable: {path} is not a plain state dict of tensors")
    expected = model.state_dict()
    state = dict(obj)
    missing = [k for k in expected if k not in state]
    for k in missing:
        if k.endswith(".num_batches_tracked"):
            state[k] = expected[k].clone()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    shapes = [f"{k}: file {tuple(state[k].shape)} vs model {tuple(v.shape)}"
              for k, v in expected.items() if k in state and tuple(state[k].shape) != tuple(v.shape)]
    if missing or unexpected or shapes:
        def few(xs: list[str]) -> str:
            return ", ".join(xs[:5]) + (f" (+{len(xs) - 5} more)" if len(xs) > 5 else "")

        raise MetricUnavailable(
            f"{what} is unavailable: {path} does not match the expected architecture "
            f"(missing: {few(missing) or '-'}; unexpected: {few(unexpected) or '-'}; shapes: {few(shapes) or '-'})")
    model.load_state_dict(state, strict=True)


def as_float_tensor(x: np.ndarray | torch.Tensor, name: str) -> torch.Tensor:
    """``x`` as a float32 tensor in [0, 1]: uint8 is divided by 255; floats must lie in [0, 1]."""
    t = x if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x))
    if t.dtype == torch.uint8:
        return t.float() / 255.0
    t = t.float()
    if t.numel() and (t.min() < -1e-3 or t.max() > 1.0 + 1e-3):
        raise ValueError(f"{name} must be float in [0, 1] (or uint8), got values in "
                         f"[{float(t.min()):.3g}, {float(t.max()):.3g}]")
    return t.clamp(0.0, 1.0)


# --------------------------------------------------------------------------------------------------
# Architecture
# --------------------------------------------------------------------------------------------------
class ConvBN(nn.Module):
    """Conv2d (no bias) -> BatchNorm (eps 0.001) -> ReLU; submodules ``conv`` and ``bn``."""

    def __init__(self, cin: int, cout: int, kernel: int | tuple[int, int], stride: int = 1,
                 padding: int | tuple[int, int] = 0) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, stride=stride, padding=padding, bias=False)
        self.bn = nn.BatchNorm2d(cout, eps=BN_EPS)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(x)))


def _avg3(x: torch.Tensor) -> torch.Tensor:
    # The FID graph averages over the valid (unpadded) window only.
    return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=False)


class BlockA(nn.Module):
    """35x35 block (``Mixed_5b``-``5d``): 1x1 | 1x1->5x5 | 1x1->3x3->3x3 | avgpool->1x1."""

    def __init__(self, cin: int, pool_features: int) -> None:
        super().__init__()
        self.branch1x1 = ConvBN(cin, 64, 1)
        self.branch5x5_1 = ConvBN(cin, 48, 1)
        self.branch5x5_2 = ConvBN(48, 64, 5, padding=2)
        self.branch3x3dbl_1 = ConvBN(cin, 64, 1)
        self.branch3x3dbl_2 = ConvBN(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = ConvBN(96, 96, 3, padding=1)
        self.branch_pool = ConvBN(cin, pool_features, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([
            self.branch1x1(x),
            self.branch5x5_2(self.branch5x5_1(x)),
            self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
            self.branch_pool(_avg3(x)),
        ], dim=1)


class BlockB(nn.Module):
    """35->17 reduction (``Mixed_6a``): 3x3/2 | 1x1->3x3->3x3/2 | maxpool/2."""

    def __init__(self, cin: int) -> None:
        super().__init__()
        self.branch3x3 = ConvBN(cin, 384, 3, stride=2)
        self.branch3x3dbl_1 = ConvBN(cin, 64, 1)
        self.branch3x3dbl_2 = ConvBN(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = ConvBN(96, 96, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([
            self.branch3x3(x),
            self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
            F.max_pool2d(x, 3, stride=2),
        ], dim=1)


class BlockC(nn.Module):
    """17x17 block with factorised 7x7 convolutions (``Mixed_6b``-``6e``)."""

    def __init__(self, cin: int, c7: int) -> None:
        super().__init__()
        self.branch1x1 = ConvBN(cin, 192, 1)
        self.branch7x7_1 = ConvBN(cin, c7, 1)
        self.branch7x7_2 = ConvBN(c7, c7, (1, 7), padding=(0, 3))
        self.branch7x7_3 = ConvBN(c7, 192, (7, 1), padding=(3, 0))
        self.branch7x7dbl_1 = ConvBN(cin, c7, 1)
        self.branch7x7dbl_2 = ConvBN(c7, c7, (7, 1), padding=(3, 0))
        self.branch7x7dbl_3 = ConvBN(c7, c7, (1, 7), padding=(0, 3))
        self.branch7x7dbl_4 = ConvBN(c7, c7, (7, 1), padding=(3, 0))
        self.branch7x7dbl_5 = ConvBN(c7, 192, (1, 7), padding=(0, 3))
        self.branch_pool = ConvBN(cin, 192, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
        d = self.branch7x7dbl_1(x)
        for conv in (self.branch7x7dbl_2, self.branch7x7dbl_3, self.branch7x7dbl_4, self.branch7x7dbl_5):
            d = conv(d)
        return torch.cat([self.branch1x1(x), b7, d, self.branch_pool(_avg3(x))], dim=1)


class BlockD(nn.Module):
    """17->8 reduction (``Mixed_7a``): 1x1->3x3/2 | 1x1->1x7->7x1->3x3/2 | maxpool/2."""

    def __init__(self, cin: int) -> None:
        super().__init__()
        self.branch3x3_1 = ConvBN(cin, 192, 1)
        self.branch3x3_2 = ConvBN(192, 320, 3, stride=2)
        self.branch7x7x3_1 = ConvBN(cin, 192, 1)
        self.branch7x7x3_2 = ConvBN(192, 192, (1, 7), padding=(0, 3))
        self.branch7x7x3_3 = ConvBN(192, 192, (7, 1), padding=(3, 0))
        self.branch7x7x3_4 = ConvBN(192, 192, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b7 = self.branch7x7x3_1(x)
        for conv in (self.branch7x7x3_2, self.branch7x7x3_3, self.branch7x7x3_4):
            b7 = conv(b7)
        return torch.cat([self.branch3x3_2(self.branch3x3_1(x)), b7, F.max_pool2d(x, 3, stride=2)], dim=1)


class BlockE(nn.Module):
    """8x8 block with split 1x3 / 3x1 outputs (``Mixed_7b``: average pool; ``Mixed_7c``: max pool in FID)."""

    def __init__(self, cin: int, pool: str) -> None:
        super().__init__()
        if pool not in ("avg", "max"):
            raise ValueError(f"pool must be 'avg' or 'max', got {pool!r}")
        self.pool = pool
        self.branch1x1 = ConvBN(cin, 320, 1)
        self.branch3x3_1 = ConvBN(cin, 384, 1)
        self.branch3x3_2a = ConvBN(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3_2b = ConvBN(384, 384, (3, 1), padding=(1, 0))
        self.branch3x3dbl_1 = ConvBN(cin, 448, 1)
        self.branch3x3dbl_2 = ConvBN(448, 384, 3, padding=1)
        self.branch3x3dbl_3a = ConvBN(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3dbl_3b = ConvBN(384, 384, (3, 1), padding=(1, 0))
        self.branch_pool = ConvBN(cin, 192, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b3 = self.branch3x3_1(x)
        d = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
        pooled = _avg3(x) if self.pool == "avg" else F.max_pool2d(x, 3, stride=1, padding=1)
        return torch.cat([
            self.branch1x1(x),
            self.branch3x3_2a(b3), self.branch3x3_2b(b3),
            self.branch3x3dbl_3a(d), self.branch3x3dbl_3b(d),
            self.branch_pool(pooled),
        ], dim=1)


class InceptionFeatures(nn.Module):
    """FID Inception-v3: ``forward`` maps RGB images ``N x 3 x H x W`` in [0, 1] to 2048-d pool3 features.

    Build with ``from_pretrained`` for metrics; the bare constructor gives random weights (tests only).
    """

    def __init__(self) -> None:
        super().__init__()
        self.Conv2d_1a_3x3 = ConvBN(3, 32, 3, stride=2)
        self.Conv2d_2a_3x3 = ConvBN(32, 32, 3)
        self.Conv2d_2b_3x3 = ConvBN(32, 64, 3, padding=1)
        self.Conv2d_3b_1x1 = ConvBN(64, 80, 1)
        self.Conv2d_4a_3x3 = ConvBN(80, 192, 3)
        self.Mixed_5b = BlockA(192, pool_features=32)
        self.Mixed_5c = BlockA(256, pool_features=64)
        self.Mixed_5d = BlockA(288, pool_features=64)
        self.Mixed_6a = BlockB(288)
        self.Mixed_6b = BlockC(768, c7=128)
        self.Mixed_6c = BlockC(768, c7=160)
        self.Mixed_6d = BlockC(768, c7=160)
        self.Mixed_6e = BlockC(768, c7=192)
        self.Mixed_7a = BlockD(768)
        self.Mixed_7b = BlockE(1280, pool="avg")
        self.Mixed_7c = BlockE(2048, pool="max")
        self.fc = nn.Linear(FID_FEATURE_DIM, FID_NUM_CLASSES)  # kept for the official key set; unused by FID
        self.eval()

    @classmethod
    def from_pretrained(cls, weights_dir: str | os.PathLike | None = None) -> InceptionFeatures:
        """The network with the official FID weights (``pt_inception-2015-12-05-6726825d.pth``) from
        ``weights_dir`` (a folder or the file itself; see ``find_weights``); ``MetricUnavailable`` if absent."""
        path = find_weights(FID_INCEPTION.key, weights_dir)
        model = cls()
        load_official_state_dict(model, path, FID_INCEPTION.used_by)
        model.requires_grad_(False)
        return model.eval()

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """``N x 3 x H x W`` in [0, 1] -> 299x299 (bilinear, no antialiasing) in [-1, 1]."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"images must be N x 3 x H x W, got {tuple(images.shape)}")
        x = F.interpolate(images, size=(FID_INPUT_SIZE, FID_INPUT_SIZE), mode="bilinear", align_corners=False)
        return 2.0 * x - 1.0

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.preprocess(images)
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
        x = F.max_pool2d(x, 3, stride=2)
        x = self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x))
        x = F.max_pool2d(x, 3, stride=2)
        for block in (self.Mixed_5b, self.Mixed_5c, self.Mixed_5d, self.Mixed_6a, self.Mixed_6b, self.Mixed_6c,
                      self.Mixed_6d, self.Mixed_6e, self.Mixed_7a, self.Mixed_7b, self.Mixed_7c):
            x = block(x)
        return torch.flatten(F.adaptive_avg_pool2d(x, 1), 1)

    @torch.no_grad()
    def fid_features(self, images: np.ndarray | torch.Tensor | Sequence[np.ndarray | torch.Tensor],
                     batch_size: int = 32, device: str | torch.device | None = None) -> np.ndarray:
        """Pool3 features ``N x 2048`` (float64) of RGB images ``N x H x W x 3`` in [0, 1] (or uint8).

        ``images`` may also be a sequence of ``H x W x 3`` images of different sizes (each is resized to
        299x299 on its own). Runs in eval mode, in batches of ``batch_size``, on ``device`` (default: the
        device of the parameters).
        """
        if device is not None:
            self.to(device)
        dev = next(self.parameters()).device
        self.eval()
        n = len(images)
        out = []
        for start in range(0, n, batch_size):
            chunk = images[start:start + batch_size]
            if isinstance(chunk, (np.ndarray, torch.Tensor)):
                batch = self._to_nchw(as_float_tensor(chunk, "images"))
                out.append(self(batch.to(dev)).double().cpu())
            else:
                resized = [self._to_nchw(as_float_tensor(im, "images")[None]) for im in chunk]
                resized = [F.interpolate(r, size=(FID_INPUT_SIZE, FID_INPUT_SIZE), mode="bilinear",
                                         align_corners=False) for r in resized]
                out.append(self(torch.cat(resized).to(dev)).double().cpu())
        if not out:
            return np.zeros((0, FID_FEATURE_DIM))
        return torch.cat(out).numpy()

    @staticmethod
    def _to_nchw(x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or x.shape[-1] != 3:
            raise ValueError(f"images must be N x H x W x 3 (RGB), got {tuple(x.shape)}")
        return x.permute(0, 3, 1, 2).contiguous()

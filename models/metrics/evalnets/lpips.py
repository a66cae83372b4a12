"""LPIPS, the learned perceptual image patch similarity (v0.1), written here in plain torch.

Zhang, Isola, Efros, Shechtman & Wang, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric", CVPR 2018 (Eq. 1): both images go through a frozen ImageNet trunk; at five taps the features are
unit-normalised along channels, their squared difference is weighted per channel by a learned 1x1
convolution ``w_l`` (the "lin" heads), averaged over space and summed over taps::

    d(x, x0) = sum_l mean_hw || w_l * (f_l(x) / |f_l(x)| - f_l(x0) / |f_l(x0)|) ||^2

(the learned, non-negative ``w_l`` multiplies the *squared* difference, as in the released v0.1 weights).
Inputs are in ``[-1, 1]`` and, in v0.1, are first shifted and scaled by the fixed per-channel constants
``shift = (-.030, -.088, -.188)``, ``scale = (.458, .448, .450)``. Unit normalisation divides by the
channel L2 norm plus ``1e-10``.

Trunks (architectures from Krizhevsky 2014 "One weird trick..." / torchvision's AlexNet, and Simonyan &
Zisserman 2015 VGG-16, configuration D) are written with the module indices of torchvision's ``features``
``Sequential`` so that its official ImageNet checkpoints load by key:

* AlexNet: convs at ``features.0, 3, 6, 8, 10``; taps relu1..relu5 (after each conv).
* VGG16: convs at ``features.0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28``; taps relu1_2, relu2_2,
  relu3_3, relu4_3, relu5_3.

Weights are two official files per trunk, looked up by ``find_weights`` (never downloaded, never random):
the torchvision ImageNet checkpoint (only its ``features.*`` entries are used; ``classifier.*`` is
ignored) and the LPIPS v0.1 lin heads (keys ``lin0.model.1.weight`` .. ``lin4.model.1.weight``: a
dropout at index 0, the bias-free 1x1 conv at index 1). Both are loaded with strict key and shape checks.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from navcrafter.models.metrics.evalnets.weights import MetricUnavailable, WeightFile, find_weights, register

NetName = Literal["alex", "vgg"]

TORCHVISION_URL = "https://download.pytorch.org/models"
LPIPS_REPO = "https://github.com/richzhang/PerceptualSimilarity"

TRUNK_WEIGHTS = {
    "alex": register(WeightFile("alexnet-torchvision", "alexnet-owt-7be5be79.pth",
                                f"{TORCHVISION_URL}/alexnet-owt-7be5be79.pth", "LPIPS (alex)")),
    "vgg": register(WeightFile("vgg16-torchvision", "vgg16-397923af.pth",
                               f"{TORCHVISION_URL}/vgg16-397923af.pth", "LPIPS (vgg)")),
}
LIN_WEIGHTS = {
    "alex": register(WeightFile("lpips-alex-v0.1", "alex.pth",
                                f"{LPIPS_REPO} (file lpips/weights/v0.1/alex.pth)", "LPIPS (alex)")),
    "vgg": register(WeightFile("lpips-vgg-v0.1", "vgg.pth",
                               f"{LPIPS_REPO} (file lpips/weights/v0.1/vgg.pth)", "LPIPS (vgg)")),
}

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
NORM_EPS = 1e-10


class WeightFileError(MetricUnavailable):
    """A weight file exists but cannot be used (unreadable, or not the expected keys/shapes)."""


# --------------------------------------------------------------------------------------------------
# Trunks
# --------------------------------------------------------------------------------------------------
class _Trunk(nn.Module):
    """A torchvision-style ``features`` Sequential returning the activations at ``taps`` (module indices)."""

    channels: tuple[int, ...]
    taps: tuple[int, ...]

    def __init__(self, layers: list[nn.Module]) -> None:
        super().__init__()
        self.features = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        outs = []
        for i, layer in enumerate(self.features[: self.taps[-1] + 1]):
            x = layer(x)
            if i in self.taps:
                outs.append(x)
        return outs


class AlexNetFeatures(_Trunk):
    """AlexNet (torchvision "one weird trick" variant) convolutional trunk; taps relu1..relu5."""

    channels = (64, 192, 384, 256, 256)
    taps = (1, 4, 7, 9, 11)

    def __init__(self) -> None:
        super().__init__([
            nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(),  # 0, 1
            nn.MaxPool2d(3, stride=2),  # 2
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(),  # 3, 4
            nn.MaxPool2d(3, stride=2),  # 5
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),  # 6, 7
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),  # 8, 9
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),  # 10, 11
            nn.MaxPool2d(3, stride=2),  # 12
        ])


VGG16_CONFIG: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
                                       512, 512, 512, "M")


class VGG16Features(_Trunk):
    """VGG-16 (configuration D, no batch norm) convolutional trunk; taps relu1_2, 2_2, 3_3, 4_3, 5_3."""

    channels = (64, 128, 256, 512, 512)
    taps = (3, 8, 15, 22, 29)

    def __init__(self) -> None:
        layers: list[nn.Module] = []
        c_in = 3
        for v in VGG16_CONFIG:
            if v == "M":
                layers.append(nn.MaxPool2d(2, stride=2))
            else:
                layers += [nn.Conv2d(c_in, int(v), 3, padding=1), nn.ReLU()]
                c_in = int(v)
        super().__init__(layers)


TRUNKS: dict[str, type[_Trunk]] = {"alex": AlexNetFeatures, "vgg": VGG16Features}


# --------------------------------------------------------------------------------------------------
# LPIPS
# --------------------------------------------------------------------------------------------------
class LinHead(nn.Module):
    """One LPIPS head: dropout (identity in eval) then a bias-free 1x1 conv to one channel."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


def _unit_normalise(f: torch.Tensor) -> torch.Tensor:
    return f / (f.pow(2).sum(dim=1, keepdim=True).sqrt() + NORM_EPS)


class LPIPS(nn.Module):
    """LPIPS v0.1 distance between ``Nx3xHxW`` images in ``[-1, 1]``; ``forward`` returns ``(N,)``.

    Built with random weights; use ``from_pretrained`` (the only way metrics should obtain one).
    ``trunk_state_dict`` / ``lin_state_dict`` give the state in the official files' key layouts.
    """

    def __init__(self, net: NetName = "alex") -> None:
        super().__init__()
        if net not in TRUNKS:
            raise ValueError(f"net must be one of {sorted(TRUNKS)}, got {net!r}")
        self.net_name = net
        self.net = TRUNKS[net]()
        for k, c in enumerate(self.net.channels):
            self.add_module(f"lin{k}", LinHead(c))
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.eval()  # a metric: dropout off unless someone explicitly calls train()

    @property
    def lins(self) -> list[LinHead]:
        return [getattr(self, f"lin{k}") for k in range(len(self.net.channels))]

    def forward(self, x0: torch.Tensor, x1: torch.Tensor, per_layer: bool = False
                ) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
        """Distances ``(N,)`` for inputs in ``[-1, 1]``; with ``per_layer`` also each tap's ``(N,)`` term."""
        if x0.shape != x1.shape or x0.ndim != 4 or x0.shape[1] != 3:
            raise ValueError(f"expected two Nx3xHxW tensors of equal shape, got {tuple(x0.shape)}, {tuple(x1.shape)}")
        n = x0.shape[0]
        feats = self.net((torch.cat([x0, x1]) - self.shift) / self.scale)
        terms = []
        for f, lin in zip(feats, self.lins):
            f = _unit_normalise(f)
            terms.append(lin((f[:n] - f[n:]) ** 2).mean(dim=(1, 2, 3)))
        total = torch.stack(terms).sum(dim=0)
        return (total, terms) if per_layer else total

    # ---- official key layouts -------------------------------------------------------------------
    def trunk_state_dict(self) -> dict[str, torch.Tensor]:
        """Trunk parameters keyed as torchvision's ``alexnet``/``vgg16`` (``features.0.weight`` ...)."""
        return {k: v.detach().clone() for k, v in self.net.state_dict().items()}

    def lin_state_dict(self) -> dict[str, torch.Tensor]:
        """Head parameters keyed as the official LPIPS v0.1 files (``lin0.model.1.weight`` ...)."""
        return {f"lin{k}.{name}": v.detach().clone()
                for k, lin in enumerate(self.lins) for name, v in lin.state_dict().items()}

    def load_trunk_state(self, state: dict[str, Any], origin: str = "state dict") -> None:
        """Load a torchvision checkpoint: all ``features.*`` keys must match; ``classifier.*`` is ignored."""
        other = [k for k in state if not k.startswith(("features.", "classifier."))]
        _load_strict(self.net, {k: v for k, v in state.items() if k.startswith("features.")}, origin, other)

    def load_lin_state(self, state: dict[str, Any], origin: str = "state dict") -> None:
        """Load the LPIPS v0.1 heads (exactly ``lin0.model.1.weight`` .. ``lin4.model.1.weight``)."""
        heads = nn.ModuleDict({f"lin{k}": lin for k, lin in enumerate(self.lins)})
        _load_strict(heads, dict(state), origin, [])

    @classmethod
    def from_pretrained(cls, net: NetName = "alex", weights_dir: str | os.PathLike | None = None) -> LPIPS:
        """LPIPS with the official trunk and head weights found in ``weights_dir`` (see ``find_weights``).

        Raises ``MetricUnavailable`` when a file is missing, ``WeightFileError`` (a ``MetricUnavailable``)
        when one is unreadable or does not hold the expected keys and shapes. Returned in eval mode, frozen.
        """
        if net not in TRUNKS:
            raise ValueError(f"net must be one of {sorted(TRUNKS)}, got {net!r}")
        if weights_dir is not None and Path(weights_dir).expanduser().is_file():
            raise ValueError(f"LPIPS needs two weight files: weights_dir must be a folder, got the file {weights_dir}")
        trunk_path = find_weights(TRUNK_WEIGHTS[net].key, weights_dir)
        lin_path = find_weights(LIN_WEIGHTS[net].key, weights_dir)
        model = cls(net)
        model.load_trunk_state(_read_state(trunk_path), origin=str(trunk_path))
        model.load_lin_state(_read_state(lin_path), origin=str(lin_path))
        model.eval().requires_grad_(False)
        return model


def _read_state(path: Path) -> dict[str, Any]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # any failure to unpickle means an unusable file
        raise WeightFileError(f"weight file {path} could not be read ({type(e).__name__}: {e}); "
                              "it is corrupt or not a torch checkpoint: replace it with the official file") from e
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise WeightFileError(f"weight file {path} is not a state dict of tensors; replace it with the official file")
    return state


def _load_strict(module: nn.Module, state: dict[str, Any], origin: str, other: list[str]) -> None:
    """``load_state_dict(strict=True)`` with a readable error; ``other``: further unexpected keys of the file."""
    expected = module.state_dict()
    missing = [k for k in expected if k not in state]  # in module order
    extra = [k for k in state if k not in expected] + other
    shapes = [f"{k}: {tuple(state[k].shape)} != {tuple(v.shape)}" for k, v in expected.items()
              if k in state and tuple(state[k].shape) != tuple(v.shape)]
    if missing or extra or shapes:
        parts = [f"{label}: {', '.join(items[:6])}{' ...' if len(items) > 6 else ''}"
                 for label, items in (("missing keys", missing), ("unexpected keys", extra),
                                      ("wrong shapes", shapes)) if items]
        raise WeightFileError(f"weight file {origin} does not match the expected layout ({'; '.join(parts)}); "
                              "is it the right official file?")
    module.load_state_dict(state, strict=True)


# --------------------------------------------------------------------------------------------------
# Convenience
# --------------------------------------------------------------------------------------------------
def lpips_distance(a: Any, b: Any, net: NetName = "alex", weights_dir: str | os.PathLike | None = None, *,
                   model: LPIPS | None = None, batch_size: int = 16,
                   device: str | torch.device | None = None) -> np.ndarray:
    """LPIPS v0.1 distance per image pair for float images in ``[0, 1]`` (``NxHxWx3`` or ``HxWx3``).

    Loads the official weights via ``LPIPS.from_pretrained`` unless a ``model`` is given (pass one to
    avoid reloading across calls). Returns an ``(N,)`` float64 array. Raises ``MetricUnavailable``.
    """
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    if hasattr(b, "detach"):
        b = b.detach().cpu().numpy()
    a, b = np.asarray(a, dtype=np.float32), np.asarray(b, dtype=np.float32)
    if a.ndim == 3:
        a, b = a[None], b[None]
    if a.shape != b.shape or a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"expected NxHxWx3 images of equal shape, got {a.shape} and {b.shape}")
    if model is None:
        model = LPIPS.from_pretrained(net, weights_dir)
    if device is not None:
        model = model.to(device)  # in place, like any nn.Module.to
    model.eval()
    dev = model.shift.device
    out = []
    with torch.inference_mode():
        for i in range(0, len(a), batch_size):
            x0 = torch.from_numpy(a[i:i + batch_size]).to(dev).permute(0, 3, 1, 2) * 2 - 1
            x1 = torch.from_numpy(b[i:i + batch_size]).to(dev).permute(0, 3, 1, 2) * 2 - 1
            out.append(model(x0, x1).double().cpu().numpy())
    return np.concatenate(out) if out else np.zeros(0)

"""FID and FVD between sets of real and generated images / videos.

* ``fid``: Fréchet Inception Distance (Heusel et al. 2017) on the 2048-d pool3 features of the FID
  Inception-v3 (``inception.py``; pytorch-fid's weights ``pt_inception-2015-12-05-6726825d.pth``).
* ``fvd``: Fréchet Video Distance (Unterthiner et al. 2018) on the 400-d logits of I3D (``i3d.py``; weights
  ``i3d_pretrained_400.pt``).

Both fit a Gaussian (mean, unbiased covariance) to each feature set and return the Fréchet distance
(``frechet.py``). Weights are looked up with ``find_weights`` (``weights_dir``, else
``$NAVCRAFTER_EVAL_WEIGHTS``, else ``~/.cache/navcrafter/eval``); missing weights raise ``MetricUnavailable``
before anything is computed. Loaded networks are cached per (file, device). Values computed from few samples
are biased upwards (the estimate needs many samples: FID is usually reported on 10k-50k images); they are only
comparable between runs with the same sample counts.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from navcrafter.models.metrics.evalnets.frechet import FeatureMethod, frechet_distance_from_features
from navcrafter.models.metrics.evalnets.i3d import FVD_I3D, I3DFeatures
from navcrafter.models.metrics.evalnets.inception import FID_INCEPTION, InceptionFeatures
from navcrafter.models.metrics.evalnets.weights import find_weights

Images = np.ndarray | torch.Tensor | Sequence[np.ndarray | torch.Tensor]


@lru_cache(maxsize=2)
def _inception(path: str, stamp: tuple[int, int], device: str) -> InceptionFeatures:
    return InceptionFeatures.from_pretrained(path).to(device)


@lru_cache(maxsize=2)
def _i3d(path: str, stamp: tuple[int, int], device: str) -> I3DFeatures:
    return I3DFeatures.from_pretrained(path).to(device)


def _stamp(path: Path) -> tuple[int, int]:
    st = path.stat()
    return (st.st_mtime_ns, st.st_size)


def _device(device: str | torch.device | None) -> str:
    return str(device) if device is not None else ("cuda" if torch.cuda.is_available() else "cpu")


def _check_count(name: str, items: Images) -> None:
    if len(items) < 2:
        raise ValueError(f"{name} needs at least 2 samples per set (a covariance is estimated), got {len(items)}")


def load_inception(weights_dir: str | os.PathLike | None = None,
                   device: str | torch.device | None = None) -> InceptionFeatures:
    """The FID network with official weights (cached); ``MetricUnavailable`` if the file is missing."""
    path = find_weights(FID_INCEPTION.key, weights_dir)
    return _inception(str(path), _stamp(path), _device(device))


def load_i3d(weights_dir: str | os.PathLike | None = None, device: str | torch.device | None = None) -> I3DFeatures:
    """The FVD network with official weights (cached); ``MetricUnavailable`` if the file is missing."""
    path = find_weights(FVD_I3D.key, weights_dir)
    return _i3d(str(path), _stamp(path), _device(device))


def fid(real_images: Images, fake_images: Images, weights_dir: str | os.PathLike | None = None, *,
        batch_size: int = 32, device: str | torch.device | None = None, method: FeatureMethod = "sqrtm") -> float:
    """FID between two image sets, each ``N x H x W x 3`` float in [0, 1] (or uint8, or a sequence of
    ``H x W x 3`` images), ``N >= 2``.

    ``method`` chooses how ``Tr((sigma1 sigma2)^(1/2))`` is computed (see ``frechet``): ``"sqrtm"`` as
    pytorch-fid (about 25 s for 2048-d features on 2 CPU cores), ``"eigh"``, or ``"gram"`` (exact, fast for
    up to a few thousand images)."""
    _check_count("FID", real_images)
    _check_count("FID", fake_images)
    net = load_inception(weights_dir, device)
    f_real = net.fid_features(real_images, batch_size=batch_size)
    f_fake = net.fid_features(fake_images, batch_size=batch_size)
    return frechet_distance_from_features(f_real, f_fake, method=method)


def fvd(real_videos: Images, fake_videos: Images, weights_dir: str | os.PathLike | None = None, *,
        batch_size: int = 4, device: str | torch.device | None = None, method: FeatureMethod = "sqrtm") -> float:
    """FVD between two video sets, each ``N x T x H x W x 3`` float in [0, 1] (or uint8, or a sequence of
    ``T x H x W x 3`` clips), ``N >= 2``, ``T >= 9`` (16 is the usual setting)."""
    _check_count("FVD", real_videos)
    _check_count("FVD", fake_videos)
    net = load_i3d(weights_dir, device)
    f_real = net.fvd_features(real_videos, batch_size=batch_size)
    f_fake = net.fvd_features(fake_videos, batch_size=batch_size)
    return frechet_distance_from_features(f_real, f_fake, method=method)


_WEIGHTS_OF = {"FID": "fid-inception", "FVD": "fvd-i3d"}


def require_weights(metric: str, weights_dir: str | Path | None = None) -> Path:
    """The weight file ``metric`` ("FID" or "FVD") needs; ``MetricUnavailable`` when it is missing."""
    if metric not in _WEIGHTS_OF:
        raise KeyError(f"unknown metric {metric!r}; known: {sorted(_WEIGHTS_OF)}")
    return find_weights(_WEIGHTS_OF[metric], weights_dir)

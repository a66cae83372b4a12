"""Full-reference image metrics: PSNR and SSIM.

Images are float arrays in ``[0, data_range]`` laid out ``HxWxC`` (one image) or ``NxHxWxC`` (a batch);
numpy arrays and torch tensors are accepted (tensors are copied to CPU numpy), computation is float64.
A single image pair gives a ``float``, a batch gives an ``(N,)`` array of per-pair values.

* **PSNR** = ``10 log10(data_range^2 / MSE)`` with the MSE over all pixels and channels of a pair;
  identical images give ``inf``.
* **SSIM** follows Wang, Bovik, Sheikh & Simoncelli, "Image quality assessment: from error visibility to
  structural similarity", IEEE TIP 2004: local statistics under an 11x11 circular Gaussian window with
  sigma = 1.5 (the 1-D kernel ``exp(-x^2 / 2 sigma^2)``, ``x = -5..5``, normalised to sum 1), constants
  ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2`` with ``L = data_range`` and population (not sample) variances.
  The SSIM map is evaluated only where the window lies fully inside the image (the "valid" region,
  i.e. a 5-pixel border is dropped), averaged over that region for each channel, then averaged over
  channels. This is the convention of scikit-image's ``structural_similarity(..., gaussian_weights=True,
  sigma=1.5, use_sample_covariance=False, channel_axis=-1)``, which it matches to float precision.
"""

from __future__ import annotations

from typing import Any

import numpy as np

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _as_batch(a: Any, b: Any) -> tuple[np.ndarray, np.ndarray, bool]:
    """Both images as float64 ``NxHxWxC`` arrays of equal shape, and whether the input was a single pair."""

    def to_numpy(x: Any) -> np.ndarray:
        if hasattr(x, "detach"):  # torch tensor, without importing torch here
            x = x.detach().cpu().numpy()
        return np.asarray(x, dtype=np.float64)

    a, b = to_numpy(a), to_numpy(b)
    if a.shape != b.shape:
        raise ValueError(f"images must have the same shape, got {a.shape} and {b.shape}")
    if a.ndim == 3:
        return a[None], b[None], True
    if a.ndim == 4:
        return a, b, False
    raise ValueError(f"expected HxWxC or NxHxWxC images, got shape {a.shape}")


def _unbatch(values: np.ndarray, single: bool) -> float | np.ndarray:
    return float(values[0]) if single else values


def psnr(a: Any, b: Any, data_range: float = 1.0) -> float | np.ndarray:
    """Peak signal-to-noise ratio in dB per image pair (``inf`` for identical images)."""
    a, b, single = _as_batch(a, b)
    mse = np.mean((a - b) ** 2, axis=(1, 2, 3))
    with np.errstate(divide="ignore"):
        values = 10.0 * np.log10(data_range**2 / mse)
    return _unbatch(values, single)


def gaussian_kernel_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """Normalised 1-D Gaussian taps ``exp(-x^2 / 2 sigma^2)`` for ``x = -(size//2) .. size//2``."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _filter_valid(x: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Separable correlation of ``NxHxWxC`` maps with ``g`` over H and W, keeping the 'valid' region only."""
    k = len(g)
    x = np.lib.stride_tricks.sliding_window_view(x, k, axis=1) @ g  # N x (H-k+1) x W x C
    return np.lib.stride_tricks.sliding_window_view(x, k, axis=2) @ g  # N x (H-k+1) x (W-k+1) x C


def ssim_map(a: Any, b: Any, data_range: float = 1.0) -> np.ndarray:
    """Per-pixel SSIM over the valid region: ``Nx(H-10)x(W-10)xC`` (a leading axis is always present)."""
    a, b, _ = _as_batch(a, b)
    if min(a.shape[1], a.shape[2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {a.shape[1:3]}")
    g = gaussian_kernel_1d()
    mu_a, mu_b = _filter_valid(a, g), _filter_valid(b, g)
    var_a = _filter_valid(a * a, g) - mu_a**2
    var_b = _filter_valid(b * b, g) - mu_b**2
    cov = _filter_valid(a * b, g) - mu_a * mu_b
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


def ssim(a: Any, b: Any, data_range: float = 1.0) -> float | np.ndarray:
    """Mean SSIM per image pair (Gaussian 11x11 window, sigma 1.5, valid region, mean over channels)."""
    single = np.ndim(a) == 3
    values = ssim_map(a, b, data_range).mean(axis=(1, 2, 3))
    return _unbatch(values, single)

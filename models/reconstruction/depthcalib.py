"""Depth calibration: monocular relative inverse depth aligned to the geometry depth (paper, Sec. III-D).

A monocular depth model (the ``MonoDepth`` role) returns inverse depth ``d_m_inv`` up to an unknown scale
and shift; the lift step's geometry depth ``d_v`` is metric (in scene units) but noisier and incomplete.
The calibration finds ``s, b`` minimising ``sum (s * d_m_inv + b - 1 / d_v)^2`` over pixels that are valid
in both and not sky, and returns the calibrated depth ``1 / (s * d_m_inv + b)``: dense, with the monocular
model's sharp structure and the geometry's scale.

The fit is robust to outliers (wrong geometry depth at edges, moving or hallucinated content): least
trimmed squares by concentration steps (fit, keep the ``trim`` fraction of smallest residuals, refit, until
the kept set is stable), started from ordinary least squares and from a quantile match; then the inliers are
every pixel whose residual is within ``threshold`` robust sigmas (1.4826 x the median absolute residual of
all pixels) and the final ``s, b`` is the least-squares fit on them. Deterministic (no random sampling).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAD_TO_SIGMA = 1.4826


class CalibrationError(ValueError):
    """Too few usable pixels, or a degenerate (constant) monocular depth."""


@dataclass(frozen=True)
class DepthCalibration:
    scale: float  # s
    bias: float  # b
    depth: np.ndarray  # [H, W] float32 calibrated z-depth 1 / (s d_m_inv + b); 0 = invalid (sky, non-positive)
    inliers: np.ndarray  # [H, W] bool pixels that agreed with the fit (a subset of the valid mask)
    n_valid: int  # pixels used by the fit (valid, non-sky, positive geometry depth)
    sigma: float  # robust residual sigma in inverse-depth units

    @property
    def inlier_fraction(self) -> float:
        return float(self.inliers.sum()) / max(self.n_valid, 1)


def _lstsq(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least squares ``y ~ s x + b`` (closed form, float64)."""
    mx, my = x.mean(), y.mean()
    vx = ((x - mx) ** 2).sum()
    if vx <= 0:
        raise CalibrationError("the monocular inverse depth is constant over the valid pixels")
    s = float(((x - mx) * (y - my)).sum() / vx)
    return s, float(my - s * mx)


def _trimmed(x: np.ndarray, y: np.ndarray, s: float, b: float, h: int, max_steps: int
             ) -> tuple[float, float, float, np.ndarray]:
    """Concentration steps of least trimmed squares from ``(s, b)``: (s, b, trimmed SSE, kept indices)."""
    keep = None
    for _ in range(max_steps):
        r2 = (s * x + b - y) ** 2
        new = np.zeros(len(x), dtype=bool)  # the h smallest residuals, as a mask (x[mask] keeps index order)
        new[np.argpartition(r2, h - 1)[:h]] = True
        if keep is not None and np.array_equal(new, keep):
            break
        keep = new
        s, b = _lstsq(x[keep], y[keep])
    r2 = (s * x[keep] + b - y[keep]) ** 2
    return s, b, float(r2.sum()), keep


def calibrate_depth(inv_depth: np.ndarray, geo_depth: np.ndarray, valid: np.ndarray | None = None,
                    sky: np.ndarray | None = None, *, trim: float = 0.6, threshold: float = 3.0,
                    max_steps: int = 30, min_pixels: int = 16, max_fit_pixels: int = 16384) -> DepthCalibration:
    """Align monocular inverse depth ``inv_depth`` [H, W] to geometry z-depth ``geo_depth`` [H, W].

    ``valid`` (optional) marks trusted geometry pixels (e.g. confidence above a threshold); pixels with
    ``geo_depth <= 0``, non-finite values or ``sky`` are never used. ``trim`` is the fraction of pixels the
    trimmed fit keeps (it tolerates up to ``1 - trim`` outliers); ``threshold`` the inlier bound in robust
    sigmas. The trimmed fit of ``(s, b)`` runs on at most ``max_fit_pixels`` of the usable pixels (an even,
    deterministic stride through them: two numbers need no more, and it keeps the fit step's calibration of
    every frame cheap); the final refit, sigma and inliers use all of them. Raises ``CalibrationError`` with
    fewer than ``min_pixels`` usable pixels.
    """
    d_m = np.asarray(inv_depth, dtype=np.float64)
    d_v = np.asarray(geo_depth, dtype=np.float64)
    if d_m.shape != d_v.shape or d_m.ndim != 2:
        raise ValueError(f"inv_depth and geo_depth must be [H, W] of one shape, got {d_m.shape} and {d_v.shape}")
    if not 0.0 < trim <= 1.0:
        raise ValueError(f"trim must be in (0, 1], got {trim}")
    mask = np.isfinite(d_m) & np.isfinite(d_v) & (d_v > 0)
    if valid is not None:
        mask &= np.asarray(valid, dtype=bool)
    sky_mask = np.zeros_like(mask) if sky is None else np.asarray(sky, dtype=bool)
    mask &= ~sky_mask
    n = int(mask.sum())
    if n < min_pixels:
        raise CalibrationError(f"only {n} pixels have valid geometry and monocular depth (need {min_pixels})")
    x_all, y_all = d_m[mask], 1.0 / d_v[mask]
    stride = max(1, -(-n // max_fit_pixels))
    x, y = x_all[::stride], y_all[::stride]
    h = max(min_pixels // 2, int(np.ceil(trim * len(x))))
    # two starts: ordinary least squares, and matching the medians and interquartile ranges
    qx, qy = np.percentile(x, [25, 50, 75]), np.percentile(y, [25, 50, 75])
    starts = [_lstsq(x, y)]
    if qx[2] > qx[0]:
        s0 = (qy[2] - qy[0]) / (qx[2] - qx[0])
        starts.append((float(s0), float(qy[1] - s0 * qx[1])))
    best = min((_trimmed(x, y, s, b, h, max_steps) for s, b in starts), key=lambda t: t[2])
    s, b, _, keep = best
    x, y = x_all, y_all  # sigma, inliers and the refit over every usable pixel
    res = s * x + b - y
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(res)))  # over all pixels: robust while outliers < 50 %
    sigma = max(sigma, 1e-12 * max(float(np.abs(y).max()), 1e-12))
    inl = np.abs(res) <= threshold * sigma
    if inl.sum() >= 2:
        s, b = _lstsq(x[inl], y[inl])
        res = s * x + b - y
        inl = np.abs(res) <= threshold * sigma
    inliers = np.zeros_like(mask)
    inliers[mask] = inl
    inv = s * d_m + b
    ok = np.isfinite(inv) & (inv > 0) & ~sky_mask
    depth = np.zeros(d_m.shape, dtype=np.float32)
    depth[ok] = (1.0 / inv[ok]).astype(np.float32)
    return DepthCalibration(scale=s, bias=b, depth=depth, inliers=inliers, n_valid=n, sigma=sigma)

"""The Fréchet distance between two Gaussians, as used by FID and FVD.

For feature statistics ``(mu1, sigma1)`` and ``(mu2, sigma2)`` (mean vectors and covariance matrices of
network features of two sample sets), the Fréchet (2-Wasserstein) distance between the Gaussians
``N(mu1, sigma1)`` and ``N(mu2, sigma2)`` is (Dowson & Landau 1982; used for FID by Heusel et al. 2017,
"GANs Trained by a Two Time-Scale Update Rule ...", and for FVD by Unterthiner et al. 2018)::

    d^2 = ||mu1 - mu2||^2 + Tr(sigma1 + sigma2 - 2 (sigma1 sigma2)^(1/2))

Three ways to get ``Tr((sigma1 sigma2)^(1/2))`` are implemented; they are equal in exact arithmetic:

* ``method="sqrtm"`` (default): the principal square root of the product by ``scipy.linalg.sqrtm``, as the
  reference FID code does (TTUR, pytorch-fid): if the result is not finite (a singular product), the
  product is recomputed with ``eps * I`` added to both covariances; a complex result whose diagonal has
  an imaginary part above ``1e-3`` is an error, otherwise its real part is used. Slow for 2048-d features
  (about 25 s on 2 CPU cores).
* ``method="eigh"``: ``sigma1 sigma2`` is similar to the symmetric PSD matrix
  ``A = sigma1^(1/2) sigma2 sigma1^(1/2)``, so the trace is the sum of the square roots of the (clipped
  non-negative) eigenvalues of ``A``; this is the route of TF-GAN's ``trace_sqrt_product``, which the
  original FVD code uses. Fast and stable for singular (few-sample) covariances. Eigenvalues below
  ``D * machine-eps * largest`` are round-off and count as 0.
* ``method="gram"`` (from features only, ``frechet_distance_from_features``): with centred feature matrices
  ``X1`` (``N1 x D``) and ``X2``, the non-zero eigenvalues of ``sigma1 sigma2`` are the squared singular
  values of ``X1 X2^T / sqrt((N1 - 1)(N2 - 1))``, so the trace is that matrix's nuclear norm. Exact and
  cheap when the sample counts are small (it never forms a ``D x D`` matrix); memory grows as ``N1 N2``.

Statistics follow the reference code: mean over samples and the unbiased (``N - 1``) sample covariance,
in float64.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy import linalg

TraceMethod = Literal["sqrtm", "eigh"]
FeatureMethod = Literal["sqrtm", "eigh", "gram"]

# Largest imaginary part on the diagonal of sqrtm's result that is treated as round-off (reference FID code).
IMAG_TOLERANCE = 1e-3


def _as_features(features: ArrayLike) -> np.ndarray:
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"features must be N x D, got shape {f.shape}")
    if f.shape[0] < 2:
        raise ValueError(f"need at least 2 samples for a covariance, got {f.shape[0]}")
    if not np.isfinite(f).all():
        raise ValueError("features contain NaN or infinite values")
    return f


def feature_statistics(features: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(D,)`` and unbiased covariance ``(D, D)`` (float64) of ``features`` of shape ``(N, D)``, ``N >= 2``."""
    f = _as_features(features)
    return f.mean(axis=0), np.cov(f, rowvar=False)


def _check_stats(mu1: ArrayLike, sigma1: ArrayLike, mu2: ArrayLike, sigma2: ArrayLike
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    m1, m2 = np.atleast_1d(np.asarray(mu1, np.float64)), np.atleast_1d(np.asarray(mu2, np.float64))
    s1, s2 = np.atleast_2d(np.asarray(sigma1, np.float64)), np.atleast_2d(np.asarray(sigma2, np.float64))
    if m1.ndim != 1 or m1.shape != m2.shape:
        raise ValueError(f"means must be vectors of the same length, got {m1.shape} and {m2.shape}")
    d = m1.shape[0]
    if s1.shape != (d, d) or s2.shape != (d, d):
        raise ValueError(f"covariances must be {d}x{d}, got {s1.shape} and {s2.shape}")
    return m1, s1, m2, s2


def _clip_roundoff(w: np.ndarray) -> np.ndarray:
    """Eigenvalues of a PSD matrix with round-off (negative or below ``D * eps * max``) set to 0."""
    tol = max(w.shape[0], 1) * np.finfo(np.float64).eps * max(float(np.abs(w).max(initial=0.0)), 0.0)
    return np.where(w > tol, w, 0.0)


def _psd_sqrt(sigma: np.ndarray) -> np.ndarray:
    """Symmetric square root of a (numerically) symmetric PSD matrix."""
    w, v = np.linalg.eigh(0.5 * (sigma + sigma.T))
    return (v * np.sqrt(_clip_roundoff(w))) @ v.T


def trace_sqrt_product(sigma1: np.ndarray, sigma2: np.ndarray, eps: float = 1e-6,
                       method: TraceMethod = "sqrtm") -> float:
    """``Tr((sigma1 sigma2)^(1/2))`` for two covariance matrices (see the module docstring for the methods)."""
    if method == "eigh":
        r = _psd_sqrt(sigma1)
        a = r @ sigma2 @ r
        w = np.linalg.eigvalsh(0.5 * (a + a.T))
        return float(np.sqrt(_clip_roundoff(w)).sum())
    if method != "sqrtm":
        raise ValueError(f"method must be 'sqrtm' or 'eigh', got {method!r}")
    covmean = linalg.sqrtm(sigma1 @ sigma2)
    if not np.isfinite(covmean).all():
        offset = eps * np.eye(sigma1.shape[0])
        covmean = linalg.sqrtm((sigma1 + offset) @ (sigma2 + offset))
    if np.iscomplexobj(covmean):
        imag = float(np.abs(np.diagonal(covmean).imag).max(initial=0.0))
        if imag > IMAG_TOLERANCE:
            raise ValueError(f"sqrtm of the covariance product has an imaginary component {imag:.3g}; "
                             "try method='eigh'")
        covmean = covmean.real
    return float(np.trace(covmean))


def frechet_distance(mu1: ArrayLike, sigma1: ArrayLike, mu2: ArrayLike, sigma2: ArrayLike, eps: float = 1e-6,
                     method: TraceMethod = "sqrtm") -> float:
    """``||mu1 - mu2||^2 + Tr(sigma1 + sigma2 - 2 (sigma1 sigma2)^(1/2))`` (the FID / FVD formula).

    ``eps`` is added to the covariances' diagonals only when ``sqrtm`` of their product is not finite.
    The result may be slightly negative (round-off) for (nearly) identical statistics.
    """
    m1, s1, m2, s2 = _check_stats(mu1, sigma1, mu2, sigma2)
    diff = m1 - m2
    tr_covmean = trace_sqrt_product(s1, s2, eps=eps, method=method)
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * tr_covmean)


def frechet_distance_from_features(features1: ArrayLike, features2: ArrayLike, eps: float = 1e-6,
                                   method: FeatureMethod = "sqrtm") -> float:
    """Fréchet distance between the Gaussians fitted to two feature sets ``(N1, D)`` and ``(N2, D)``."""
    if method == "gram":
        return _frechet_gram(features1, features2)
    mu1, sigma1 = feature_statistics(features1)
    mu2, sigma2 = feature_statistics(features2)
    return frechet_distance(mu1, sigma1, mu2, sigma2, eps=eps, method=method)


def _frechet_gram(features1: ArrayLike, features2: ArrayLike) -> float:
    f1, f2 = _as_features(features1), _as_features(features2)
    if f1.shape[1] != f2.shape[1]:
        raise ValueError(f"feature sets differ in dimension: {f1.shape[1]} vs {f2.shape[1]}")
    mu1, mu2 = f1.mean(axis=0), f2.mean(axis=0)
    x1, x2 = f1 - mu1, f2 - mu2
    n1, n2 = f1.shape[0] - 1, f2.shape[0] - 1
    tr1, tr2 = float(np.sum(x1 * x1)) / n1, float(np.sum(x2 * x2)) / n2
    tr_covmean = float(np.linalg.svd(x1 @ x2.T, compute_uv=False).sum()) / np.sqrt(n1 * n2)
    diff = mu1 - mu2
    return float(diff @ diff + tr1 + tr2 - 2.0 * tr_covmean)

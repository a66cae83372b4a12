"""Real spherical harmonics up to degree 3, in the convention of the original 3D Gaussian Splatting code.

The basis order, signs and constants are those of 3DGS (and gsplat, and every common splat viewer), so SH
coefficients written to a 3DGS PLY by :mod:`navcrafter.models.gaussians.ply` mean the same thing
elsewhere. Colours are ``max(sum_k c_k Y_k(d) + 0.5, 0)``: the 0.5 offset makes an all-zero Gaussian
mid-grey, and the DC term alone gives ``C0 * dc + 0.5`` (see :func:`rgb_to_sh_dc`).

``d`` is the unit viewing direction from the camera centre to the Gaussian's mean, in world coordinates.
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per colour channel for ``degree`` (1, 4, 9, 16)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def sh_degree_from_bases(num_bases: int) -> int:
    """Inverse of :func:`num_sh_bases`."""
    for d in range(MAX_SH_DEGREE + 1):
        if (d + 1) ** 2 == num_bases:
            return d
    raise ValueError(f"{num_bases} SH coefficients per channel is not (degree + 1)^2 for a degree in 0..3")


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """The ``(degree + 1)^2`` real SH basis functions at unit directions ``dirs`` [..., 3] -> [..., K]."""
    k = num_sh_bases(degree)
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    assert len(out) == k
    return torch.stack(out, dim=-1)


def sh_to_rgb(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Colour of SH coefficients ``coeffs`` [..., K, 3] seen along ``dirs`` [..., 3] (normalised here).

    Uses the first ``(degree + 1)^2`` coefficients (``K`` may be larger: a model can be rendered at a lower
    degree than it stores, as gsplat allows). Returns ``max(sum + 0.5, 0)`` [..., 3], differentiable in
    both arguments.
    """
    k = num_sh_bases(degree)
    if coeffs.shape[-1] != 3 or coeffs.shape[-2] < k:
        raise ValueError(f"SH coefficients must be [..., K>={k}, 3] for degree {degree}, got {tuple(coeffs.shape)}")
    d = torch.nn.functional.normalize(dirs, dim=-1)
    basis = sh_basis(degree, d)  # [..., k]
    rgb = (basis[..., :, None] * coeffs[..., :k, :]).sum(dim=-2)
    return torch.clamp_min(rgb + 0.5, 0.0)


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient whose colour (alone) is ``rgb`` (the 3DGS ``RGB2SH``)."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    """Colour of a DC coefficient alone, before the clamp (the 3DGS ``SH2RGB``)."""
    return dc * SH_C0 + 0.5

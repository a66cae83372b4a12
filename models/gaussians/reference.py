"""Brute-force reference for :func:`navcrafter.models.gaussians.rasterize.rasterization` (tests, benchmarks).

Deliberately naive and written independently of the fast renderer: per camera, the rotation comes from the
Rodrigues form ``I + 2w[v]x + 2[v]x^2``, the 2D covariance from explicit matrix products and its inverse
from ``torch.linalg.inv``; every Gaussian is tested against every pixel (a dense [pixels, N] matrix), and
compositing is a plain front-to-back loop over the depth-sorted Gaussians with gsplat's per-pixel rules
(skip ``alpha < 1/255``, stop before ``T <= 1e-4``). The conventions it shares with the fast renderer on
purpose are the definitions, not the code: gsplat's radius estimate, its tile rule (a Gaussian is seen by
the pixels of the 16x16 tiles its ``mean +- radius`` square touches) and the Jacobian clamp.

Cost O(C * H * W * N) memory and a Python loop over N: only for small scenes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from navcrafter.models.gaussians.sh import sh_to_rgb

_ALPHA_MIN = 1.0 / 255.0
_T_STOP = 1e-4


def _rotation_rodrigues(quats: Tensor) -> Tensor:
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, v = q[:, 0], q[:, 1:]
    zero = torch.zeros_like(w)
    skew = torch.stack(
        [
            torch.stack([zero, -v[:, 2], v[:, 1]], dim=-1),
            torch.stack([v[:, 2], zero, -v[:, 0]], dim=-1),
            torch.stack([-v[:, 1], v[:, 0], zero], dim=-1),
        ],
        dim=-2,
    )
    eye = torch.eye(3, dtype=quats.dtype, device=quats.device).expand_as(skew)
    return eye + 2.0 * w[:, None, None] * skew + 2.0 * skew @ skew


def rasterize_reference(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,
    render_mode: str = "RGB",
    rasterize_mode: str = "classic",
    alpha_clamp: float = 0.99,
) -> tuple[Tensor, Tensor, dict]:
    """Same contract as ``rasterization`` (meta holds ``radii`` only)."""
    dtype, device = means.dtype, means.device
    n = means.shape[0]
    n_cam = viewmats.shape[0]
    rot = _rotation_rodrigues(quats)
    sigma3 = rot @ torch.diag_embed(scales * scales) @ rot.transpose(1, 2)  # [N, 3, 3]
    eye2 = torch.eye(2, dtype=dtype, device=device)
    jj, ii = torch.meshgrid(torch.arange(width, device=device), torch.arange(height, device=device), indexing="xy")
    centres = torch.stack([jj, ii], dim=-1).reshape(-1, 2).to(dtype) + 0.5  # [P, 2], row-major pixels
    pix_tx, pix_ty = (jj // tile_size).reshape(-1), (ii // tile_size).reshape(-1)
    tiles_w, tiles_h = math.ceil(width / tile_size), math.ceil(height / tile_size)

    renders, alphas_out, radii_out = [], [], []
    for c in range(n_cam):
        w_rot, w_t = viewmats[c, :3, :3], viewmats[c, :3, 3]
        p = means @ w_rot.T + w_t  # [N, 3] camera coordinates
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        depth_ok = (z > near_plane) & (z < far_plane)
        zs = torch.where(depth_ok, z, torch.ones_like(z))
        k = Ks[c]
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        # Jacobian of (x, y, z) -> (fx x / z, fy y / z) at the mean, x/z and y/z clamped to 1.3x the FoV
        lim_x = (-(cx / fx + 0.3 * 0.5 * width / fx), (width - cx) / fx + 0.3 * 0.5 * width / fx)
        lim_y = (-(cy / fy + 0.3 * 0.5 * height / fy), (height - cy) / fy + 0.3 * 0.5 * height / fy)
        tx = torch.minimum(torch.maximum(x / zs, lim_x[0]), lim_x[1])
        ty = torch.minimum(torch.maximum(y / zs, lim_y[0]), lim_y[1])
        jac = torch.zeros(n, 2, 3, dtype=dtype, device=device)
        jac[:, 0, 0] = fx / zs
        jac[:, 0, 2] = -fx * tx / zs
        jac[:, 1, 1] = fy / zs
        jac[:, 1, 2] = -fy * ty / zs
        cov_cam = w_rot @ sigma3 @ w_rot.T
        cov2_raw = jac @ cov_cam @ jac.transpose(1, 2)
        cov2 = cov2_raw + eps2d * eye2
        det = torch.linalg.det(cov2)
        visible = depth_ok & (det > 0)
        conic = torch.linalg.inv(torch.where(visible[:, None, None], cov2, eye2.expand_as(cov2)))
        u = (k[0, 0] * x + k[0, 1] * y) / zs + k[0, 2]
        v = k[1, 1] * y / zs + k[1, 2]
        with torch.no_grad():
            b = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
            radius = torch.ceil(3.0 * torch.sqrt(b + torch.sqrt(torch.clamp(b * b - det, min=0.01))))
            on_screen = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
            visible = visible & on_screen & (radius > radius_clip)
            radius = torch.where(visible, radius, torch.zeros_like(radius))
            tx0 = torch.floor(u / tile_size - radius / tile_size).clamp(0, tiles_w)
            tx1 = torch.ceil(u / tile_size + radius / tile_size).clamp(0, tiles_w)
            ty0 = torch.floor(v / tile_size - radius / tile_size).clamp(0, tiles_h)
            ty1 = torch.ceil(v / tile_size + radius / tile_size).clamp(0, tiles_h)
        opac = opacities
        if rasterize_mode == "antialiased":
            opac = opac * torch.sqrt(torch.clamp(torch.linalg.det(cov2_raw) / det.clamp(min=1e-30), min=0.0))

        if render_mode in ("D", "ED"):
            feats = z[:, None]
        else:
            if sh_degree is None:
                feats = colors if colors.dim() == 2 else colors[c]
            else:
                campos = -w_rot.T @ w_t
                coeffs = colors if colors.dim() == 3 else colors[c]
                feats = sh_to_rgb(sh_degree, means - campos, coeffs)
            if render_mode in ("RGB+D", "RGB+ED"):
                feats = torch.cat([feats, z[:, None]], dim=-1)
        bg = None
        if backgrounds is not None:
            bg = torch.zeros(feats.shape[-1], dtype=dtype, device=device)
            if render_mode not in ("D", "ED"):
                n_col = feats.shape[-1] - (1 if render_mode in ("RGB+D", "RGB+ED") else 0)
                bg = torch.cat([backgrounds[c, :n_col].to(dtype), bg[n_col:]])

        # every Gaussian against every pixel
        mean2d = torch.stack([u, v], dim=-1)  # [N, 2]
        delta = centres[:, None, :] - mean2d[None, :, :]  # [P, N, 2]
        half_q = 0.5 * torch.einsum("pni,nij,pnj->pn", delta, conic, delta)
        alpha = torch.clamp(opac[None, :] * torch.exp(-half_q), max=alpha_clamp)
        in_tile = ((pix_tx[:, None] >= tx0[None]) & (pix_tx[:, None] < tx1[None]) & (pix_ty[:, None] >= ty0[None])) & (
            pix_ty[:, None] < ty1[None]
        )
        candidate = visible[None, :] & in_tile & (half_q >= 0) & (alpha >= _ALPHA_MIN)

        n_pix = centres.shape[0]
        trans = torch.ones(n_pix, dtype=dtype, device=device)
        done = torch.zeros(n_pix, dtype=torch.bool, device=device)
        acc = torch.zeros(n_pix, feats.shape[-1], dtype=dtype, device=device)
        order = torch.argsort(z.detach(), stable=True)
        # per-Gaussian columns as separate tensors (unbind: one cheap backward op, unlike N column selects)
        alpha_cols = torch.where(candidate, alpha, torch.zeros_like(alpha)).T.unbind(0)
        feat_rows = feats.unbind(0)
        for g in order[visible[order]].tolist():
            a = torch.where(done, torch.zeros_like(alpha_cols[g]), alpha_cols[g])
            stop = (a > 0) & (trans * (1.0 - a) <= _T_STOP)
            done = done | stop
            a = torch.where(stop, torch.zeros_like(a), a)
            acc = acc + (a * trans)[:, None] * feat_rows[g][None, :]
            trans = trans * (1.0 - a)
        if bg is not None:
            acc = acc + trans[:, None] * bg[None, :]
        alpha_img = (1.0 - trans)[:, None]
        if render_mode in ("ED", "RGB+ED"):
            acc = torch.cat([acc[:, :-1], acc[:, -1:] / alpha_img.clamp(min=1e-10)], dim=-1)
        renders.append(acc.reshape(height, width, -1))
        alphas_out.append(alpha_img.reshape(height, width, 1))
        radii_out.append(radius.to(torch.int32))
    return torch.stack(renders), torch.stack(alphas_out), {"radii": torch.stack(radii_out)}

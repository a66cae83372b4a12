"""Differentiable 3D Gaussian Splatting rasterizer in pure PyTorch (the CPU backend).

:func:`rasterization` has the inputs, outputs and semantics of gsplat's ``gsplat.rasterization`` (for one
batch of cameras, ``packed`` irrelevant), so the CUDA backend can be gsplat itself:

* ``means`` [N, 3], ``quats`` [N, 4] (w, x, y, z; normalised here), ``scales`` [N, 3] (activated, i.e.
  ``exp`` of the stored log-scales), ``opacities`` [N] (activated, i.e. ``sigmoid`` of the logits),
  ``colors`` [N, D] / [C, N, D] post-activation features, or SH coefficients [N, K, 3] / [C, N, K, 3] when
  ``sh_degree`` is given (view direction: camera centre -> mean; colour ``max(SH + 0.5, 0)``).
* ``viewmats`` [C, 4, 4] world-to-camera in the **OpenCV** convention (+x right, +y down, +z forward; the
  inverse of navcrafter's camera-to-world poses), ``Ks`` [C, 3, 3] pinhole intrinsics, pixel ``(row i,
  col j)`` centred at ``(j + 0.5, i + 0.5)``.
* returns ``render_colors`` [C, H, W, X] (X = D, or 1 for ``"D"``/``"ED"``, or D + 1 with the depth last),
  ``render_alphas`` [C, H, W, 1] and a ``meta`` dict of intermediate results (``radii``, ``means2d``,
  ``depths``, ``conics``, ``opacities``, tile counts). ``"D"`` is the accumulated z-depth
  ``sum_i w_i z_i``; ``"ED"`` the expected depth ``D / max(alpha, 1e-10)``. Backgrounds apply to colour
  channels only (``C_pixel += T_final * background``); depth channels get no background.

The algorithm is the one of 3DGS / gsplat: covariance ``R S S^T R^T``; EWA projection with the Jacobian of
the perspective map (the mean clamped to 1.3x the field of view for the Jacobian only) plus a ``eps2d``
(0.3 px^2) low-pass dilation; culling of Gaussians outside ``(near_plane, far_plane)``, with a singular 2D
covariance, or whose 3-sigma square (radius ``ceil(3 sqrt(lambda_max))``, lambda_max as gsplat estimates it)
misses the image; 16x16 tiles, each Gaussian listed in the tiles its square touches; per tile a depth sort
(z of the mean) and front-to-back compositing of ``alpha = min(alpha_clamp, o * exp(-q/2))``, skipping
``alpha < 1/255`` and stopping a pixel (exclusive) once its transmittance would drop to ``<= 1e-4``.

Differences to gsplat's CUDA kernels, all deliberate or documented: ``alpha_clamp`` defaults to 0.99 (the
original 3DGS; gsplat uses 0.999 -- pass ``alpha_clamp=0.999`` for gsplat parity); radii are gsplat's
classic isotropic 3-sigma bound (newer gsplat releases use a tighter, opacity-aware bound per axis, which
changes which tiles see a Gaussian's faint tail); no batch dimensions, fisheye/ortho cameras, ``packed``,
``sparse_grad``, ``absgrad`` or distributed mode.

How it is vectorised (same results as gsplat's tile loop, without materialising tiles): a Gaussian may only
touch the pixels of the tiles its square covers (gsplat's rule) and, inside them, only pixels in the
bounding box of its ``alpha >= 1/255`` ellipse ``q <= 2 ln(255 o)``; those candidate (pixel, Gaussian)
pairs are enumerated and tested without autograd, and the survivors are sorted by (pixel, depth rank).
Transmittance is a segmented exclusive product, computed as a float64 cumulative sum of ``log(1 - alpha)``;
the early-stop rule truncates each pixel's list. Only the surviving pairs are evaluated again with autograd,
so memory and time scale with the pixel-Gaussian pairs that actually contribute. Deterministic on CPU.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor

from navcrafter.models.gaussians.sh import sh_to_rgb

RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
ALPHA_THRESHOLD = 1.0 / 255.0  # contributions below this are skipped (3DGS, gsplat)
TRANSMITTANCE_STOP = 1e-4  # a pixel stops before the Gaussian that would take T to <= this
DEFAULT_ALPHA_CLAMP = 0.99  # original 3DGS; gsplat uses 0.999
ED_ALPHA_MIN = 1e-10  # "ED": the accumulated depth over max(alpha, this)
_PAIRS_PER_CHUNK = 1 << 20  # pixel-Gaussian candidate pairs tested at once (bounds peak memory)


# --------------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------------
def _mm(a: Tensor, b: Tensor) -> Tensor:
    """Batched product of small matrices by broadcasting (much faster than ``bmm`` on CPU for 3x3)."""
    return (a[..., :, :, None] * b[..., None, :, :]).sum(dim=-2)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of (w, x, y, z) quaternions [..., 4] (normalised first)."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """3D covariances ``R diag(s)^2 R^T`` [N, 3, 3]."""
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return _mm(m, m.transpose(-1, -2))


def project_gaussians(
    means: Tensor,
    covars: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    calc_compensations: bool = False,
) -> dict[str, Tensor | None]:
    """EWA projection of N Gaussians into C pinhole cameras (gsplat's ``fully_fused_projection``, unpacked).

    Returns ``radii`` [C, N] int32 (0 = culled), ``means2d`` [C, N, 2], ``depths`` [C, N] (camera z),
    ``conics`` [C, N, 3] (upper triangle ``a, b, c`` of the inverse dilated 2D covariance), ``covars2d``
    [C, N, 2, 2] (dilated) and ``compensations`` [C, N] (``sqrt(det(S) / det(S + eps2d I))``, only when asked).
    Values of culled Gaussians are finite but meaningless.
    """
    rot = viewmats[:, :3, :3]
    trans = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]  # [C, N, 3]
    covars_c = _mm(_mm(rot[:, None], covars[None]), rot.transpose(1, 2)[:, None])  # [C, N, 3, 3]
    x, y, z = means_c.unbind(-1)
    depth_ok = (z > near_plane) & (z < far_plane)
    zs = torch.where(depth_ok, z, torch.ones_like(z))  # keeps culled Gaussians finite (and their grads zero)

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    xj = zs * torch.clamp(x / zs, min=-lim_x_neg, max=lim_x_pos)
    yj = zs * torch.clamp(y / zs, min=-lim_y_neg, max=lim_y_pos)
    zero = torch.zeros_like(zs)
    jac = torch.stack([fx / zs, zero, -fx * xj / (zs * zs), zero, fy / zs, -fy * yj / (zs * zs)], dim=-1)
    jac = jac.reshape(zs.shape + (2, 3))
    cov2d = _mm(_mm(jac, covars_c), jac.transpose(-1, -2))  # [C, N, 2, 2]
    means2d = torch.einsum("cij,cnj->cni", Ks[:, :2, :3], torch.stack([x, y, zs], dim=-1)) / zs[..., None]

    det_orig = cov2d[..., 0, 0] * cov2d[..., 1, 1] - cov2d[..., 0, 1] * cov2d[..., 1, 0]
    cov2d = cov2d + eps2d * torch.eye(2, dtype=cov2d.dtype, device=cov2d.device)
    det = cov2d[..., 0, 0] * cov2d[..., 1, 1] - cov2d[..., 0, 1] * cov2d[..., 1, 0]
    valid = depth_ok & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack(
        [
            cov2d[..., 1, 1] / det_safe,
            -0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0]) / det_safe,
            cov2d[..., 0, 0] / det_safe,
        ],
        dim=-1,
    )
    compensations = None
    if calc_compensations:
        compensations = torch.sqrt(torch.clamp(det_orig / det_safe, min=0.0))

    with torch.no_grad():
        b = 0.5 * (cov2d[..., 0, 0] + cov2d[..., 1, 1])
        v1 = b + torch.sqrt(torch.clamp(b * b - det_safe, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(v1))
        u, v = means2d[..., 0], means2d[..., 1]
        inside = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        keep = valid & inside & (radius > radius_clip)
        radii = torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32)
    return {
        "radii": radii,
        "means2d": means2d,
        "depths": z,
        "conics": conics,
        "covars2d": cov2d,
        "compensations": compensations,
    }


# --------------------------------------------------------------------------------------------------
# Tiles and compositing
# --------------------------------------------------------------------------------------------------
def tile_ranges(means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int, tile_height: int) -> Tensor:
    """Per (camera, Gaussian) the tiles its square ``mean +- radius`` touches, as gsplat's ``isect_tiles``
    computes them: ``[C, N, 4]`` int64 ``(x0, x1, y0, y1)``, half-open, clamped to the tile grid."""
    with torch.no_grad():
        tm = means2d.detach() / tile_size
        tr = radii.to(means2d.dtype) / tile_size
        x0 = torch.floor(tm[..., 0] - tr).clamp(0, tile_width)
        x1 = torch.ceil(tm[..., 0] + tr).clamp(0, tile_width)
        y0 = torch.floor(tm[..., 1] - tr).clamp(0, tile_height)
        y1 = torch.ceil(tm[..., 1] + tr).clamp(0, tile_height)
        return torch.stack([x0, x1, y0, y1], dim=-1).to(torch.int64)


def _pair_alpha(delta: Tensor, conic: Tensor, opacity: Tensor, alpha_clamp: float) -> tuple[Tensor, Tensor]:
    """``sigma = q/2`` and ``alpha`` of pixel offsets ``delta`` [..., 2] (pixel centre minus mean)."""
    dx, dy = delta[..., 0], delta[..., 1]
    sigma = 0.5 * (conic[..., 0] * dx * dx + conic[..., 2] * dy * dy) + conic[..., 1] * dx * dy
    alpha = torch.clamp(opacity * torch.exp(-sigma), max=alpha_clamp)
    return sigma, alpha


def _pixel_centres(pix: Tensor, width: int, height: int, dtype: torch.dtype) -> Tensor:
    """``(u, v)`` centres [M, 2] of flat pixel ids ``(camera * H + row) * W + col``."""
    return torch.stack([pix % width, (pix // width) % height], dim=-1).to(dtype) + 0.5


def _segment_exclusive_log_t(log1m: Tensor, seg_start: Tensor) -> Tensor:
    """Per element, ``sum`` of ``log1m`` over the earlier elements of its segment (segments contiguous;
    ``seg_start`` = index of each element's segment start)."""
    excl = torch.cumsum(log1m, dim=0) - log1m
    return excl - excl[seg_start]


def rasterize_to_pixels(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    *,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,
    alpha_clamp: float = DEFAULT_ALPHA_CLAMP,
    expected_depth: bool = False,
) -> tuple[Tensor, Tensor, dict[str, int]]:
    """Composite projected Gaussians front to back: ``colors`` [C, N, D], ``opacities`` [C, N] ->
    (``render`` [C, H, W, D], ``alphas`` [C, H, W, 1], counts). See the module docstring. With
    ``expected_depth`` the last feature (a depth) is rendered as the expected depth (:func:`normalize_depth`)."""
    n_cam, n = radii.shape
    d = colors.shape[-1]
    dtype, device = means2d.dtype, means2d.device
    tile_w, tile_h = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_pix = n_cam * height * width

    with torch.no_grad():
        m2, con, opa = means2d.detach(), conics.detach(), opacities.detach()
        rng = tile_ranges(means2d, radii, tile_size, tile_w, tile_h)
        tiles_per_gauss = (rng[..., 1] - rng[..., 0]) * (rng[..., 3] - rng[..., 2]) * (radii > 0)
        # Candidate pixels of each (camera, Gaussian): those of the tiles it is listed in (gsplat's rule),
        # narrowed to the bounding box of its alpha >= 1/255 ellipse, q <= 2 ln(255 o), plus a pixel of
        # margin. The box only skips pairs that the alpha test would reject anyway.
        inv_det = 1.0 / (con[..., 0] * con[..., 2] - con[..., 1] ** 2).clamp(min=1e-30)
        extent = 2.0 * torch.log(torch.clamp(opa * 255.0, min=1.0))
        half_w = torch.sqrt(extent * con[..., 2] * inv_det) + 1.0
        half_h = torch.sqrt(extent * con[..., 0] * inv_det) + 1.0
        u, v = m2[..., 0] - 0.5, m2[..., 1] - 0.5
        x0 = torch.maximum(torch.floor(u - half_w).clamp(min=0).to(torch.int64), rng[..., 0] * tile_size)
        x1 = torch.minimum(torch.floor(u + half_w).clamp(max=width - 1).to(torch.int64) + 1, rng[..., 1] * tile_size)
        y0 = torch.maximum(torch.floor(v - half_h).clamp(min=0).to(torch.int64), rng[..., 2] * tile_size)
        y1 = torch.minimum(torch.floor(v + half_h).clamp(max=height - 1).to(torch.int64) + 1, rng[..., 3] * tile_size)
        nx, ny = (x1 - x0).clamp(min=0), (y1 - y0).clamp(min=0)
        counts = nx * ny * ((radii > 0) & (extent > 0))
        flat_ids = torch.nonzero(counts.reshape(-1) > 0, as_tuple=True)[0]  # camera * N + Gaussian
        cnt = counts.reshape(-1)[flat_ids]
        n_cand = int(cnt.sum())
        # depth rank of each Gaussian within its camera (ties: index order, as a stable sort gives)
        order = torch.argsort(depths.detach(), dim=1, stable=True)
        rank = torch.empty_like(order)
        rank.scatter_(1, order, torch.arange(n, device=device).expand(n_cam, n).contiguous())

        pix_parts, gid_parts = [], []
        first = torch.cumsum(cnt, 0) - cnt
        bounds = torch.searchsorted(first, torch.arange(0, n_cand, _PAIRS_PER_CHUNK, device=device), right=True) - 1
        bounds = [*bounds.tolist(), len(flat_ids)]
        x0f, y0f, nxf = x0.reshape(-1), y0.reshape(-1), nx.reshape(-1)
        m2f, conf, opaf, rankf = m2.reshape(-1, 2), con.reshape(-1, 3), opa.reshape(-1), rank.reshape(-1)
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            if lo >= hi:
                continue
            kk = cnt[lo:hi]
            src = torch.repeat_interleave(torch.arange(hi - lo, device=device), kk)
            local = torch.arange(len(src), device=device) - (torch.cumsum(kk, 0) - kk)[src]
            ff = flat_ids[lo:hi][src]
            w_box = nxf[ff]
            px = x0f[ff] + local % w_box
            py = y0f[ff] + local // w_box
            delta = torch.stack([px, py], dim=-1).to(dtype) + 0.5 - m2f[ff]
            sigma, alpha = _pair_alpha(delta, conf[ff], opaf[ff], alpha_clamp)
            ok = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
            ff = ff[ok]
            pix_parts.append((torch.div(ff, max(n, 1), rounding_mode="floor") * height + py[ok]) * width + px[ok])
            gid_parts.append(ff)
        if pix_parts:
            pix, pflat = torch.cat(pix_parts), torch.cat(gid_parts)
        else:
            pix = pflat = torch.zeros(0, dtype=torch.int64, device=device)
        # group per pixel, front to back
        sort_idx = torch.argsort(pix * max(n, 1) + rankf[pflat])
        pix, pflat = pix[sort_idx], pflat[sort_idx]
        _, palpha = _pair_alpha(
            _pixel_centres(pix, width, height, dtype) - m2f[pflat], conf[pflat], opaf[pflat], alpha_clamp
        )

        # early stop: drop every pair from the one that would take T to <= 1e-4 on (per pixel)
        seg_counts = torch.bincount(pix, minlength=n_pix)
        seg_first = torch.cumsum(seg_counts, 0) - seg_counts
        log1m = torch.log1p(-palpha.to(torch.float64))
        log_t_incl = _segment_exclusive_log_t(log1m, seg_first[pix]) + log1m
        keep = log_t_incl > math.log(TRANSMITTANCE_STOP)
        pix, pflat = pix[keep], pflat[keep]
        seg_counts = torch.bincount(pix, minlength=n_pix)
        seg_first = torch.cumsum(seg_counts, 0) - seg_counts
        centre = _pixel_centres(pix, width, height, dtype)

    # the differentiable part, on the contributing pairs only
    _, alpha = _pair_alpha(
        centre - means2d.reshape(-1, 2).index_select(0, pflat),
        conics.reshape(-1, 3).index_select(0, pflat),
        opacities.reshape(-1).index_select(0, pflat),
        alpha_clamp,
    )
    log1m = torch.log1p(-alpha.to(torch.float64))
    trans = torch.exp(_segment_exclusive_log_t(log1m, seg_first[pix])).to(dtype)
    weights = alpha * trans
    render = torch.zeros(n_pix, d, dtype=dtype, device=device).index_add(
        0, pix, weights[:, None] * colors.reshape(-1, d).index_select(0, pflat)
    )
    log_t_final = torch.zeros(n_pix, dtype=torch.float64, device=device).index_add(0, pix, log1m)
    t_final = torch.exp(log_t_final).to(dtype)
    if backgrounds is not None:
        bg = backgrounds.to(dtype)[:, None, :].expand(n_cam, height * width, d).reshape(n_pix, d)
        render = render + t_final[:, None] * bg
    render = render.reshape(n_cam, height, width, d)
    alphas = (1.0 - t_final).reshape(n_cam, height, width, 1)
    if expected_depth:
        render = normalize_depth(render, alphas)
    info = {
        "tile_width": tile_w,
        "tile_height": tile_h,
        "tiles_per_gauss": tiles_per_gauss,
        "n_isects": int(tiles_per_gauss.sum()),
        "n_candidates": n_cand,
        "n_pairs": int(len(pix)),
    }
    return render, alphas, info


def normalize_depth(render: Tensor, alphas: Tensor) -> Tensor:
    """``render`` with its last feature, an accumulated depth ``D``, as the expected depth ``D / max(alpha,
    ED_ALPHA_MIN)`` (the render modes "ED" and "RGB+ED")."""
    return torch.cat([render[..., :-1], render[..., -1:] / alphas.clamp(min=ED_ALPHA_MIN)], dim=-1)


# --------------------------------------------------------------------------------------------------
# The gsplat-compatible entry point
# --------------------------------------------------------------------------------------------------
def _check_inputs(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    sh_degree: int | None,
    render_mode: str,
    covars: Tensor | None,
) -> None:
    n = means.shape[0]
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    if covars is None:
        if quats is None or scales is None or quats.shape != (n, 4) or scales.shape != (n, 3):
            raise ValueError(
                f"quats must be [N, 4] and scales [N, 3] for N={n}, got "
                f"{None if quats is None else tuple(quats.shape)} and {None if scales is None else tuple(scales.shape)}"
            )
    elif covars.shape != (n, 3, 3):
        raise ValueError(f"covars must be [N, 3, 3], got {tuple(covars.shape)}")
    if opacities.shape != (n,):
        raise ValueError(f"opacities must be [N] (activated), got {tuple(opacities.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must be [C, 4, 4] world-to-camera, got {tuple(viewmats.shape)}")
    c = viewmats.shape[0]
    if Ks.shape != (c, 3, 3):
        raise ValueError(f"Ks must be [C, 3, 3] for C={c}, got {tuple(Ks.shape)}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if sh_degree is None:
        if not (colors.dim() == 2 and colors.shape[0] == n) and not (colors.dim() == 3 and colors.shape[:2] == (c, n)):
            raise ValueError(f"colors must be [N, D] or [C, N, D] without sh_degree, got {tuple(colors.shape)}")
    else:
        ok = (colors.dim() == 3 and colors.shape[0] == n) or (colors.dim() == 4 and colors.shape[:2] == (c, n))
        if not ok or colors.shape[-1] != 3 or colors.shape[-2] < (sh_degree + 1) ** 2:
            raise ValueError(
                f"colors must be SH coefficients [N, K, 3] or [C, N, K, 3] with K >= {(sh_degree + 1) ** 2} "
                f"for sh_degree={sh_degree}, got {tuple(colors.shape)}"
            )


def resolve_colors(means: Tensor, colors: Tensor, viewmats: Tensor, sh_degree: int | None) -> Tensor:
    """Per-camera post-activation colours [C, N, D]: features as given, or SH evaluated along the direction
    from each camera centre to each mean."""
    n_cam, n = viewmats.shape[0], means.shape[0]
    if sh_degree is None:
        return colors if colors.dim() == 3 else colors[None].expand(n_cam, n, colors.shape[-1])
    campos = torch.linalg.inv(viewmats)[:, :3, 3]  # [C, 3]
    dirs = means[None, :, :] - campos[:, None, :]
    coeffs = colors if colors.dim() == 4 else colors[None].expand((n_cam,) + tuple(colors.shape))
    return sh_to_rgb(sh_degree, dirs, coeffs)


def composite_features(means: Tensor, colors: Tensor, viewmats: Tensor, sh_degree: int | None, radii: Tensor,
                       depths: Tensor, with_depth: bool) -> Tensor:
    """The features the compositing reads [C, N, D], or [C, N, D + 1] with the depth last (``with_depth``: the
    "RGB+D" / "RGB+ED" modes): :func:`resolve_colors`. ``radii`` (the projection's, 0 where culled) are not read
    here; the compiled renderer does not evaluate the SH of culled Gaussians (their features are never read)."""
    del radii
    feats = resolve_colors(means, colors, viewmats, sh_degree)
    return torch.cat([feats, depths[..., None]], dim=-1) if with_depth else feats


def rasterization(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
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
    packed: bool = False,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,
    render_mode: RenderMode = "RGB",
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    covars: Tensor | None = None,
    alpha_clamp: float = DEFAULT_ALPHA_CLAMP,
) -> tuple[Tensor, Tensor, dict]:
    """Render N Gaussians into C cameras; gsplat's ``rasterization`` contract (see the module docstring).

    ``packed`` is accepted for signature compatibility and ignored (results are always per camera and
    Gaussian). ``alpha_clamp`` is ours (gsplat hard-codes 0.999). Differentiable with respect to ``means``,
    ``quats``, ``scales``, ``opacities``, ``colors`` (features or SH), ``covars`` and ``backgrounds``;
    ``meta["means2d"]`` is part of the graph (``retain_grad()`` it for densification statistics).
    """
    del packed
    return render_gaussians(project_gaussians, rasterize_to_pixels, means, quats, scales, opacities, colors, viewmats,
                            Ks, width, height, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
                            eps2d=eps2d, sh_degree=sh_degree, tile_size=tile_size, backgrounds=backgrounds,
                            render_mode=render_mode, rasterize_mode=rasterize_mode, covars=covars,
                            alpha_clamp=alpha_clamp)


def render_gaussians(project, composite, means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
                     near_plane, far_plane, radius_clip, eps2d, sh_degree, tile_size, backgrounds, render_mode,
                     rasterize_mode, covars, alpha_clamp, features_fn=None,
                     project_qs=None) -> tuple[Tensor, Tensor, dict]:
    """:func:`rasterization`'s body over a pair of kernels: ``project`` (:func:`project_gaussians`'s contract)
    and ``composite`` (:func:`rasterize_to_pixels`'s), and optionally ``features_fn`` (:func:`composite_features`'s;
    the default); the compiled CPU kernels (``models.gaussians.cpu_rasterize``) plug in here, so the render
    modes, SH and checks are written once. ``project_qs``, if given, projects from ``quats`` and ``scales``
    directly when no ``covars`` are given (``project``'s contract with the two in place of ``covars``)."""
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, render_mode, covars)
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")
    if width <= 0 or height <= 0 or tile_size <= 0:
        raise ValueError(f"width, height and tile_size must be positive, got {width}, {height}, {tile_size}")
    if not 0.0 < alpha_clamp < 1.0:
        raise ValueError(f"alpha_clamp must be in (0, 1), got {alpha_clamp}")
    n_cam = viewmats.shape[0]
    kw = {"eps2d": eps2d, "near_plane": near_plane, "far_plane": far_plane, "radius_clip": radius_clip,
          "calc_compensations": rasterize_mode == "antialiased"}
    if covars is None and project_qs is not None:
        proj = project_qs(means, quats, scales, viewmats, Ks, width, height, **kw)
    else:
        if covars is None:
            covars = quat_scale_to_covar(quats, scales)
        proj = project(means, covars, viewmats, Ks, width, height, **kw)
    opac = opacities[None, :].expand(n_cam, -1)
    if proj["compensations"] is not None:
        opac = opac * proj["compensations"]
    depths = proj["depths"]

    if render_mode in ("D", "ED"):
        feats = depths[..., None]
        if backgrounds is not None:
            backgrounds = torch.zeros(n_cam, 1, dtype=means.dtype, device=means.device)
    else:
        with_depth = render_mode in ("RGB+D", "RGB+ED")
        feats = (features_fn or composite_features)(means, colors, viewmats, sh_degree, proj["radii"], depths,
                                                    with_depth)
        if with_depth:
            if backgrounds is not None:
                zeros = torch.zeros(n_cam, 1, dtype=backgrounds.dtype, device=backgrounds.device)
                backgrounds = torch.cat([backgrounds, zeros], dim=-1)
    if backgrounds is not None and backgrounds.shape != (n_cam, feats.shape[-1]):
        raise ValueError(f"backgrounds must be [C, D] = [{n_cam}, {feats.shape[-1]}], got {tuple(backgrounds.shape)}")

    render, alphas, info = composite(
        proj["means2d"],
        proj["conics"],
        feats,
        opac,
        proj["radii"],
        depths,
        width,
        height,
        tile_size=tile_size,
        backgrounds=backgrounds,
        alpha_clamp=alpha_clamp,
        expected_depth=render_mode in ("ED", "RGB+ED"),
    )
    meta = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": proj["radii"],
        "means2d": proj["means2d"],
        "depths": depths,
        "conics": proj["conics"],
        "opacities": opac,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_cameras": n_cam,
        **info,
    }
    return render, alphas, meta

"""The compiled CPU rasterizer: gsplat's ``rasterization`` contract on numba kernels (the default on the CPU).

:func:`rasterization` takes exactly the arguments of :func:`~navcrafter.models.gaussians.rasterize.rasterization`
(gsplat's signature) and gives the same results: the render modes and input checks are that module's
(``render_gaussians``); covariances, projection, SH of shared coefficients, tile binning and sorting, compositing
and their backward passes run in :mod:`~navcrafter.models.gaussians.cpu_kernels` (float64 arithmetic except the
compositing, which computes in the inputs' dtype: float32 in a fit; results in the inputs' dtype).
Tests hold both to each other and to the brute-force reference (``tests/models/gaussians/test_cpu_rasterizer.py``);
``benchmarks/rasterizer.py`` times them.

Differentiable with respect to ``means``, ``quats``, ``scales``, ``opacities``, ``colors`` (features or SH),
``covars`` and ``backgrounds`` (per-camera SH coefficients [C, N, K, 3] are evaluated by PyTorch); ``viewmats``
and ``Ks`` are not differentiated: a camera that needs gradients is refused with a pointer to the PyTorch
renderer. ``meta["means2d"]`` is part of the graph (densification's ``retain_grad()`` works).

Threads: numba's pool, :func:`set_threads` (``fit.threads``; default: every core numba sees, i.e.
``NUMBA_NUM_THREADS``). Results do not depend on the thread count (see the kernels' docstring). The threading
layer (``cpu_kernels``; ``NUMBA_THREADING_LAYER`` overrides it) is numba's OpenMP layer where
``OMP_WAIT_POLICY=PASSIVE`` (which the CLI, the tests and the benchmarks set, for torch's own threads too; numba's
``workqueue`` where no OpenMP runtime loads), else ``workqueue``: beside spinning OpenMP threads the OpenMP layer
costs ~8 ms per parallel call on a busy 2-core machine. Calls are serialised by a lock: the workqueue layer must
not be entered by two Python threads at once (the explore flow runs scenes on a thread pool); the kernels release
the GIL, so other work goes on meanwhile.
"""

from __future__ import annotations

import math
import sys
import threading
from typing import Literal

import numba
import numpy as np
import torch
from torch import Tensor

from navcrafter.models.gaussians import cpu_kernels as K
from navcrafter.models.gaussians.rasterize import (
    DEFAULT_ALPHA_CLAMP,
    ED_ALPHA_MIN,
    RenderMode,
    render_gaussians,
)
from navcrafter.models.gaussians.rasterize import composite_features as torch_composite_features
from navcrafter.models.gaussians.rasterize import resolve_colors as torch_resolve_colors

_LOCK = threading.Lock()


def set_threads(threads: int | None) -> int:
    """Use ``threads`` of numba's threads (None: all of them); returns the number in use."""
    top = numba.config.NUMBA_NUM_THREADS
    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        numba.set_num_threads(min(int(threads), top))
    else:
        numba.set_num_threads(top)
    return numba.get_num_threads()


class _Scratch:
    """Reused work arrays, outputs and gradients: a fresh multi-megabyte ``np.empty`` per call is fresh pages
    from the kernel, and touching them (page faults, zeroing) cost ~5-10 ms per 100k-Gaussian render (the
    outputs and gradients handed to PyTorch: ~2,700 faults, ~1.7 us each, per SH3 call when glibc returned them
    to the system between calls). A buffer is handed out again only when nothing references it any more (no view
    of it is alive: no autograd context waiting for its backward pass, no tensor made from it: a render, a meta
    entry or a ``.grad`` kept by the caller keeps its buffer), so results never share memory; a few per name, for
    a forward issued before the previous graph is freed."""

    KEEP = 3  # buffers kept per name
    ALIGN = 64  # bytes: arrays start on a cache line (a 16-float record row is one line, not two)

    def __init__(self) -> None:
        self._bufs: dict[str, list[np.ndarray]] = {}  # per name: buffers, each with its aligned start
        self._starts: dict[int, int] = {}
        self._lock = threading.Lock()

    def get(self, name: str, shape, dtype) -> np.ndarray:
        # ~36 calls per render: math.prod and the start kept per buffer (np.prod and ``ctypes.data`` took ~4 us of
        # the ~6.5 us per call)
        dtype = np.dtype(dtype)
        need = (math.prod(shape) if isinstance(shape, tuple) else int(shape)) * dtype.itemsize
        with self._lock:
            bufs = self._bufs.setdefault(name, [])
            for buf in bufs:
                # free: referenced only by the list, this loop's variable and getrefcount's argument
                if buf.nbytes >= need + self.ALIGN and sys.getrefcount(buf) <= 3:
                    break
            else:
                buf = np.empty(max(need + need // 4, 64) + self.ALIGN, dtype=np.uint8)  # headroom for the next call
                if len(bufs) >= self.KEEP:
                    self._starts.pop(id(bufs.pop(0)))
                bufs.append(buf)
                self._starts[id(buf)] = -buf.ctypes.data % self.ALIGN
            start = self._starts[id(buf)]
            return buf[start:start + need].view(dtype).reshape(shape)


_SCRATCH = _Scratch()


def _np(t: Tensor) -> np.ndarray:
    """A float64, C-contiguous NumPy copy of ``t`` (always a copy: the autograd functions keep these arrays for
    the backward pass, and a view would silently follow an in-place change of a float64 input)."""
    return np.array(t.detach().to(device="cpu", dtype=torch.float64).numpy(), dtype=np.float64, order="C", copy=True)


def _as_kernel_dtype(t: Tensor, dtype) -> np.ndarray:
    """``t`` on the CPU in the kernels' ``dtype`` (float32 for ``np.float32``, float64 otherwise), as NumPy;
    shares memory with ``t`` where it already is that (the callers copy or not)."""
    return t.detach().to(device="cpu", dtype=torch.float32 if dtype == np.float32 else torch.float64).numpy()


def _np_native(t: Tensor, dtype) -> np.ndarray:
    """A C-contiguous NumPy copy of ``t`` in ``dtype`` (float32 or float64: the kernels' input and output dtype)."""
    return np.array(_as_kernel_dtype(t, dtype), order="C", copy=True)


def _np_view(t: Tensor, dtype) -> np.ndarray:
    """``t`` as a C-contiguous array in ``dtype``, without a copy where it already is one: for inputs a kernel
    only reads during the call (nothing kept for a backward pass)."""
    return np.ascontiguousarray(_as_kernel_dtype(t, dtype))


def _dt(t: Tensor):
    """The NumPy dtype the kernels read and write for ``t``: float32 stays float32 (the kernels compute in
    float64 per Gaussian and round once on writing, as a conversion would), anything else is float64."""
    return np.float32 if t.dtype == torch.float32 else np.float64


def _grad_np(v: Tensor | None, shape, dt) -> np.ndarray:
    return np.zeros(shape, dt) if v is None else _np_native(v, dt)


def _grad_view(v: Tensor | None, shape, dt) -> np.ndarray:
    """An output gradient as the kernels read it, without a copy (any strides: the compositing's gradients
    arrive as views of one [C, N, 6 + D] array, and copying them cost ~1 ms per call at 100k Gaussians);
    zeros for None (no gradient flowed: the function does not materialise them)."""
    return np.zeros(shape, dt) if v is None else _as_kernel_dtype(v, dt)


def _out(a: np.ndarray, like: Tensor) -> Tensor:
    return torch.from_numpy(a).to(dtype=like.dtype, device=like.device)


class _Covar(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, scales):
        q, sc = _np(quats), _np(scales)
        covars = np.empty((len(q), 3, 3))
        with _LOCK:
            K.covar_forward(q, sc, covars)
        ctx.arrays, ctx.likes = (q, sc), (quats, scales)
        return _out(covars, scales)

    @staticmethod
    def backward(ctx, v_covars):
        q, sc = ctx.arrays
        v_q, v_s = np.empty_like(q), np.empty_like(sc)
        with _LOCK:
            K.covar_backward(q, sc, _np(v_covars), v_q, v_s)
        return _out(v_q, ctx.likes[0]), _out(v_s, ctx.likes[1])


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """:func:`~navcrafter.models.gaussians.rasterize.quat_scale_to_covar` on the compiled kernels."""
    return _Covar.apply(quats, scales)


class _SH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, degree, means, campos, dc, rest, radii, depths):
        # the coefficients: ``dc`` [N, K, 3] alone (``rest`` None), or ``dc`` [N, 3] and ``rest`` [N, K - 1, 3]
        # (a fit's two parameters: no [N, K, 3] concatenation, and contiguous gradients for each); read in their
        # own dtype, not copied (the biggest input of a fit): saved for backward, so an in-place change before it
        # is caught by autograd's version check. ``radii`` (the projection's; None: every colour) and ``depths``
        # (None: no depth column): the compositing's features (K.sh_forward).
        ins = (dc,) if rest is None else (dc, rest)
        co_t = tuple(t.detach().contiguous() for t in ins)
        dt = _dt(means)
        # the means read in place too (saved for backward: autograd's version check guards them)
        m = _np_view(means, dt)
        n_cam = len(campos)
        rad = np.zeros((0, 0), np.int32) if radii is None else np.ascontiguousarray(radii.numpy())
        dep = np.zeros((0, 0), dt) if depths is None else _np_view(depths, dt)
        rgb = _SCRATCH.get("sh_rgb", (n_cam, len(m), 3 if depths is None else 4), dt)
        cut = _SCRATCH.get("sh_cut", (n_cam, len(m)), np.uint8)  # where the clamp stops the gradient (3 bits)
        with _LOCK:
            K.sh_forward(degree, m, campos, *_coef_arrays(co_t), rad, dep, rgb, cut)
        ctx.save_for_backward(*co_t, means)
        ctx.arrays, ctx.degree, ctx.likes = (campos, rad, cut), degree, (means,) + ins
        ctx.with_depth = depths is not None
        return _out(rgb, means)

    @staticmethod
    def backward(ctx, v_rgb):
        cp, rad, cut = ctx.arrays
        *co_t, means = ctx.saved_tensors
        m = _np_view(means, _dt(means))
        cos = [_coef_array(t) for t in co_t]
        v_m = _SCRATCH.get("sh_v_means", m.shape, m.dtype)
        v_cos = [_SCRATCH.get(f"sh_v_coef{i}", c.shape, c.dtype) for i, c in enumerate(cos)]
        with _LOCK:  # v_rgb read in place (a view of the compositing's gradients: any strides)
            K.sh_backward(ctx.degree, m, cp, *_coef_arrays(cos), rad, cut, _as_kernel_dtype(v_rgb, m.dtype), v_m,
                          *_coef_arrays(v_cos)[:2])  # the gradients' rows: the coefficients' layout (r0)
        v_co = [_out(v, like) for v, like in zip(v_cos, ctx.likes[1:])]
        v_depths = v_rgb[..., 3] if ctx.with_depth else None
        return None, _out(v_m, ctx.likes[0]), None, v_co[0], v_co[1] if len(v_co) > 1 else None, None, v_depths


def _coef_array(t) -> np.ndarray:
    """Coefficients as the SH kernels read them: float32 / float64 in place, anything else as float64."""
    if isinstance(t, np.ndarray):
        return t
    return t.numpy() if t.dtype in (torch.float32, torch.float64) else _np(t)


def _rows(a: np.ndarray) -> np.ndarray:
    """[N, ...] contiguous as [N, M] rows: a view (a copy would lose a kernel's writes into it)."""
    if not a.flags.c_contiguous:
        raise ValueError("SH coefficient arrays must be C-contiguous")
    return a.reshape(a.shape[0], math.prod(a.shape[1:]))


def _coef_arrays(co) -> tuple[np.ndarray, np.ndarray, np.uintp]:
    """The SH kernels' coefficient rows (dc, rest, r0): one [N, K, 3] array as [N, 3 K] rows passed twice (r0 =
    3), or the two given ([N, 3] and [N, K - 1, 3], as [N, 3] and [N, 3 (K - 1)] rows; r0 = 0). Contiguous."""
    arrs = [_coef_array(t) for t in co]
    if len(arrs) == 1:
        rows = _rows(arrs[0])
        return rows, rows, np.uintp(3)
    return _rows(arrs[0]), _rows(arrs[1]), np.uintp(0)


def _campos(viewmats: Tensor) -> np.ndarray:
    return _np(torch.linalg.inv(viewmats.detach())[:, :3, 3])


def _compiled_sh(colors: Tensor, sh_degree: int | None) -> bool:
    """Whether ``colors`` are SH coefficients [N, K, 3] shared by the cameras, valid for ``sh_degree``: what the
    compiled SH evaluates (per-camera coefficients, plain features and invalid ones go to PyTorch's, whose checks
    name the problem)."""
    return (sh_degree is not None and colors.dim() == 3 and colors.shape[-1] == 3
            and colors.shape[-2] >= (sh_degree + 1) ** 2 and 0 <= sh_degree <= 3)


def resolve_colors(means: Tensor, colors: Tensor, viewmats: Tensor, sh_degree: int | None) -> Tensor:
    """:func:`~navcrafter.models.gaussians.rasterize.resolve_colors` with the SH of shared coefficients
    [N, K, 3] evaluated by the compiled kernels (per-camera coefficients and plain features: PyTorch's)."""
    if not _compiled_sh(colors, sh_degree):
        return torch_resolve_colors(means, colors, viewmats, sh_degree)
    return _SH.apply(int(sh_degree), means, _campos(viewmats), colors, None, None, None)


def composite_features(means: Tensor, colors: Tensor, viewmats: Tensor, sh_degree: int | None, radii: Tensor,
                       depths: Tensor, with_depth: bool) -> Tensor:
    """:func:`~navcrafter.models.gaussians.rasterize.composite_features` with the SH of shared coefficients [N, K,
    3] evaluated by the compiled kernels, the depth column written beside the colours (no concatenation), and the
    SH of Gaussians culled in a camera (radius 0: never composited) not evaluated there: zeros; what the
    compositing reads is :func:`resolve_colors`' bit for bit, and so are the gradients (per-camera coefficients and
    plain features: PyTorch's)."""
    if not _compiled_sh(colors, sh_degree):
        return torch_composite_features(means, colors, viewmats, sh_degree, radii, depths, with_depth)
    return _SH.apply(int(sh_degree), means, _campos(viewmats), colors, None, radii, depths if with_depth else None)


def sh_colors(means: Tensor, sh_dc: Tensor, sh_rest: Tensor, viewmats: Tensor, sh_degree: int) -> Tensor:
    """Per-camera colours [C, N, 3] of SH coefficients held as two tensors, ``sh_dc`` [N, 3] (degree 0) and
    ``sh_rest`` [N, K - 1, 3] (a fit's parameters), on the compiled kernels: the colours
    ``resolve_colors(means, torch.cat([sh_dc[:, None], sh_rest], 1), viewmats, sh_degree)`` gives, bit for bit,
    with their gradients, without the concatenation (a copy of every coefficient forward, and two backward)."""
    n = means.shape[0]
    if sh_dc.shape != (n, 3) or sh_rest.dim() != 3 or sh_rest.shape[0] != n or sh_rest.shape[2] != 3:
        raise ValueError(f"sh_dc must be [N, 3] and sh_rest [N, K - 1, 3] for N={n}, got {tuple(sh_dc.shape)} "
                         f"and {tuple(sh_rest.shape)}")
    if not 0 <= sh_degree <= 3 or sh_rest.shape[1] + 1 < (sh_degree + 1) ** 2:
        raise ValueError(f"sh_degree {sh_degree} needs 0..3 and K >= {(sh_degree + 1) ** 2} coefficients, got "
                         f"K = {sh_rest.shape[1] + 1}")
    return _SH.apply(int(sh_degree), means, _campos(viewmats), sh_dc, sh_rest, None, None)


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, covars, viewmats, Ks, width, height, eps2d, near, far, radius_clip):
        dt = _dt(means)
        m, cv, vm, k = _np_native(means, dt), _np(covars), _np(viewmats), _np(Ks)
        n_cam, n = vm.shape[0], m.shape[0]
        means2d, depths = np.empty((n_cam, n, 2), dt), np.empty((n_cam, n), dt)
        conics, comps = np.empty((n_cam, n, 3), dt), np.empty((n_cam, n), dt)
        radii = np.empty((n_cam, n), dtype=np.int32)
        with _LOCK:
            K.project_forward(m, cv, vm, k, width, height, eps2d, near, far, radius_clip,
                              means2d, depths, conics, radii, comps)
        ctx.arrays = (m, cv, vm, k)
        ctx.scalars = (width, height, eps2d, near, far)
        ctx.like = means
        radii_t = torch.from_numpy(radii).to(means.device)
        ctx.mark_non_differentiable(radii_t)
        return _out(means2d, means), _out(depths, means), _out(conics, means), _out(comps, means), radii_t

    @staticmethod
    def backward(ctx, v_means2d, v_depths, v_conics, v_comps, _v_radii):
        m, cv, vm, k = ctx.arrays
        n_cam, n, dt = vm.shape[0], m.shape[0], m.dtype
        v_comps_np = _grad_np(v_comps, (n_cam, n), dt)
        v_means, v_covars = np.empty((n, 3), dt), np.empty((n, 3, 3))
        with _LOCK:
            K.project_backward(m, cv, vm, k, *ctx.scalars, _grad_np(v_means2d, (n_cam, n, 2), dt),
                               _grad_np(v_depths, (n_cam, n), dt), _grad_np(v_conics, (n_cam, n, 3), dt), v_comps_np,
                               v_comps is not None, v_means, v_covars)
        like = ctx.like
        return _out(v_means, like), _out(v_covars, like), None, None, None, None, None, None, None, None


def project_gaussians(means: Tensor, covars: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int, *,
                      eps2d: float = 0.3, near_plane: float = 0.01, far_plane: float = 1e10, radius_clip: float = 0.0,
                      calc_compensations: bool = False) -> dict[str, Tensor | None]:
    """:func:`~navcrafter.models.gaussians.rasterize.project_gaussians` on the compiled kernels (no
    ``covars2d`` in the result: nothing downstream reads it)."""
    if viewmats.requires_grad or Ks.requires_grad:
        raise ValueError("the compiled CPU rasterizer does not differentiate viewmats or Ks; render with "
                         "backend='torch' (navcrafter's PyTorch rasterizer) to optimise cameras")
    means2d, depths, conics, comps, radii = _Project.apply(means, covars, viewmats, Ks, int(width), int(height),
                                                           float(eps2d), float(near_plane), float(far_plane),
                                                           float(radius_clip))
    return {"radii": radii, "means2d": means2d, "depths": depths, "conics": conics,
            "compensations": comps if calc_compensations else None}


class _ProjectQS(torch.autograd.Function):
    """:class:`_Project` with the covariances made from quaternions and scales inside the kernels (never
    stored, no [N, 3, 3] tensors crossing into PyTorch and back)."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmats, Ks, width, height, eps2d, near, far, radius_clip):
        dt = _dt(means)
        # read in place where they already are float32 / float64 and contiguous (no copies of the biggest
        # inputs); saved for backward, so an in-place change before it is caught by autograd's version check
        m, q, sc = _np_view(means, dt), _np_view(quats, _dt(quats)), _np_view(scales, _dt(scales))
        vm, k = _np(viewmats), _np(Ks)
        n_cam, n = vm.shape[0], m.shape[0]
        means2d, depths = _SCRATCH.get("qs_means2d", (n_cam, n, 2), dt), _SCRATCH.get("qs_depths", (n_cam, n), dt)
        conics, comps = _SCRATCH.get("qs_conics", (n_cam, n, 3), dt), _SCRATCH.get("qs_comps", (n_cam, n), dt)
        radii = _SCRATCH.get("qs_radii", (n_cam, n), np.int32)
        with _LOCK:
            K.project_qs_forward(m, q, sc, vm, k, width, height, eps2d, near, far, radius_clip,
                                 means2d, depths, conics, radii, comps)
        ctx.save_for_backward(means, quats, scales)
        ctx.set_materialize_grads(False)  # unused outputs (depths, compensations) give None, not zero tensors
        ctx.arrays = (vm, k)
        ctx.scalars = (width, height, eps2d, near, far)
        radii_t = torch.from_numpy(radii).to(means.device)
        ctx.mark_non_differentiable(radii_t)
        return _out(means2d, means), _out(depths, means), _out(conics, means), _out(comps, means), radii_t

    @staticmethod
    def backward(ctx, v_means2d, v_depths, v_conics, v_comps, _v_radii):
        means, quats, scales = ctx.saved_tensors
        m, q, sc = _np_view(means, _dt(means)), _np_view(quats, _dt(quats)), _np_view(scales, _dt(scales))
        vm, k = ctx.arrays
        n_cam, n, dt = vm.shape[0], m.shape[0], m.dtype
        v_means, v_quats = _SCRATCH.get("qs_v_means", (n, 3), dt), _SCRATCH.get("qs_v_quats", (n, 4), q.dtype)
        v_scales = _SCRATCH.get("qs_v_scales", (n, 3), sc.dtype)
        with _LOCK:
            K.project_qs_backward(m, q, sc, vm, k, *ctx.scalars, _grad_view(v_means2d, (n_cam, n, 2), dt),
                                  _grad_view(v_depths, (n_cam, n), dt), _grad_view(v_conics, (n_cam, n, 3), dt),
                                  _grad_view(v_comps, (n_cam, n), dt), v_comps is not None, v_means, v_quats,
                                  v_scales)
        return (_out(v_means, means), _out(v_quats, quats), _out(v_scales, scales), None, None, None, None, None, None,
                None, None)


def project_gaussians_qs(means: Tensor, quats: Tensor, scales: Tensor, viewmats: Tensor, Ks: Tensor, width: int,
                         height: int, *, eps2d: float = 0.3, near_plane: float = 0.01, far_plane: float = 1e10,
                         radius_clip: float = 0.0, calc_compensations: bool = False) -> dict[str, Tensor | None]:
    """:func:`project_gaussians` of the covariances of ``quats`` and ``scales`` (fused: equal to
    ``project_gaussians(means, quat_scale_to_covar(quats, scales), ...)`` up to rounding)."""
    if viewmats.requires_grad or Ks.requires_grad:
        raise ValueError("the compiled CPU rasterizer does not differentiate viewmats or Ks; render with "
                         "backend='torch' (navcrafter's PyTorch rasterizer) to optimise cameras")
    means2d, depths, conics, comps, radii = _ProjectQS.apply(means, quats, scales, viewmats, Ks, int(width),
                                                             int(height), float(eps2d), float(near_plane),
                                                             float(far_plane), float(radius_clip))
    return {"radii": radii, "means2d": means2d, "depths": depths, "conics": conics,
            "compensations": comps if calc_compensations else None}


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds, radii, depths, width, height, tile_size,
                alpha_clamp, record, ed, info):
        n_cam, n = radii.shape
        d = colors.shape[-1]
        tile_w, tile_h = -(-width // tile_size), -(-height // tile_size)
        # the compositing arithmetic is float32 for float32 inputs (the fit), float64 otherwise
        dt = np.float32 if means2d.dtype == torch.float32 else np.float64
        m2, con, col, opa = (_np_view(x, dt) for x in (means2d, conics, colors, opacities))
        use_bg = backgrounds is not None
        bg = _np_native(backgrounds, dt) if use_bg else np.zeros((n_cam, d), dt)
        cst = K.composite_constants(alpha_clamp, ED_ALPHA_MIN, dt)
        rad = np.ascontiguousarray(radii.cpu().numpy())
        cbox = _SCRATCH.get("cbox", (n_cam, n), np.int64)
        rec = _SCRATCH.get("rec", (n_cam, n, K.R_FEAT + d), dt)
        render = _SCRATCH.get("render", (n_cam, height, width, d), dt)
        t_final = _SCRATCH.get("t_final", (n_cam, height, width), dt)
        # the expected depths ("ED" modes), kept for the backward pass
        ed_val = _SCRATCH.get("ed_val", (n_cam, height, width) if ed else (0, 0, 0), dt)
        # compositing tiles (K.composite_tile_size) apart from the API's tile_size, which decides n_isects and
        # which pixels a Gaussian may touch (its boxes are clipped to its tile_size squares)
        ctile = K.composite_tile_size(width, height)
        ctw, cth = -(-width // ctile), -(-height // ctile)
        offsets = _SCRATCH.get("offsets", n_cam * ctw * cth + 1, np.int64)
        depth64 = _SCRATCH.get("depth64", (n_cam, n), np.float64)
        tiles_per_gauss = _SCRATCH.get("tiles_per_gauss", (n_cam, n), np.int64)
        with _LOCK:
            n_isects, n_ent = K.pack_gaussians(m2, con, opa, col, rad, depths.numpy(), tile_size, tile_w, tile_h,
                                               ctile, width, height, rec, cbox, depth64, tiles_per_gauss)
            gids, epos = _SCRATCH.get("gids", n_ent, np.int64), _SCRATCH.get("epos", n_ent, np.int64)
            order, roff = _SCRATCH.get("order", (n_cam, n), np.int64), _SCRATCH.get("roff", n_cam * n + 1, np.int64)
            iwork, kwork = _SCRATCH.get("bin_iwork", (4, n), np.int64), _SCRATCH.get("bin_kwork", (2, n), np.uint64)
            hist = _SCRATCH.get("bin_hist", (64 // K.RADIX_BITS + 1, 1 << K.RADIX_BITS), np.int64)
            K.bin_gaussians(cbox, depth64.view(np.uint64), ctw, cth, offsets, gids, order, roff, epos, iwork, kwork,
                            hist)
            ent = _SCRATCH.get("ent", (n_ent, rec.shape[2]), dt)
            cap = _SCRATCH.get("cap", n_cam * ctw * cth, np.int64)
            K.gather_entries(offsets, gids, ctw * cth, ctw, ctile, width, height, rec, ent, cap)
            pbase = _SCRATCH.get("pbase", len(cap) + 1, np.int64)
            pbase[0] = 0
            if record:
                np.cumsum(cap, out=pbase[1:])
            else:
                pbase[1:] = 0
            pend = _SCRATCH.get("pend", n_ent, np.int64)
            pix = _SCRATCH.get("pix", pbase[-1], np.int32)
            pes = _SCRATCH.get("pes", pbase[-1], dt)
            pts = _SCRATCH.get("pts", pbase[-1], dt)
            K.composite_forward(ent, offsets, width, height, ctile, ctw, cst, bg, use_bg, render, t_final,
                                pbase, pend, pix, pes, pts, record, ed, ed_val)
        ctx.arrays = (ent, bg, cst, offsets, gids, order, roff, epos, t_final, ed_val, pbase, pend, pix, pes, pts)
        ctx.shape = (n_cam, n, d)
        ctx.scalars = (width, height, ctile, ctw, use_bg, ed)
        ctx.likes = (means2d, conics, colors, opacities, backgrounds)
        info.update({"tile_width": tile_w, "tile_height": tile_h, "n_isects": int(n_isects),
                     "tiles_per_gauss": torch.from_numpy(tiles_per_gauss)})
        alphas = 1.0 - t_final
        return _out(render, means2d), _out(alphas[..., None], means2d)

    @staticmethod
    def backward(ctx, v_render, v_alphas):
        ent, bg, cst, offsets, gids, order, roff, epos, t_final, ed_val, pbase, pend, pix, pes, pts = ctx.arrays
        width, height, ctile, ctw, use_bg, ed = ctx.scalars
        n_cam, n, d = ctx.shape
        dt = ent.dtype
        vr = np.zeros((n_cam, height, width, d), dt) if v_render is None else _np_view(v_render, dt)
        va = np.zeros((n_cam, height, width), dt) if v_alphas is None else _np_view(v_alphas[..., 0], dt)
        slots = _SCRATCH.get("slots", (len(gids), 6 + d), dt)  # per-entry sums, in the dtype
        # the gradients in the inputs' dtype (float64 sums), handed to PyTorch as views of one array
        grads = _SCRATCH.get("grads", (n_cam, n, 6 + d), dt)
        # Gaussians without entries keep zeros (one memset, ~0.2 ms at 100k: zeroing only their rows in
        # pack_gaussians cost ~0.3 ms there, scattered 40-byte rows, raster28)
        grads.fill(0)
        with _LOCK:
            K.composite_backward(ent, offsets, width, height, ctile, ctw, cst, bg, use_bg, vr, va,
                                 pbase, pend, pix, pes, pts, slots, ed, t_final, ed_val)
            K.gather_slots(order, roff, epos, slots, grads)
        v_m2, v_con, v_opa, v_col = grads[..., 0:2], grads[..., 2:5], grads[..., 5], grads[..., 6:]
        l_m2, l_con, l_col, l_opa, l_bg = ctx.likes
        v_bg = None
        if use_bg and ctx.needs_input_grad[4]:
            if ed:  # the accumulated depth's gradient (the kernel's, from the expected depth's)
                vr = vr.copy()
                vr[..., -1] /= np.maximum(1.0 - t_final, cst[7])
            v_bg = _out(np.einsum("chw,chwd->cd", t_final.astype(np.float64), vr.astype(np.float64)), l_bg)
        return (_out(v_m2, l_m2), _out(v_con, l_con), _out(v_col, l_col), _out(v_opa, l_opa), v_bg,
                None, None, None, None, None, None, None, None, None)


def rasterize_to_pixels(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, radii: Tensor,
                        depths: Tensor, width: int, height: int, *, tile_size: int = 16,
                        backgrounds: Tensor | None = None, alpha_clamp: float = DEFAULT_ALPHA_CLAMP,
                        expected_depth: bool = False) -> tuple[Tensor, Tensor, dict]:
    """:func:`~navcrafter.models.gaussians.rasterize.rasterize_to_pixels` on the compiled kernels (the expected
    depth made in the compositing kernels)."""
    info: dict = {}
    # forward keeps the contributing pairs for the backward pass only when one can follow
    record = torch.is_grad_enabled() and any(x.requires_grad for x in (means2d, conics, colors, opacities))
    render, alphas = _Composite.apply(means2d, conics, colors, opacities, backgrounds, radii, depths.detach(),
                                      int(width), int(height), int(tile_size), float(alpha_clamp), record,
                                      bool(expected_depth), info)
    return render, alphas, info


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
    """Render N Gaussians into C cameras on the compiled CPU kernels; the contract of
    :func:`navcrafter.models.gaussians.rasterize.rasterization` (gsplat's), results equal to it."""
    del packed
    if means.device.type != "cpu":
        raise ValueError(f"the compiled CPU rasterizer needs CPU tensors, got {means.device}; use backend 'gsplat' "
                         "or 'torch' on CUDA")
    return render_gaussians(project_gaussians, rasterize_to_pixels, means, quats, scales, opacities, colors, viewmats,
                            Ks, width, height, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
                            eps2d=eps2d, sh_degree=sh_degree, tile_size=tile_size, backgrounds=backgrounds,
                            render_mode=render_mode, rasterize_mode=rasterize_mode, covars=covars,
                            alpha_clamp=alpha_clamp, features_fn=composite_features, project_qs=project_gaussians_qs)


class _L1InverseDepth(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rgb, depth, image, ref, alpha, alpha_min, d_min, info):
        arrays = tuple(t.detach().numpy() for t in (rgb, image, depth, ref, alpha))
        s, sd, n = K.l1_inverse_depth_forward(*arrays, np.float32(alpha_min), np.float32(d_min))
        ctx.arrays, ctx.consts = arrays, (np.float32(alpha_min), np.float32(d_min), n)
        info["pixels"] = n
        return torch.tensor(s / rgb.numel(), dtype=rgb.dtype), torch.tensor(sd / max(n, 1), dtype=rgb.dtype)

    @staticmethod
    def backward(ctx, g_l1, g_depth):
        rgb, image, depth, ref, alpha = ctx.arrays
        v_rgb, v_depth = np.empty(rgb.shape, np.float32), np.empty(depth.shape, np.float32)
        K.l1_inverse_depth_backward(rgb, image, depth, ref, alpha, *ctx.consts, np.float32(g_l1),
                                    np.float32(g_depth), v_rgb, v_depth)
        return torch.from_numpy(v_rgb), torch.from_numpy(v_depth), None, None, None, None, None, None


def l1_inverse_depth(rgb: Tensor, depth: Tensor, image: Tensor, ref_depth: Tensor | None, alpha: Tensor | None,
                     alpha_min: float = 0.5, d_min: float = 1e-6) -> tuple[Tensor, Tensor | None]:
    """The fit's two loss terms in one compiled pass each way (CPU float32): ``(rgb - image).abs().mean()`` and,
    over the pixels where ``ref_depth > 0`` and ``alpha > alpha_min`` (None where there are none, or no
    ``ref_depth``), ``(1 / depth.clamp(min=d_min) - 1 / ref_depth).abs().mean()``. The gradients are those of
    these torch expressions (with boolean-mask indexing), bit for bit; the values are their sums in float64
    (torch's float32 reductions differ in the last bits). Replaces ~25 small torch ops forward and backward,
    each of which wakes torch's threads (~1.4 ms per iteration of the demo's fit on 2 cores; issue 31, fit33)."""
    if ref_depth is not None and alpha is None:
        raise ValueError("l1_inverse_depth: the depth term needs the rendered alpha (its mask)")
    if ref_depth is None:
        ref_depth = alpha = torch.zeros((0, 0))
    if not fused_loss_applies(rgb, depth, image, ref_depth, alpha):
        raise ValueError("l1_inverse_depth needs float32 CPU tensors; use the torch expressions elsewhere")
    if rgb.dim() != 3 or rgb.shape[-1] != 3 or rgb.shape != image.shape or rgb.shape[:2] != depth.shape or (
            ref_depth.numel() and not depth.shape == alpha.shape == ref_depth.shape):
        raise ValueError(f"rgb / image [H, W, 3] and depth / alpha / ref_depth [H, W] must agree, got "
                         f"{tuple(rgb.shape)}, {tuple(image.shape)}, {tuple(depth.shape)}, {tuple(alpha.shape)}, "
                         f"{tuple(ref_depth.shape)}")
    info: dict = {}
    l1, term = _L1InverseDepth.apply(rgb, depth, image.detach(), ref_depth.detach(), alpha.detach(),
                                     float(alpha_min), float(d_min), info)
    return l1, (term if info["pixels"] > 0 else None)


def fused_loss_applies(*tensors: Tensor | None) -> bool:
    """Whether :func:`l1_inverse_depth` takes these tensors (float32, on the CPU; None is skipped)."""
    return all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors if t is not None)

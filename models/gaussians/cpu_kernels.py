"""Compiled CPU kernels of the 3DGS rasterizer (numba): projection, tile binning, compositing, backward passes.

Plain functions over NumPy arrays: ``float64`` arithmetic per Gaussian (covariances, projection, SH, records)
whatever the input dtype, and the compositing in the dtype of its inputs (see below); the autograd glue
and the gsplat-shaped entry point are in :mod:`~navcrafter.models.gaussians.cpu_rasterize`. The maths is the
one of :mod:`~navcrafter.models.gaussians.rasterize` (the PyTorch renderer these kernels are checked against):
EWA projection with the clamped Jacobian and ``eps2d`` dilation, gsplat's 3-sigma tile squares, tile lists in
stable depth order, front-to-back compositing with the ``1/255`` skip and the exclusive ``T <= 1e-4`` stop.

Every kernel is deterministic for any thread count: parallel loops write disjoint outputs (one Gaussian, one
tile), and the per-Gaussian sums of the backward pass are taken in a fixed order (each tile writes the
gradients of its own list entries; a pass adds each Gaussian's up in list order), so a fit gives the same
bits whether it runs on 1 or 16 threads, and resuming a run reproduces it exactly.
"""

from __future__ import annotations

import math
import os

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic, models, register_model

# The threading layer, unless the user chose one (NUMBA_THREADING_LAYER). Where OpenMP threads sleep between
# parallel regions (OMP_WAIT_POLICY=PASSIVE: the CLI, the tests and the benchmarks set it before torch loads),
# numba's OpenMP layer, falling back to its own workqueue where no OpenMP runtime loads: the calling thread works
# in every region (one worker to wake on 2 threads, not two workers and the caller) and on a 2-vCPU VM the wall
# time of a call stops jumping between levels (issue 31, raster31: SH3 + RGB+ED at 100k x 256², 40 calls per
# process, three processes: median 26.4 ms / max 29-32 ms against workqueue's 29.0-32.8 / 38.6-44.2 ms, the same
# CPU time). Elsewhere (OMP_WAIT_POLICY unset: spinning OpenMP threads) the workqueue layer: the OpenMP layer
# then pays ~8 ms per parallel call beside torch's spinning threads. Both are serialised by cpu_rasterize's lock
# (workqueue requires it). Takes effect at the first parallel call. With GNU OpenMP, a process forked after a
# parallel call cannot run these kernels in parallel (numba ends such a child: GNU OpenMP is not fork-safe);
# nothing in navcrafter forks (subprocesses exec).
if "NUMBA_THREADING_LAYER" not in os.environ:
    if os.environ.get("OMP_WAIT_POLICY", "").strip().upper() == "PASSIVE":
        # a permutation of the three (numba's rule); workqueue always loads, so tbb is never reached
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
        numba.config.THREADING_LAYER = "default"
    else:
        numba.config.THREADING_LAYER = "workqueue"

CHUNK = 512  # Gaussians per parallel chunk of the per-Gaussian kernels (scratch arrays allocated per chunk)
ALPHA_THRESHOLD = 1.0 / 255.0
TRANSMITTANCE_STOP = 1e-4
# The compositing loops index with unsigned integers (np.uintp): numba gives every access by a signed index a
# negative-index wraparound (a compare and a select), ~8 % of those loops' time (measured: forward 30.1 -> 27.8 ms,
# backward 20.0 -> 18.2 ms at 100k x 256², one thread, same process). Their constants are unsigned too: a signed
# operand would promote the index to float64.
_U1, _U2, _U3, _U4 = np.uintp(1), np.uintp(2), np.uintp(3), np.uintp(4)
_U16, _UFFFF = np.uintp(16), np.uintp(0xFFFF)

# error_model "numpy": a float division by zero gives inf / nan instead of a check and branch on every division
# (no kernel divides by a value that can be zero: denominators are clamped, or tested first)
_jit = numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
_pjit = numba.njit(cache=True, fastmath=False, nogil=True, parallel=True, error_model="numpy")
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}  # not nnan / ninf: the code compares and clamps
_fjit = numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, error_model="numpy")
# helpers called per Gaussian or per pixel row: inlined into their callers (numba's own inlining; LLVM does not
# inline across numba functions, and the calls with their array arguments cost as much as the maths)
_ijit = numba.njit(cache=True, fastmath=False, nogil=True, error_model="numpy", inline="always")
_ifjit = numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, error_model="numpy", inline="always")
_pfjit = numba.njit(cache=True, fastmath=_FASTMATH, nogil=True, parallel=True, error_model="numpy")


# --------------------------------------------------------------------------------------------------
# Covariances
# --------------------------------------------------------------------------------------------------
@_ifjit
def _rotmat(w, x, y, z, R):
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@_ifjit
def _covar(quats, scales, g, R, cov):
    """``cov`` [3, 3] = ``R diag(s)^2 R^T`` of Gaussian g's (w, x, y, z) quaternion (normalised here, as
    ``torch.nn.functional.normalize``) and scales; ``R`` [3, 3] is scratch."""
    qw, qx, qy, qz = float(quats[g, 0]), float(quats[g, 1]), float(quats[g, 2]), float(quats[g, 3])
    nrm = max(math.sqrt(qw ** 2 + qx ** 2 + qy ** 2 + qz ** 2), 1e-12)
    _rotmat(qw / nrm, qx / nrm, qy / nrm, qz / nrm, R)
    s0, s1, s2 = float(scales[g, 0]), float(scales[g, 1]), float(scales[g, 2])
    for i in range(3):
        for j in range(3):
            cov[i, j] = R[i, 0] * s0 * s0 * R[j, 0] + R[i, 1] * s1 * s1 * R[j, 1] + R[i, 2] * s2 * s2 * R[j, 2]


@_ifjit
def _covar_grad(quats, scales, g, v_cov, R, vR, v_quats, v_scales):
    """Gradients of :func:`_covar` for Gaussian g from ``v_cov`` [3, 3] into ``v_quats[g]``, ``v_scales[g]``
    (``R``, ``vR`` [3, 3] are scratch; float64 sums, written once in the outputs' dtype)."""
    qw, qx, qy, qz = float(quats[g, 0]), float(quats[g, 1]), float(quats[g, 2]), float(quats[g, 3])
    nrm = max(math.sqrt(qw ** 2 + qx ** 2 + qy ** 2 + qz ** 2), 1e-12)
    w, x, y, z = qw / nrm, qx / nrm, qy / nrm, qz / nrm
    _rotmat(w, x, y, z, R)
    sc = (float(scales[g, 0]), float(scales[g, 1]), float(scales[g, 2]))
    # Sigma = M M^T, M = R diag(s): v_M = (G + G^T) M
    vs0 = vs1 = vs2 = 0.0
    for i in range(3):
        for j in range(3):
            vm = ((v_cov[i, 0] + v_cov[0, i]) * R[0, j] + (v_cov[i, 1] + v_cov[1, i]) * R[1, j]
                  + (v_cov[i, 2] + v_cov[2, i]) * R[2, j]) * sc[j]
            vR[i, j] = vm * sc[j]
            if j == 0:
                vs0 += vm * R[i, j]
            elif j == 1:
                vs1 += vm * R[i, j]
            else:
                vs2 += vm * R[i, j]
    v_scales[g, 0], v_scales[g, 1], v_scales[g, 2] = vs0, vs1, vs2
    vw = 2 * (-z * vR[0, 1] + y * vR[0, 2] + z * vR[1, 0] - x * vR[1, 2] - y * vR[2, 0] + x * vR[2, 1])
    vx = 2 * (y * vR[0, 1] + z * vR[0, 2] + y * vR[1, 0] - 2 * x * vR[1, 1] - w * vR[1, 2] + z * vR[2, 0]
              + w * vR[2, 1] - 2 * x * vR[2, 2])
    vy = 2 * (-2 * y * vR[0, 0] + x * vR[0, 1] + w * vR[0, 2] + x * vR[1, 0] + z * vR[1, 2] - w * vR[2, 0]
              + z * vR[2, 1] - 2 * y * vR[2, 2])
    vz = 2 * (-2 * z * vR[0, 0] - w * vR[0, 1] + x * vR[0, 2] + w * vR[1, 0] - 2 * z * vR[1, 1] + y * vR[1, 2]
              + x * vR[2, 0] + y * vR[2, 1])
    dot = w * vw + x * vx + y * vy + z * vz
    v_quats[g, 0] = (vw - w * dot) / nrm
    v_quats[g, 1] = (vx - x * dot) / nrm
    v_quats[g, 2] = (vy - y * dot) / nrm
    v_quats[g, 3] = (vz - z * dot) / nrm


@_pfjit
def covar_forward(quats, scales, covars):
    """``covars`` [N, 3, 3] = ``R diag(s)^2 R^T`` of (w, x, y, z) ``quats`` [N, 4] (normalised here, as
    ``torch.nn.functional.normalize``) and ``scales`` [N, 3]."""
    n = quats.shape[0]
    for ch in numba.prange((n + CHUNK - 1) // CHUNK):
        R = np.empty((3, 3))  # scratch per chunk: a heap allocation per Gaussian cost more than its maths
        for g in range(ch * CHUNK, min((ch + 1) * CHUNK, n)):
            _covar(quats, scales, g, R, covars[g])


@_pfjit
def covar_backward(quats, scales, v_covars, v_quats, v_scales):
    """Gradients of :func:`covar_forward` into ``v_quats`` [N, 4] and ``v_scales`` [N, 3]."""
    n = quats.shape[0]
    for ch in numba.prange((n + CHUNK - 1) // CHUNK):
        R = np.empty((3, 3))
        vR = np.empty((3, 3))
        for g in range(ch * CHUNK, min((ch + 1) * CHUNK, n)):
            _covar_grad(quats, scales, g, v_covars[g], R, vR, v_quats, v_scales)


# --------------------------------------------------------------------------------------------------
# Projection (from covariances, or fused with them: from quaternions and scales)
# --------------------------------------------------------------------------------------------------
@_ifjit
def _fov_limits(Ks, width, height, c):
    """The tangents (right, left, down, up) the Jacobian clamps the mean to: 1.3x the field of view."""
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    return ((width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx,
            (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy)


@_ifjit
def _camera_limits(Ks, width, height):
    """:func:`_fov_limits` of every camera [C, 4], computed once per call (six divisions each, per Gaussian
    otherwise)."""
    lims = np.empty((Ks.shape[0], 4))
    for c in range(Ks.shape[0]):
        lims[c, 0], lims[c, 1], lims[c, 2], lims[c, 3] = _fov_limits(Ks, width, height, c)
    return lims


@_ifjit
def _camera_frame(means, cov, viewmats, Ks, lims, near, far, c, g, Sc):
    """Gaussian g (world covariance ``cov`` [3, 3]) in camera c: its camera-space mean ``x, y, z``, the depth
    the Jacobian uses ``zs`` (1 when culled by depth), ``depth_ok``, the clamped ``tx, ty`` and the Jacobian
    entries; writes the camera-space covariance ``R S R^T`` into ``Sc`` [3, 3]. Shared by the projection and
    its backward pass."""
    mx, my, mz = float(means[g, 0]), float(means[g, 1]), float(means[g, 2])
    x = viewmats[c, 0, 0] * mx + viewmats[c, 0, 1] * my + viewmats[c, 0, 2] * mz + viewmats[c, 0, 3]
    y = viewmats[c, 1, 0] * mx + viewmats[c, 1, 1] * my + viewmats[c, 1, 2] * mz + viewmats[c, 1, 3]
    z = viewmats[c, 2, 0] * mx + viewmats[c, 2, 1] * my + viewmats[c, 2, 2] * mz + viewmats[c, 2, 3]
    depth_ok = (z > near) and (z < far)
    zs = z if depth_ok else 1.0
    for i in range(3):
        r0, r1, r2 = viewmats[c, i, 0], viewmats[c, i, 1], viewmats[c, i, 2]
        rc0 = r0 * cov[0, 0] + r1 * cov[1, 0] + r2 * cov[2, 0]
        rc1 = r0 * cov[0, 1] + r1 * cov[1, 1] + r2 * cov[2, 1]
        rc2 = r0 * cov[0, 2] + r1 * cov[1, 2] + r2 * cov[2, 2]
        for j in range(3):
            Sc[i, j] = rc0 * viewmats[c, j, 0] + rc1 * viewmats[c, j, 1] + rc2 * viewmats[c, j, 2]
    fx, fy = Ks[c, 0, 0], Ks[c, 1, 1]
    lxp, lxn, lyp, lyn = lims[c, 0], lims[c, 1], lims[c, 2], lims[c, 3]
    tx = zs * min(max(x / zs, -lxn), lxp)
    ty = zs * min(max(y / zs, -lyn), lyp)
    return x, y, z, zs, depth_ok, tx, ty, fx / zs, -fx * tx / (zs * zs), fy / zs, -fy * ty / (zs * zs)


@_ifjit
def _cov2d(Sc, j00, j02, j11, j12):
    """Upper triangle (a, b, d) of ``J Sc J^T`` with ``J = [[j00, 0, j02], [0, j11, j12]]``."""
    a = j00 * (j00 * Sc[0, 0] + j02 * Sc[2, 0]) + j02 * (j00 * Sc[0, 2] + j02 * Sc[2, 2])
    b = j00 * (j11 * Sc[0, 1] + j12 * Sc[0, 2]) + j02 * (j11 * Sc[2, 1] + j12 * Sc[2, 2])
    d = j11 * (j11 * Sc[1, 1] + j12 * Sc[2, 1]) + j12 * (j11 * Sc[1, 2] + j12 * Sc[2, 2])
    return a, b, d


@_ifjit
def _project_one(means, cov, viewmats, Ks, lims, width, height, eps2d, near, far, radius_clip, c, g, Sc,
                 means2d, depths, conics, radii, comps):
    """:func:`project_forward` of Gaussian g (world covariance ``cov``) into camera c."""
    x, y, z, zs, depth_ok, tx, ty, j00, j02, j11, j12 = _camera_frame(means, cov, viewmats, Ks, lims, near, far,
                                                                      c, g, Sc)
    depths[c, g] = z
    a, b, d = _cov2d(Sc, j00, j02, j11, j12)
    u = (Ks[c, 0, 0] * x + Ks[c, 0, 1] * y + Ks[c, 0, 2] * zs) / zs
    v = (Ks[c, 1, 0] * x + Ks[c, 1, 1] * y + Ks[c, 1, 2] * zs) / zs
    means2d[c, g, 0], means2d[c, g, 1] = u, v
    det_orig = a * d - b * b
    a += eps2d
    d += eps2d
    det = a * d - b * b
    valid = depth_ok and det > 0
    det_safe = det if valid else 1.0
    conics[c, g, 0] = d / det_safe
    conics[c, g, 1] = -b / det_safe
    conics[c, g, 2] = a / det_safe
    comps[c, g] = math.sqrt(max(det_orig / det_safe, 0.0))
    bb = 0.5 * (a + d)
    v1 = bb + math.sqrt(max(bb * bb - det_safe, 0.01))
    radius = math.ceil(3.0 * math.sqrt(v1))
    inside = (u + radius > 0) and (u - radius < width) and (v + radius > 0) and (v - radius < height)
    radii[c, g] = np.int32(radius) if (valid and inside and radius > radius_clip) else 0


@_pfjit
def project_forward(means, covars, viewmats, Ks, width, height, eps2d, near, far, radius_clip,
                    means2d, depths, conics, radii, comps):
    """EWA projection of ``means`` [N, 3], ``covars`` [N, 3, 3] into ``viewmats`` [C, 4, 4] / ``Ks``
    [C, 3, 3]; writes ``means2d`` [C, N, 2], ``depths`` [C, N], ``conics`` [C, N, 3], ``radii`` [C, N]
    (int32, 0 = culled) and ``comps`` [C, N] (antialiasing compensation)."""
    n_cam, n = viewmats.shape[0], means.shape[0]
    lims = _camera_limits(Ks, width, height)
    for ch in numba.prange((n + CHUNK - 1) // CHUNK):
        Sc, cov = np.empty((3, 3)), np.empty((3, 3))
        for g in range(ch * CHUNK, min((ch + 1) * CHUNK, n)):
            for k in range(3):
                for j in range(3):
                    cov[k, j] = covars[g, k, j]
            for c in range(n_cam):
                _project_one(means, cov, viewmats, Ks, lims, width, height, eps2d, near, far, radius_clip, c, g, Sc,
                             means2d, depths, conics, radii, comps)


@_ifjit
def _conic_grad(q00, q01, q11, vc0, vc1, vc2):
    """The gradient (m00, m01, m11) of the symmetric 2D covariance M = [[a, b], [b, d]] from its conic's
    (Q = M^-1 = [[q00, q01], [q01, q11]]) gradient (vc0, vc1, vc2) as the conic's three stored entries (the
    off-diagonal one counted once): dL/dM = -Q G Q with G = [[vc0, vc1 / 2], [vc1 / 2, vc2]]."""
    g00, g01, g11 = vc0, 0.5 * vc1, vc2
    t00 = q00 * g00 + q01 * g01
    t01 = q00 * g01 + q01 * g11
    t10 = q01 * g00 + q11 * g01
    t11 = q01 * g01 + q11 * g11
    return -(t00 * q00 + t01 * q01), -(t00 * q01 + t01 * q11), -(t10 * q01 + t11 * q11)


@_ifjit
def _project_grad_one(means, cov, viewmats, Ks, lims, eps2d, near, far, v_means2d, v_depths, v_conics,
                      v_comps, use_comps, c, g, Sc, v_mean, v_cov):
    """Gradients of :func:`_project_one`'s outputs for (c, g): adds into ``v_mean`` [3] and ``v_cov`` [3, 3]
    (the world covariance); ``Sc`` [3, 3] is scratch. Nothing to add when every
    output gradient of (c, g) is zero (a Gaussian culled in this camera, the common case): skipped."""
    if (v_means2d[c, g, 0] == 0.0 and v_means2d[c, g, 1] == 0.0 and v_depths[c, g] == 0.0
            and v_conics[c, g, 0] == 0.0 and v_conics[c, g, 1] == 0.0 and v_conics[c, g, 2] == 0.0
            and (not use_comps or v_comps[c, g] == 0.0)):
        return
    x, y, z, zs, depth_ok, tx, ty, j00, j02, j11, j12 = _camera_frame(means, cov, viewmats, Ks, lims, near, far,
                                                                      c, g, Sc)
    fx, fy = Ks[c, 0, 0], Ks[c, 1, 1]
    lxp, lxn, lyp, lyn = lims[c, 0], lims[c, 1], lims[c, 2], lims[c, 3]
    rx, ry = x / zs, y / zs
    x_clamped = rx < -lxn or rx > lxp
    y_clamped = ry < -lyn or ry > lyp
    a0, b0, d0 = _cov2d(Sc, j00, j02, j11, j12)
    a, d = a0 + eps2d, d0 + eps2d
    det = a * d - b0 * b0
    valid = depth_ok and det > 0
    if not valid:
        # culled: conics are constants (det_safe = 1 branch) and never rasterized; only depth flows
        v_z = v_depths[c, g]
        for k in range(3):
            v_mean[k] += viewmats[c, 2, k] * v_z
        return
    # conic = inverse(M), M = [[a, b], [b, d]]
    q00, q01, q11 = d / det, -b0 / det, a / det
    m00, m01, m11 = _conic_grad(q00, q01, q11, v_conics[c, g, 0], v_conics[c, g, 1], v_conics[c, g, 2])
    if use_comps:
        det_orig = a0 * d0 - b0 * b0
        ratio = det_orig / det
        if ratio > 0:
            comp = math.sqrt(ratio)
            f = 0.5 / comp * v_comps[c, g] / (det * det)
            m00 += f * (d0 * det - det_orig * d)
            m11 += f * (a0 * det - det_orig * a)
            m01 += 0.5 * f * (-2.0 * b0 * det + 2.0 * b0 * det_orig)
    # cov2d = J Sc J^T: dL/dSc = J^T Gm J, dL/dJ = 2 Gm J Sc (Gm, Sc symmetric); J = [[j00, 0, j02],
    # [0, j11, j12]], in scalars (GJ = Gm J, v_Sc = J^T GJ; only v_J's four structural non-zeros are needed)
    gj00, gj01, gj02 = m00 * j00, m01 * j11, m00 * j02 + m01 * j12
    gj10, gj11, gj12 = m01 * j00, m11 * j11, m01 * j02 + m11 * j12
    s00, s01, s02 = j00 * gj00, j00 * gj01, j00 * gj02
    s10, s11, s12 = j11 * gj10, j11 * gj11, j11 * gj12
    s20, s21, s22 = j02 * gj00 + j12 * gj10, j02 * gj01 + j12 * gj11, j02 * gj02 + j12 * gj12
    vj00 = 2.0 * (gj00 * Sc[0, 0] + gj01 * Sc[1, 0] + gj02 * Sc[2, 0])
    vj02 = 2.0 * (gj00 * Sc[0, 2] + gj01 * Sc[1, 2] + gj02 * Sc[2, 2])
    vj11 = 2.0 * (gj10 * Sc[0, 1] + gj11 * Sc[1, 1] + gj12 * Sc[2, 1])
    vj12 = 2.0 * (gj10 * Sc[0, 2] + gj11 * Sc[1, 2] + gj12 * Sc[2, 2])
    # J's dependence on zs, tx, ty
    zs2, zs3 = zs * zs, zs * zs * zs
    v_zs = -fx / zs2 * vj00 - fy / zs2 * vj11
    v_tx = -fx / zs2 * vj02
    v_ty = -fy / zs2 * vj12
    v_zs += 2.0 * fx * tx / zs3 * vj02 + 2.0 * fy * ty / zs3 * vj12
    v_x, v_y = 0.0, 0.0
    if x_clamped:
        v_zs += min(max(rx, -lxn), lxp) * v_tx
    else:
        v_x += v_tx
    if y_clamped:
        v_zs += min(max(ry, -lyn), lyp) * v_ty
    else:
        v_y += v_ty
    # means2d = (K[:2] @ (x, y, zs)) / zs
    vu, vv = v_means2d[c, g, 0], v_means2d[c, g, 1]
    v_x += (Ks[c, 0, 0] * vu + Ks[c, 1, 0] * vv) / zs
    v_y += (Ks[c, 0, 1] * vu + Ks[c, 1, 1] * vv) / zs
    v_zs += -(vu * (Ks[c, 0, 0] * x + Ks[c, 0, 1] * y) + vv * (Ks[c, 1, 0] * x + Ks[c, 1, 1] * y)) / zs2
    v_z = v_depths[c, g] + v_zs  # depth_ok holds here
    for k in range(3):
        v_mean[k] += viewmats[c, 0, k] * v_x + viewmats[c, 1, k] * v_y + viewmats[c, 2, k] * v_z
    # Sc = R S R^T: dL/dS = R^T v_Sc R (as two products: column k of v_Sc R, then R^T times it)
    for k in range(3):
        r0k, r1k, r2k = viewmats[c, 0, k], viewmats[c, 1, k], viewmats[c, 2, k]
        rv0 = s00 * r0k + s01 * r1k + s02 * r2k
        rv1 = s10 * r0k + s11 * r1k + s12 * r2k
        rv2 = s20 * r0k + s21 * r1k + s22 * r2k
        for i in range(3):
            v_cov[i, k] += viewmats[c, 0, i] * rv0 + viewmats[c, 1, i] * rv1 + viewmats[c, 2, i] * rv2


@_pfjit
def project_backward(means, covars, viewmats, Ks, width, height, eps2d, near, far,
                     v_means2d, v_depths, v_conics, v_comps, use_comps, v_means, v_covars):
    """Gradients of :func:`project_forward`'s outputs into ``v_means`` [N, 3] and ``v_covars`` [N, 3, 3]
    (cameras summed in order per Gaussian)."""
    n_cam, n = viewmats.shape[0], means.shape[0]
    lims = _camera_limits(Ks, width, height)
    for ch in numba.prange((n + CHUNK - 1) // CHUNK):
        Sc, cov, v_cov, v_mean = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty(3)
        for g in range(ch * CHUNK, min((ch + 1) * CHUNK, n)):
            for k in range(3):
                v_mean[k] = 0.0
                for j in range(3):
                    v_cov[k, j] = 0.0
                    cov[k, j] = covars[g, k, j]
            for c in range(n_cam):
                _project_grad_one(means, cov, viewmats, Ks, lims, eps2d, near, far, v_means2d,
                                  v_depths, v_conics, v_comps, use_comps, c, g, Sc, v_mean, v_cov)
            for k in range(3):
                v_means[g, k] = v_mean[k]
                for j in range(3):
                    v_covars[g, k, j] = v_cov[k, j]


# --------------------------------------------------------------------------------------------------
# Projection from quaternions and scales, in scalars, vectorised over blocks of Gaussians (the default path)
# --------------------------------------------------------------------------------------------------
# The same maths as _covar + _project_one (and their gradients), written over scalars instead of [3, 3] scratch
# arrays, with the 2D covariance as P C P^T (P = J W, 2 x 3) instead of J (W C W^T) J^T, only the symmetric
# covariances' six entries and one reciprocal of the depth instead of a division per use: float64 arithmetic as
# before, results equal up to float64 rounding (the float32 outputs to their last bit, almost always).
# The arithmetic runs over blocks of QS_BLOCK Gaussians held as rows (structure of arrays, float64) in a few
# small work arrays, by loops that touch nothing else and branch nowhere (culling and clamps are selects): LLVM
# vectorises those (numba's array arguments may alias, and with the kernels' seven to eleven arrays, strided
# rows and branches it kept the per-Gaussian loop scalar: 4.95 -> 0.79 ms for the forward's maths at 100k, one
# thread). Loading the rows from the inputs and writing the outputs back are plain copies around them. The same
# operations in the same order per Gaussian as the scalar code, but fast-math lets LLVM contract and reassociate the
# vector loop's sums differently: means2d and depths are bit-identical, float32 conics and compensations differ in
# the last bit for some Gaussians (renders and gradients within 6.9e-7 of each tensor's largest value; README
# round raster25).
QS_BLOCK = 128  # Gaussians per block (the work rows stay in L1/L2)
# rows of a block's inputs X: mean (0-2), quaternion w, x, y, z (3-6), scales (7-9)
# camera constants (_qs_cameras, one row per camera): viewmat rows 0-2 (0-11), fx, K01, cx, K10, fy, cy (12-17),
# the Jacobian's clamp limits (18-21: right, left, down, up tangents)
_N_CAM = 22


@_ijit
def _o(k):
    """The offset of row ``k`` in a block's work array (rows of QS_BLOCK, one flat array: the offsets between
    rows are constants, so LLVM can tell the rows apart; with a 2D array's runtime stride it could not, and kept
    the loops scalar)."""
    return np.uintp(k * QS_BLOCK)


@_ijit
def _qs_cameras(viewmats, Ks, width, height):
    """Each camera's constants in one row [C, 22] (see above): read into scalars once per block loop."""
    lims = _camera_limits(Ks, width, height)
    cams = np.empty((viewmats.shape[0], _N_CAM))
    for c in range(viewmats.shape[0]):
        for i in range(3):
            for j in range(4):
                cams[c, 4 * i + j] = viewmats[c, i, j]
        cams[c, 12], cams[c, 13], cams[c, 14] = Ks[c, 0, 0], Ks[c, 0, 1], Ks[c, 0, 2]
        cams[c, 15], cams[c, 16], cams[c, 17] = Ks[c, 1, 0], Ks[c, 1, 1], Ks[c, 1, 2]
        for i in range(4):
            cams[c, 18 + i] = lims[c, i]
    return cams


@_ijit
def _qs_load(means, quats, scales, g0, m, X):
    """Gaussians ``g0 .. g0 + m`` of the inputs into the block's rows ``X`` [10 rows] (float64)."""
    for i in range(m):
        iu = np.uintp(i)
        g = g0 + i
        X[_o(0) + iu], X[_o(1) + iu], X[_o(2) + iu] = float(means[g, 0]), float(means[g, 1]), float(means[g, 2])
        X[_o(3) + iu], X[_o(4) + iu] = float(quats[g, 0]), float(quats[g, 1])
        X[_o(5) + iu], X[_o(6) + iu] = float(quats[g, 2]), float(quats[g, 3])
        X[_o(7) + iu], X[_o(8) + iu], X[_o(9) + iu] = float(scales[g, 0]), float(scales[g, 1]), float(scales[g, 2])


@_ifjit
def _qs_rot(X, iu):
    """Block column i's normalised quaternion (w, x, y, z), its norm and its rotation matrix's rows."""
    qw, qx, qy, qz = X[_o(3) + iu], X[_o(4) + iu], X[_o(5) + iu], X[_o(6) + iu]
    nrm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
    w, x, y, z = qw / nrm, qx / nrm, qy / nrm, qz / nrm
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return w, x, y, z, nrm, r00, r01, r02, r10, r11, r12, r20, r21, r22


@_fjit
def _qs_cov_block(X, Cv, m):
    """``Cv`` [6 rows] = the upper triangle (c00, c01, c02, c11, c12, c22) of ``M M^T``, ``M = R
    diag(s)``, of the block's columns (vectorised)."""
    for i in range(m):
        iu = np.uintp(i)
        _w, _x, _y, _z, _nrm, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _qs_rot(X, iu)
        s0, s1, s2 = X[_o(7) + iu], X[_o(8) + iu], X[_o(9) + iu]
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
        Cv[_o(0) + iu] = m00 * m00 + m01 * m01 + m02 * m02
        Cv[_o(1) + iu] = m00 * m10 + m01 * m11 + m02 * m12
        Cv[_o(2) + iu] = m00 * m20 + m01 * m21 + m02 * m22
        Cv[_o(3) + iu] = m10 * m10 + m11 * m11 + m12 * m12
        Cv[_o(4) + iu] = m10 * m20 + m11 * m21 + m12 * m22
        Cv[_o(5) + iu] = m20 * m20 + m21 * m21 + m22 * m22


@_ifjit
def _qs_cov_of(W, r, iu):
    """Block column ``iu``'s covariance (or its gradient) from the six rows from ``r`` on of ``W``: c00, c01,
    c02, c11, c12, c22."""
    return (W[_o(r) + iu], W[_o(r + 1) + iu], W[_o(r + 2) + iu], W[_o(r + 3) + iu], W[_o(r + 4) + iu],
            W[_o(r + 5) + iu])


@_ifjit
def _qs_frame(X, iu, cam, near, far):
    """Block column i's mean in the camera of ``cam`` (``x, y, z``), the depth the Jacobian uses ``zs`` (1 when
    culled by depth), ``1 / zs``, ``depth_ok``, the clamped ``tx, ty``, the Jacobian's non-zeros j00, j02, j11,
    j12 and ``P = J W`` (2 x 3, W the camera's rotation) as p00, p01, p02, p10, p11, p12. ``cam`` is the
    camera's constants as a tuple (loaded once, outside the block loop)."""
    (w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23, fx, _k01, _cx, _k10, fy, _cy,
     l0, l1, l2, l3) = cam
    mx, my, mz = X[_o(0) + iu], X[_o(1) + iu], X[_o(2) + iu]
    x = w00 * mx + w01 * my + w02 * mz + w03
    y = w10 * mx + w11 * my + w12 * mz + w13
    z = w20 * mx + w21 * my + w22 * mz + w23
    depth_ok = (z > near) & (z < far)
    zs = z if depth_ok else 1.0
    izs = 1.0 / zs
    tx = zs * min(max(x * izs, -l1), l0)
    ty = zs * min(max(y * izs, -l3), l2)
    j00, j02, j11, j12 = fx * izs, -fx * tx * izs * izs, fy * izs, -fy * ty * izs * izs
    return (x, y, z, zs, izs, depth_ok, tx, ty, j00, j02, j11, j12,
            j00 * w00 + j02 * w20, j00 * w01 + j02 * w21, j00 * w02 + j02 * w22,
            j11 * w10 + j12 * w20, j11 * w11 + j12 * w21, j11 * w12 + j12 * w22)


@_ifjit
def _cam_tuple(cams, c):
    """Row c of :func:`_qs_cameras` as a tuple of scalars."""
    r = cams[c]
    return (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8], r[9], r[10], r[11], r[12], r[13], r[14], r[15],
            r[16], r[17], r[18], r[19], r[20], r[21])


@_ifjit
def _qs_cov2d(X, Cv, iu, cam, near, far):
    """Block column ``iu`` in the camera ``cam``: its frame (``_qs_frame``'s 18 values), its covariance's six
    entries, ``C p0`` and ``C p1`` (p0, p1 the rows of ``P = J W``) and the 2D covariance ``P C P^T`` as ``(a, b,
    d)`` before the blur: the projection's forward and its backward (which recomputes it) share this."""
    fr = _qs_frame(X, iu, cam, near, far)
    p00, p01, p02, p10, p11, p12 = fr[12], fr[13], fr[14], fr[15], fr[16], fr[17]
    c00, c01, c02, c11, c12, c22 = _qs_cov_of(Cv, 0, iu)
    e0 = c00 * p00 + c01 * p01 + c02 * p02  # C p0
    e1 = c01 * p00 + c11 * p01 + c12 * p02
    e2 = c02 * p00 + c12 * p01 + c22 * p02
    f0 = c00 * p10 + c01 * p11 + c02 * p12  # C p1
    f1 = c01 * p10 + c11 * p11 + c12 * p12
    f2 = c02 * p10 + c12 * p11 + c22 * p12
    return (fr, (c00, c01, c02, c11, c12, c22), (e0, e1, e2), (f0, f1, f2),
            (p00 * e0 + p01 * e1 + p02 * e2, p10 * e0 + p11 * e1 + p12 * e2, p10 * f0 + p11 * f1 + p12 * f2))


@_fjit
def _qs_project_block(X, Cv, cams, c, width, height, eps2d, near, far, radius_clip, Y, m):
    """The projection of the block's columns into camera c (vectorised): ``Y`` [8 rows] = u, v, depth,
    conic (3), compensation, radius (0 when culled)."""
    cam = _cam_tuple(cams, c)
    k00, k01, k02, k10, k11, k12 = cam[12], cam[13], cam[14], cam[15], cam[16], cam[17]
    for i in range(m):
        iu = np.uintp(i)
        fr, _c, _e, _f, (a, b, d) = _qs_cov2d(X, Cv, iu, cam, near, far)
        x, y, z, zs, izs, depth_ok = fr[0], fr[1], fr[2], fr[3], fr[4], fr[5]
        u = (k00 * x + k01 * y + k02 * zs) * izs
        v = (k10 * x + k11 * y + k12 * zs) * izs
        det_orig = a * d - b * b
        a += eps2d
        d += eps2d
        det = a * d - b * b
        valid = depth_ok & (det > 0)
        det_safe = det if valid else 1.0
        idet = 1.0 / det_safe
        bb = 0.5 * (a + d)
        v1 = bb + math.sqrt(max(bb * bb - det_safe, 0.01))
        radius = math.ceil(3.0 * math.sqrt(v1))
        inside = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        Y[_o(0) + iu], Y[_o(1) + iu], Y[_o(2) + iu] = u, v, z
        Y[_o(3) + iu], Y[_o(4) + iu], Y[_o(5) + iu] = d * idet, -b * idet, a * idet
        Y[_o(6) + iu] = math.sqrt(max(det_orig * idet, 0.0))
        Y[_o(7) + iu] = radius if (valid & inside & (radius > radius_clip)) else 0.0


@_pfjit
def project_qs_forward(means, quats, scales, viewmats, Ks, width, height, eps2d, near, far, radius_clip,
                       means2d, depths, conics, radii, comps):
    """:func:`project_forward` with each covariance made from ``quats`` [N, 4] and ``scales`` [N, 3] on the
    fly (:func:`covar_forward`'s), never stored; in scalars over vectorised blocks (see above)."""
    n_cam, n = viewmats.shape[0], means.shape[0]
    cams = _qs_cameras(viewmats, Ks, width, height)
    for ch in numba.prange((n + QS_BLOCK - 1) // QS_BLOCK):
        g0 = ch * QS_BLOCK
        m = min(QS_BLOCK, n - g0)
        X, Cv, Y = np.empty(10 * QS_BLOCK), np.empty(6 * QS_BLOCK), np.empty(8 * QS_BLOCK)
        _qs_load(means, quats, scales, g0, m, X)
        _qs_cov_block(X, Cv, m)
        for c in range(n_cam):
            _qs_project_block(X, Cv, cams, c, width, height, eps2d, near, far, radius_clip, Y, m)
            for i in range(m):
                iu = np.uintp(i)
                g = g0 + i
                means2d[c, g, 0], means2d[c, g, 1], depths[c, g] = Y[_o(0) + iu], Y[_o(1) + iu], Y[_o(2) + iu]
                conics[c, g, 0], conics[c, g, 1], conics[c, g, 2] = Y[_o(3) + iu], Y[_o(4) + iu], Y[_o(5) + iu]
                comps[c, g] = Y[_o(6) + iu]
                radii[c, g] = np.int32(Y[_o(7) + iu])


@_fjit
def _qs_project_grad_block(X, Cv, cams, c, eps2d, near, far, Gc, D, m):
    """Camera c's gradients of the block's columns (vectorised): from ``Gc`` [7 rows], the output
    gradients (u, v, depth, conic (3), compensation: 0 when not used), into ``D`` [9 rows], the mean's (3)
    and the covariance's (c00, c01, c02, c11, c12, c22) gradients (written, not added: a read-modify-write of
    rows of one array kept LLVM from vectorising the loop). A column culled in this camera gets only its
    depth's gradient; one whose gradients are all zero gets zeros (added to sums that start at +0 and never
    become -0: as adding nothing)."""
    cam = _cam_tuple(cams, c)
    w00, w01, w02, w10, w11, w12, w20, w21, w22 = (cam[0], cam[1], cam[2], cam[4], cam[5], cam[6], cam[8], cam[9],
                                                   cam[10])
    k00, k01, k10, k11 = cam[12], cam[13], cam[15], cam[16]
    fx, fy, l0, l1, l2, l3 = cam[12], cam[16], cam[18], cam[19], cam[20], cam[21]
    for i in range(m):
        iu = np.uintp(i)
        vu, vv, vz_d, vc0 = Gc[_o(0) + iu], Gc[_o(1) + iu], Gc[_o(2) + iu], Gc[_o(3) + iu]
        vc1, vc2, vcp = Gc[_o(4) + iu], Gc[_o(5) + iu], Gc[_o(6) + iu]
        fr, (c00, c01, c02, c11, c12, c22), (e0, e1, e2), (f0, f1, f2), (a0, b0, d0) = _qs_cov2d(
            X, Cv, iu, cam, near, far)
        (x, y, _z, _zs, izs, depth_ok, tx, ty, j00, j02, j11, j12, p00, p01, p02, p10, p11, p12) = fr
        a, d = a0 + eps2d, d0 + eps2d
        det = a * d - b0 * b0
        valid = depth_ok & (det > 0)  # else culled: conics are constants, never rasterized; only depth flows
        idet = 1.0 / det
        # conic = inverse(M), M = [[a, b], [b, d]]
        q00, q01, q11 = d * idet, -b0 * idet, a * idet
        m00, m01, m11 = _conic_grad(q00, q01, q11, vc0, vc1, vc2)
        # the compensation's term, also where its gradient is zero (no branch: adds zeros, the sums' values unchanged)
        det_orig = a0 * d0 - b0 * b0
        ratio = det_orig * idet
        fc = 0.5 / math.sqrt(ratio) * vcp * idet * idet
        pos = ratio > 0
        m00 = m00 + fc * (d0 * det - det_orig * d) if pos else m00
        m11 = m11 + fc * (a0 * det - det_orig * a) if pos else m11
        m01 = m01 + 0.5 * fc * (-2.0 * b0 * det + 2.0 * b0 * det_orig) if pos else m01
        # cov2d = P C P^T: dL/dC = P^T Gm P, dL/dP = 2 Gm P C, dL/dJ = dL/dP W^T (its four non-zeros)
        gp00, gp01, gp02 = m00 * p00 + m01 * p10, m00 * p01 + m01 * p11, m00 * p02 + m01 * p12
        gp10, gp11, gp12 = m01 * p00 + m11 * p10, m01 * p01 + m11 * p11, m01 * p02 + m11 * p12
        D[_o(3) + iu] = (p00 * gp00 + p10 * gp10) if valid else 0.0
        D[_o(4) + iu] = (p00 * gp01 + p10 * gp11) if valid else 0.0
        D[_o(5) + iu] = (p00 * gp02 + p10 * gp12) if valid else 0.0
        D[_o(6) + iu] = (p01 * gp01 + p11 * gp11) if valid else 0.0
        D[_o(7) + iu] = (p01 * gp02 + p11 * gp12) if valid else 0.0
        D[_o(8) + iu] = (p02 * gp02 + p12 * gp12) if valid else 0.0
        # 2 Gm P C = 2 (Gm P) C, rows
        vp00 = 2.0 * (gp00 * c00 + gp01 * c01 + gp02 * c02)
        vp01 = 2.0 * (gp00 * c01 + gp01 * c11 + gp02 * c12)
        vp02 = 2.0 * (gp00 * c02 + gp01 * c12 + gp02 * c22)
        vp10 = 2.0 * (gp10 * c00 + gp11 * c01 + gp12 * c02)
        vp11 = 2.0 * (gp10 * c01 + gp11 * c11 + gp12 * c12)
        vp12 = 2.0 * (gp10 * c02 + gp11 * c12 + gp12 * c22)
        vj00 = vp00 * w00 + vp01 * w01 + vp02 * w02
        vj02 = vp00 * w20 + vp01 * w21 + vp02 * w22
        vj11 = vp10 * w10 + vp11 * w11 + vp12 * w12
        vj12 = vp10 * w20 + vp11 * w21 + vp12 * w22
        # J's dependence on zs, tx, ty
        izs2 = izs * izs
        izs3 = izs2 * izs
        v_zs = -fx * izs2 * vj00 - fy * izs2 * vj11
        v_tx = -fx * izs2 * vj02
        v_ty = -fy * izs2 * vj12
        v_zs += 2.0 * fx * tx * izs3 * vj02 + 2.0 * fy * ty * izs3 * vj12
        rx, ry = x * izs, y * izs
        x_clamped = (rx < -l1) | (rx > l0)
        y_clamped = (ry < -l3) | (ry > l2)
        v_zs = v_zs + min(max(rx, -l1), l0) * v_tx if x_clamped else v_zs
        v_x = 0.0 if x_clamped else 0.0 + v_tx
        v_zs = v_zs + min(max(ry, -l3), l2) * v_ty if y_clamped else v_zs
        v_y = 0.0 if y_clamped else 0.0 + v_ty
        # means2d = (K[:2] @ (x, y, zs)) / zs
        v_x += (k00 * vu + k10 * vv) * izs
        v_y += (k01 * vu + k11 * vv) * izs
        v_zs -= (vu * (k00 * x + k01 * y) + vv * (k10 * x + k11 * y)) * izs2
        v_z = vz_d + v_zs  # depth_ok holds where valid
        D[_o(0) + iu] = (w00 * v_x + w10 * v_y + w20 * v_z) if valid else w20 * vz_d
        D[_o(1) + iu] = (w01 * v_x + w11 * v_y + w21 * v_z) if valid else w21 * vz_d
        D[_o(2) + iu] = (w02 * v_x + w12 * v_y + w22 * v_z) if valid else w22 * vz_d


@_fjit
def _qs_cov_grad_block(X, A, Z, m):
    """``Z`` [7 rows] = the quaternion's (4) and the scales' (3) gradients of the block's columns from the
    covariance's (``A`` rows 3-8), vectorised: ``C = M M^T``, ``M = R diag(s)``: dL/dM = 2 G M (G symmetric);
    dL/dR = dL/dM diag(s), dL/ds_j = sum_i dL/dM_ij R_ij; then through the rotation and the normalisation."""
    for i in range(m):
        iu = np.uintp(i)
        w, x, y, z, nrm, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _qs_rot(X, iu)
        s0, s1, s2 = X[_o(7) + iu], X[_o(8) + iu], X[_o(9) + iu]
        g00, g01, g02, g11, g12, g22 = _qs_cov_of(A, 3, iu)
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
        u00 = 2.0 * (g00 * m00 + g01 * m10 + g02 * m20)
        u01 = 2.0 * (g00 * m01 + g01 * m11 + g02 * m21)
        u02 = 2.0 * (g00 * m02 + g01 * m12 + g02 * m22)
        u10 = 2.0 * (g01 * m00 + g11 * m10 + g12 * m20)
        u11 = 2.0 * (g01 * m01 + g11 * m11 + g12 * m21)
        u12 = 2.0 * (g01 * m02 + g11 * m12 + g12 * m22)
        u20 = 2.0 * (g02 * m00 + g12 * m10 + g22 * m20)
        u21 = 2.0 * (g02 * m01 + g12 * m11 + g22 * m21)
        u22 = 2.0 * (g02 * m02 + g12 * m12 + g22 * m22)
        Z[_o(4) + iu] = u00 * r00 + u10 * r10 + u20 * r20
        Z[_o(5) + iu] = u01 * r01 + u11 * r11 + u21 * r21
        Z[_o(6) + iu] = u02 * r02 + u12 * r12 + u22 * r22
        vr00, vr01, vr02 = u00 * s0, u01 * s1, u02 * s2
        vr10, vr11, vr12 = u10 * s0, u11 * s1, u12 * s2
        vr20, vr21, vr22 = u20 * s0, u21 * s1, u22 * s2
        vw = 2 * (-z * vr01 + y * vr02 + z * vr10 - x * vr12 - y * vr20 + x * vr21)
        vx = 2 * (y * vr01 + z * vr02 + y * vr10 - 2 * x * vr11 - w * vr12 + z * vr20 + w * vr21 - 2 * x * vr22)
        vy = 2 * (-2 * y * vr00 + x * vr01 + w * vr02 + x * vr10 + z * vr12 - w * vr20 + z * vr21 - 2 * y * vr22)
        vz = 2 * (-2 * z * vr00 - w * vr01 + x * vr02 + w * vr10 - 2 * z * vr11 + y * vr12 + x * vr20 + y * vr21)
        dot = w * vw + x * vx + y * vy + z * vz
        Z[_o(0) + iu] = (vw - w * dot) / nrm
        Z[_o(1) + iu] = (vx - x * dot) / nrm
        Z[_o(2) + iu] = (vy - y * dot) / nrm
        Z[_o(3) + iu] = (vz - z * dot) / nrm


@_pfjit
def project_qs_backward(means, quats, scales, viewmats, Ks, width, height, eps2d, near, far,
                        v_means2d, v_depths, v_conics, v_comps, use_comps, v_means, v_quats, v_scales):
    """Gradients of :func:`project_qs_forward`'s outputs into ``v_means`` [N, 3], ``v_quats`` [N, 4] and
    ``v_scales`` [N, 3] (cameras summed in order per Gaussian, in float64, then through the covariance), over
    vectorised blocks (see above); the output gradients are read with any strides."""
    n_cam, n = viewmats.shape[0], means.shape[0]
    cams = _qs_cameras(viewmats, Ks, width, height)
    for ch in numba.prange((n + QS_BLOCK - 1) // QS_BLOCK):
        g0 = ch * QS_BLOCK
        m = min(QS_BLOCK, n - g0)
        X, Cv, Gc = np.empty(10 * QS_BLOCK), np.empty(6 * QS_BLOCK), np.empty(7 * QS_BLOCK)
        A, D, Z = np.zeros(9 * QS_BLOCK), np.empty(9 * QS_BLOCK), np.empty(7 * QS_BLOCK)
        _qs_load(means, quats, scales, g0, m, X)
        _qs_cov_block(X, Cv, m)
        for c in range(n_cam):
            for i in range(m):
                iu = np.uintp(i)
                g = g0 + i
                Gc[_o(0) + iu], Gc[_o(1) + iu] = v_means2d[c, g, 0], v_means2d[c, g, 1]
                Gc[_o(2) + iu] = v_depths[c, g]
                Gc[_o(3) + iu], Gc[_o(4) + iu] = v_conics[c, g, 0], v_conics[c, g, 1]
                Gc[_o(5) + iu] = v_conics[c, g, 2]
                Gc[_o(6) + iu] = v_comps[c, g] if use_comps else 0.0
            _qs_project_grad_block(X, Cv, cams, c, eps2d, near, far, Gc, D, m)
            for k in range(9):
                for i in range(m):
                    A[_o(k) + np.uintp(i)] += D[_o(k) + np.uintp(i)]
        _qs_cov_grad_block(X, A, Z, m)
        for i in range(m):
            iu = np.uintp(i)
            g = g0 + i
            v_means[g, 0], v_means[g, 1], v_means[g, 2] = A[_o(0) + iu], A[_o(1) + iu], A[_o(2) + iu]
            v_quats[g, 0], v_quats[g, 1] = Z[_o(0) + iu], Z[_o(1) + iu]
            v_quats[g, 2], v_quats[g, 3] = Z[_o(2) + iu], Z[_o(3) + iu]
            v_scales[g, 0], v_scales[g, 1], v_scales[g, 2] = Z[_o(4) + iu], Z[_o(5) + iu], Z[_o(6) + iu]


# --------------------------------------------------------------------------------------------------
# Tile binning
# --------------------------------------------------------------------------------------------------
@_ijit
def _depth_key(bits):
    """The unsigned integer key of a float64's IEEE ``bits`` (uint64) whose order is the order of the floats:
    the sign bit set for positives, every bit flipped for negatives."""
    if bits >> np.uint64(63):
        return ~bits
    return bits | np.uint64(1 << 63)


RADIX_BITS = 11  # the widest digit (2048 bins, L1-resident)


@_ijit
def _radix_digits(diff):
    """The digits of a radix sort of keys whose differing bits are those set in ``diff`` (the OR of each key XOR
    the first): ``(lo, width, passes)``, the fewest passes of at most ``RADIX_BITS`` bits over the bits from the
    lowest to the highest set one, each ``width`` bits wide (balanced: narrower digits have fewer bins to scatter
    into). The bits outside are the same in every key, so sorting these alone gives the full keys' order.
    ``passes`` is 0 when all keys are equal."""
    if diff == 0:
        return 0, 1, 0
    lo = 0
    while (diff >> np.uint64(lo)) & np.uint64(1) == 0:
        lo += 1
    hi = 63
    while (diff >> np.uint64(hi)) & np.uint64(1) == 0:
        hi -= 1
    n_bits = hi - lo + 1
    passes = (n_bits + RADIX_BITS - 1) // RADIX_BITS
    return lo, (n_bits + passes - 1) // passes, passes


@_jit
def bin_gaussians(cbox, depth_bits, tile_w, tile_h, offsets, gids, order_out, roff, epos, iwork, kwork, hist):
    """Per tile (``camera * tiles + row * tile_w + col``) the Gaussians whose tile range ``cbox`` [C, N]
    (:func:`pack_gaussians`' packed x0 | x1 << 16 | y0 << 32 | y1 << 48 of the compositing tiles, 0 = none)
    covers it, in depth order
    (stable: ties keep index order): ``offsets`` [C * tiles + 1], ``gids`` [n_isects]. One stable LSD radix
    sort of each camera's visible Gaussians by their depths (``depth_bits`` [C, N]: the float64 depths' bits,
    keyed by :func:`_depth_key`; only the bits in which the keys differ, in :func:`_radix_digits`' digits, all
    digits' histograms counted in the pass that finds the visible Gaussians; each Gaussian's tile square packed
    into one integer travels with it, so the pass that appends them to their tiles in that order reads
    sequentially), instead of a sort per tile. Also, per camera, the visible Gaussians in depth order
    ``order_out`` [C, N] (-1 past the last) and, per rank ``idx = camera * N + rank``, the list positions of its
    entries in row-major tile order ``epos[roff[idx]:roff[idx + 1]]`` (for :func:`gather_slots`). Work arrays
    from the caller (reused between calls: no fresh pages): ``iwork`` [4, N] int64, ``kwork`` [2, N] uint64,
    ``hist`` [64 // RADIX_BITS + 1, 2 ** RADIX_BITS] int64."""
    n_cam, n = cbox.shape[0], cbox.shape[1]
    n_tiles = tile_w * tile_h
    counts = np.empty(n_tiles, dtype=np.int64)
    fill = np.empty(n_tiles, dtype=np.int64)
    offsets[0] = 0
    order, tmp, obox, tbox = iwork[0], iwork[1], iwork[2], iwork[3]
    okey, tkey = kwork[0], kwork[1]  # the keys and squares travel with the indices: each pass reads them in
    j = 0  # sequence
    for c in range(n_cam):
        m = 0
        counts[:] = 0
        diff = np.uint64(0)
        key0 = np.uint64(0)
        for g in range(n):  # the visible Gaussians in index order, and the entries per tile (one pass)
            box = cbox[c, g]
            if box != 0:
                key = _depth_key(depth_bits[c, g])
                if m == 0:
                    key0 = key
                diff |= key ^ key0
                mu = np.uintp(m)
                order[mu] = g
                okey[mu] = key
                obox[mu] = box
                m += 1
                for ty in range((box >> 32) & 0xFFFF, box >> 48):
                    for tx in range(box & 0xFFFF, (box >> 16) & 0xFFFF):
                        counts[np.uintp(ty * tile_w + tx)] += 1
        for t in range(n_tiles):
            fill[t] = offsets[c * n_tiles + t]
            offsets[c * n_tiles + t + 1] = offsets[c * n_tiles + t] + counts[t]
        lo, width, passes = _radix_digits(diff)
        n_bins = 1 << width
        mask = np.uint64(n_bins - 1)
        hist[:passes, :n_bins] = 0
        # every digit's histogram in one pass over the keys (up to three digits without the loop over them: its
        # shifts and signed indices cost ~2 ns an increment)
        h0, h1, h2 = hist[0], hist[1], hist[2]
        ulo, w1, w2 = np.uint64(lo), np.uint64(width), np.uint64(2 * width)
        for i in range(m):
            k = okey[i] >> ulo
            h0[np.uintp(k & mask)] += 1
            if passes > 1:
                h1[np.uintp((k >> w1) & mask)] += 1
                if passes > 2:
                    h2[np.uintp((k >> w2) & mask)] += 1
                    for p in range(3, passes):
                        hist[p, (k >> np.uint64(p * width)) & mask] += 1
        for p in range(passes):
            sh = np.uint64(lo + p * width)
            if hist[p, (okey[0] >> sh) & mask] == m:
                continue  # one digit value for all: the pass would not move anything
            acc = 0
            for b in range(n_bins):
                h = hist[p, b]
                hist[p, b] = acc
                acc += h
            hp = hist[p]
            for i in range(m):  # unsigned indices: no wraparound test per access
                b = np.uintp((okey[i] >> sh) & mask)
                d = np.uintp(hp[b])
                tmp[d] = order[i]
                tkey[d] = okey[i]
                tbox[d] = obox[i]
                hp[b] = d + _U1
            order, tmp = tmp, order
            okey, tkey = tkey, okey
            obox, tbox = tbox, obox
        for i in range(m):
            g = order[i]
            box = obox[i]
            x0, x1, y0, y1 = box & 0xFFFF, (box >> 16) & 0xFFFF, (box >> 32) & 0xFFFF, box >> 48
            order_out[c, i] = g
            roff[c * n + i] = j
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    t = np.uintp(ty * tile_w + tx)
                    f = fill[t]
                    gids[np.uintp(f)] = g
                    epos[np.uintp(j)] = f
                    fill[t] = f + 1
                    j += 1
        for i in range(m, n):
            order_out[c, i] = -1
            roff[c * n + i] = j
    roff[n_cam * n] = j


# --------------------------------------------------------------------------------------------------
# Compositing
# --------------------------------------------------------------------------------------------------
# The compositing kernels run in the dtype of their inputs (float32 in a fit, float64 in the parity tests): every
# constant comes from ``cst`` (:func:`composite_constants`) and every pixel centre from an array of that dtype, so
# no float64 literal promotes the per-pixel arithmetic. Fast-math without ``nnan``/``ninf`` (the code compares
# and clamps; no infinities or NaNs are assumed away); the per-tile code is the same on any thread count.
SIGMA_MARGIN = 1e-3  # a sigma cut's margin above ln(255 o): far above float32 rounding of the row spans
NARROW_BOX = 8  # boxes this wide (pixels) or narrower skip the row spans: testing each pixel costs less
# The pixel boxes bound the ellipse sigma <= ln(255 o) + SIGMA_MARGIN (the compositing's cut) plus this margin
# (pixels) against rounding: every pixel the compositing can accept, not a pixel of slack around it (the PyTorch
# renderer enumerates boxes with a whole pixel of margin: same pixels accepted, more candidates). Tiny splats
# composite ~2 pixels per row, so rows and entries, not pixels, are the forward pass's cost: the pixel of margin
# on every side made ~1.5 rows and ~1.2 entries of work per Gaussian for nothing.
BOX_MARGIN = 1e-3


def composite_constants(alpha_clamp: float, ed_alpha_min: float, dtype) -> np.ndarray:
    """The compositing kernels' constants in the arithmetic's dtype: alpha clamp, 1/255, the transmittance
    stop, 0.5, 1, 0, 2, and the expected depth's least alpha (``D / max(alpha, ed_alpha_min)``)."""
    return np.array([alpha_clamp, ALPHA_THRESHOLD, TRANSMITTANCE_STOP, 0.5, 1.0, 0.0, 2.0, ed_alpha_min], dtype=dtype)


# The expected depth's backward ("ED" render modes) per pixel, in the compositing backward (no PyTorch pass over
# the image): compiled without fast-math and not inlined, so that each operation rounds as PyTorch's backward of
# ``D / alphas.clamp(min=ed_alpha_min)`` does (the kernels' fast-math would contract its multiply-add and share
# one reciprocal between its two divisions).
@_jit
def _ed_backward(v_ed, va, T, ed, one, zero, ed_min):
    """(dL/dD, dL/dalpha) of a pixel of final transmittance ``T`` whose expected depth ``ed`` got the gradient
    ``v_ed`` and whose alpha got ``va``: PyTorch's backward of ``D / alphas.clamp(min=ed_min)`` (the division:
    ``v / a`` and ``-v * ((D / a) / a)``; the clamp: the gradient where ``alpha >= ed_min``) added to ``va``."""
    a = one - T
    ca = max(a, ed_min)
    v_ca = -v_ed * (ed / ca)
    return v_ed / ca, va + (v_ca if a >= ed_min else zero)


# A list entry's record (:func:`pack_gaussians`, gathered per tile in list order by :func:`gather_entries`): the
# compositing loops read one contiguous row per entry instead of five scattered arrays.
R_MX, R_MY, R_Q0, R_Q1, R_Q2, R_O, R_CUT, R_INVQ0, R_X0, R_X1, R_Y0, R_Y1, R_FEAT = range(13)


def composite_tile_size(width: int, height: int) -> int:
    """The side of the compositing tiles (pixels): 64 from 256² up, 32 below. Independent of the API's
    ``tile_size``, which keeps its meaning (gsplat's squares: which pixels a Gaussian may touch, ``n_isects``):
    each Gaussian's pixel box is clipped to its squares' rectangle (:func:`pack_gaussians`), the same pixels as
    compositing it tile by tile, while the larger tiles cut the list entries (fewer Gaussians cross a tile edge)."""
    return 64 if width * height >= 256 * 256 else 32


@_pfjit
def pack_gaussians(means2d, conics, opacities, colors, radii, depths, tile_size, tile_w, tile_h, ctile, width,
                   height, rec, cbox, depth64, tiles_per_gauss):
    """Per (camera, Gaussian), computed once per call instead of once per list entry, in parallel (gsplat's
    ``isect_tiles`` squares, half-open in ``tile_size`` tiles of ``tile_w`` x ``tile_h``, empty when culled,
    decide ``n_isects`` and clip the pixel box):

    - ``rec`` [C, N, 13 + D] (the compositing dtype): the 2D mean, conic, opacity, the ``sigma`` above which ``o
      exp(-sigma) < 1/255`` for certain (``ln(255 o)`` plus ``SIGMA_MARGIN``; pairs below it take the exact
      test), ``1 / q0``, the pixel box ``[x0, x1) x [y0, y1)`` of its ``alpha >= 1/255`` ellipse ``q <= 2 (ln(255
      o) + SIGMA_MARGIN)`` plus ``BOX_MARGIN`` (the pixels the PyTorch renderer's boxes can accept; empty when
      culled or never visible; clipped to the image and to the rectangle of its ``tile_size`` squares, as the PyTorch
      renderer's tiles clip it) and its features; written only for a Gaussian with a box (``cbox`` not 0), the
      only ones read;
    - ``cbox`` [C, N] = the compositing tiles (side ``ctile``) the box touches, packed into one integer
      ``x0 | x1 << 16 | y0 << 32 | y1 << 48`` (0 with an empty box; :func:`bin_gaussians` reads it);
    - ``depth64`` [C, N] = ``depths`` in float64 (:func:`bin_gaussians` sorts their bits);
    - ``tiles_per_gauss`` [C, N] = the number of ``tile_size`` squares (the API's ``meta``).

    float64 arithmetic: this is per Gaussian, not per pixel. Returns the number of (``tile_size`` tile,
    Gaussian) intersections and of (compositing tile, Gaussian) entries."""
    n_cam, n = radii.shape
    n_feat = colors.shape[2]
    total = 0
    n_isects = 0
    csh = 0  # ctile = 2^csh (composite_tile_size's sides are): the box's tiles by shifts (its bounds are >= 0)
    while (1 << csh) < ctile:
        csh += 1
    pow2 = (1 << csh) == ctile
    for c in range(n_cam):
        for g in numba.prange(n):
            depth64[c, g] = depths[c, g]
            bx0 = bx1 = by0 = by1 = 0
            if radii[c, g] > 0:
                tr = radii[c, g] / tile_size
                tx, ty = means2d[c, g, 0] / tile_size, means2d[c, g, 1] / tile_size
                bx0 = min(max(math.floor(tx - tr), 0), tile_w)
                bx1 = min(max(math.ceil(tx + tr), 0), tile_w)
                by0 = min(max(math.floor(ty - tr), 0), tile_h)
                by1 = min(max(math.ceil(ty + tr), 0), tile_h)
                n_isects += (bx1 - bx0) * (by1 - by0)
            tiles_per_gauss[c, g] = (bx1 - bx0) * (by1 - by0)
            o = float(opacities[c, g])
            x0 = x1 = y0 = y1 = 0
            q0 = q1 = q2 = lo = 0.0
            if radii[c, g] > 0 and o * 255.0 > 1.0:
                q0, q1, q2 = float(conics[c, g, 0]), float(conics[c, g, 1]), float(conics[c, g, 2])
                lo = math.log(o * 255.0)  # > 0 here: one log for the cut and the extent
                extent = 2.0 * (lo + SIGMA_MARGIN)
                inv_det = 1.0 / max(q0 * q2 - q1 * q1, 1e-30)
                half_w = math.sqrt(extent * q2 * inv_det) + BOX_MARGIN
                half_h = math.sqrt(extent * q0 * inv_det) + BOX_MARGIN
                u, v = float(means2d[c, g, 0]) - 0.5, float(means2d[c, g, 1]) - 0.5
                x0 = max(min(max(math.floor(u - half_w), 0), width), bx0 * tile_size)
                x1 = min(min(max(math.floor(u + half_w) + 1, 0), width), bx1 * tile_size)
                y0 = max(min(max(math.floor(v - half_h), 0), height), by0 * tile_size)
                y1 = min(min(max(math.floor(v + half_h) + 1, 0), height), by1 * tile_size)
            if x0 < x1 and y0 < y1:  # the record: only a Gaussian with a box is ever read (gather_entries)
                rec[c, g, R_MX], rec[c, g, R_MY] = means2d[c, g, 0], means2d[c, g, 1]
                rec[c, g, R_Q0], rec[c, g, R_Q1], rec[c, g, R_Q2], rec[c, g, R_O] = q0, q1, q2, o
                rec[c, g, R_CUT] = lo + SIGMA_MARGIN
                rec[c, g, R_INVQ0] = 1.0 / q0 if q0 > 0.0 else 0.0
                for f in range(n_feat):
                    rec[c, g, R_FEAT + f] = colors[c, g, f]
                rec[c, g, R_X0], rec[c, g, R_X1], rec[c, g, R_Y0], rec[c, g, R_Y1] = x0, x1, y0, y1
                if pow2:  # shifts: four 64-bit divisions cost ~40 cycles each, per Gaussian
                    cx0, cx1, cy0, cy1 = x0 >> csh, ((x1 - 1) >> csh) + 1, y0 >> csh, ((y1 - 1) >> csh) + 1
                else:
                    cx0, cx1, cy0, cy1 = x0 // ctile, (x1 - 1) // ctile + 1, y0 // ctile, (y1 - 1) // ctile + 1
                cbox[c, g] = cx0 | (cx1 << 16) | (cy0 << 32) | (cy1 << 48)
                total += (cx1 - cx0) * (cy1 - cy0)
            else:
                cbox[c, g] = 0
    return n_isects, total


@_pjit
def gather_entries(offsets, gids, n_tiles, tile_w, tile_size, width, height, rec, ent, cap):
    """``ent`` [n_isects, 13 + D] = each list entry's record, in list order (tiles in parallel); ``cap``
    [C * tiles] = per tile the pixels of its entries' boxes within it (the most pairs compositing can keep)."""
    n_all = offsets.shape[0] - 1
    n, n_rec = rec.shape[1], np.uintp(rec.shape[2])
    rf, ef = rec.reshape(-1), ent.reshape(-1)  # flat, unsigned offsets: 3.79 -> 3.17 ms (RGB, one thread)
    for it in numba.prange(n_all):
        t = _interleave(it, n_all)
        c, x_lo, x_hi, y_lo, y_hi = _tile(t, n_tiles, tile_w, tile_size, width, height)
        area = 0
        for k in range(offsets[t], offsets[t + 1]):
            src, dst = np.uintp(c * n + gids[k]) * n_rec, np.uintp(k) * n_rec
            for j in range(n_rec):
                ef[dst + j] = rf[src + j]
            x0, x1 = max(int(rf[src + np.uintp(R_X0)]), x_lo), min(int(rf[src + np.uintp(R_X1)]), x_hi)
            y0, y1 = max(int(rf[src + np.uintp(R_Y0)]), y_lo), min(int(rf[src + np.uintp(R_Y1)]), y_hi)
            if x0 < x1 and y0 < y1:
                area += (x1 - x0) * (y1 - y0)
        cap[t] = area


@_ijit
def _interleave(i, n):
    """The tile of parallel iteration ``i`` of ``n``: the even tiles first, then the odd ones. numba's pool gives
    each thread one contiguous range of iterations, so each thread gets every other tile of the whole image
    instead of its top or bottom half (a scene's sky and ground cost differently); which thread renders a tile
    never changes its result."""
    half = (n + 1) // 2
    return 2 * i if i < half else 2 * (i - half) + 1


@intrinsic
def _take(typingctx, counter):
    """``counter[0]``'s value before adding one to it, atomically (an int64 array): the compositing's threads
    take their next tile from one counter (numba's pool gives each thread a fixed range of a ``prange``, so a
    thread that starts late, or loses its core for a while, would hold the others up at the loop's end)."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64):
        return None

    def codegen(context, builder, sig, args):
        arr = context.make_array(sig.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", arr.data, context.get_constant(types.int64, 1), "monotonic")

    return types.int64(counter), codegen


@_ijit
def _tile(t, n_tiles, tile_w, tile_size, width, height):
    """Camera and pixel bounds ``[x_lo, x_hi) x [y_lo, y_hi)`` of tile ``t`` (``camera * n_tiles + row *
    tile_w + col``)."""
    c, tt = t // n_tiles, t % n_tiles
    x_lo, y_lo = (tt % tile_w) * tile_size, (tt // tile_w) * tile_size
    return c, x_lo, min(x_lo + tile_size, width), y_lo, min(y_lo + tile_size, height)


@_ifjit
def _row_span(dy, mx, q0, inv_q0, q1, q2, cut, half, zero, two, x0, x1):
    """The columns ``[rx0, rx1)`` of ``[x0, x1)`` in one pixel row (offset ``dy`` from the mean) where ``sigma``
    can be <= ``cut``: the roots of ``q0/2 dx^2 + q1 dy dx + q2/2 dy^2 - cut``. ``cut`` carries its own margin
    (``SIGMA_MARGIN``), so every pixel the exact test accepts is inside."""
    if q0 <= zero:
        return x0, x1
    b = q1 * dy
    disc = b * b - q0 * (q2 * dy * dy - two * cut)
    if disc < zero:
        return x0, x0
    root = math.sqrt(disc)
    lo = mx - half + (-b - root) * inv_q0
    hi = mx - half + (-b + root) * inv_q0
    return max(x0, math.floor(lo)), max(min(x1, math.floor(hi) + 1), x0)


@_ifjit
def _row_candidates(ly, dy, px0, px1, x_lo, tw, xc, mx, q0, q1, q2, cut, half, zero, done, cp, cq, cs, n):
    """Pass 1 of :func:`composite_forward` over columns ``[px0, px1)`` of the tile's row ``ly`` (offset ``dy``
    from the mean): each pixel's index in the tile, ``row << 16 | column`` and ``sigma`` stored at ``n``, which
    advances (no branch) where ``sigma`` is within the cut and the pixel is not stopped. Returns the new ``n``."""
    row = ly * tw - x_lo
    hq = ly << 16
    for px in range(px0, px1):
        p = np.uintp(row + px)
        dx = xc[np.uintp(px - x_lo)] - mx
        sigma = half * (q0 * dx * dx + q2 * dy * dy) + q1 * dx * dy
        cp[n] = p
        cq[n] = hq | (px - x_lo)
        cs[n] = sigma
        n += np.uintp((sigma >= zero) & (sigma <= cut) & (not done[p]))
    return n


@_ifjit
def _pair_weight(p, e, o, alpha_clamp, athr, tstop, one, zero, T, done):
    """One candidate pair of the compositing (``e = exp(-sigma)``): ``(w, T_i, state)``, state 0 when its alpha is
    below 1/255 (skipped), 1 when the pixel's transmittance would fall to the stop (marked done, not composited), 2
    when composited (``T[p]`` updated; ``w = alpha T_i`` is its weight)."""
    alpha = min(alpha_clamp, o * e)
    if alpha < athr:
        return zero, zero, 0
    tp = T[p]
    nt = tp * (one - alpha)
    if nt <= tstop:
        done[p] = True
        return zero, tp, 1
    T[p] = nt
    return alpha * tp, tp, 2


@_ifjit
def _record_pair(pix, pes, pts, j, q, e, tp):
    """Keep a contributing pair for the backward pass: its pixel (row << 16 | column: no division to undo it),
    ``exp(-sigma)`` and the transmittance in front of it (the backward's ``T_i``: no division to recover it)."""
    pix[j] = q
    pes[j] = e
    pts[j] = tp


@_pfjit
def composite_forward(ent, offsets, width, height, tile_size, tile_w, cst, backgrounds, use_bg, render, t_final,
                      pbase, pend, pix, pes, pts, record, ed, ed_val):
    """Front-to-back compositing: ``render`` [C, H, W, D], ``t_final`` [C, H, W] (final transmittance).

    Per tile, Gaussian-major: the tile's list is walked once in depth order and each entry visits only the
    pixels of its alpha box, row by row within the row's span of its ellipse, so the work is the candidate
    pairs, not pixels x list length; each pixel still sees its Gaussians front to back with the same arithmetic
    as a per-pixel loop. The tile's state (transmittance, accumulated features) lives in contiguous arrays.

    With ``record``, the pairs that contributed are kept for the backward pass, which then replays only them
    (no spans, cut tests, ``exp`` or divisions again): per pair its pixel in the tile ``pix`` (row << 16 |
    column), ``exp(-sigma)`` ``pes`` and the pixel's transmittance in front of it ``pts``, from the tile's slot
    ``pbase[t]`` (its capacity: :func:`gather_entries`' box areas) on, and per list entry the end of its pairs
    ``pend`` [n_isects] (written whether or not recording).

    With ``ed`` the last feature (a depth) is rendered as the expected depth, ``D / max(1 - T, ed_alpha_min)``,
    also written to ``ed_val`` [C, H, W] for the backward pass."""
    alpha_clamp, athr, tstop, half, one, zero, two = cst[0], cst[1], cst[2], cst[3], cst[4], cst[5], cst[6]
    ed_min = cst[7]
    n_cam = render.shape[0]
    n_feat = render.shape[3]
    tile_h = (height + tile_size - 1) // tile_size
    n_tiles = tile_w * tile_h
    n_all = n_cam * n_tiles
    nxt = np.zeros(1, np.int64)  # the next tile (_take)
    for _ in numba.prange(n_all):  # each iteration takes tiles until none is left (the later ones find none)
        while True:
            t = _take(nxt)
            if t >= n_all:
                break
            c, x_lo, x_hi, y_lo, y_hi = _tile(t, n_tiles, tile_w, tile_size, width, height)
            lo, hi = offsets[t], offsets[t + 1]
            tw = x_hi - x_lo
            n_px = tw * (y_hi - y_lo)
            T = np.ones(n_px, cst.dtype)
            acc = np.zeros(n_px * n_feat, cst.dtype)
            done = np.zeros(n_px, dtype=np.bool_)
            cp = np.empty(n_px, np.uintp)  # one entry's candidate pixels: index in the tile,
            cq = np.empty(n_px, np.int32)  # row << 16 | column (what forward records),
            cs = np.empty(n_px, cst.dtype)  # sigma, then exp(-sigma)
            xc = np.empty(tw, cst.dtype)
            for i in range(tw):
                xc[i] = x_lo + i + 0.5
            yc = np.empty(y_hi - y_lo, cst.dtype)
            for i in range(y_hi - y_lo):
                yc[i] = y_lo + i + 0.5
            n_done = 0
            j = pbase[t]
            for k in range(lo, hi):
                if n_done == n_px:
                    for kk in range(k, hi):
                        pend[kk] = j
                    break
                e_ = ent[k]
                x0, x1 = max(int(e_[R_X0]), x_lo), min(int(e_[R_X1]), x_hi)
                y0, y1 = max(int(e_[R_Y0]), y_lo), min(int(e_[R_Y1]), y_hi)
                if x0 < x1 and y0 < y1:
                    mx, my, q0, q1, q2 = e_[R_MX], e_[R_MY], e_[R_Q0], e_[R_Q1], e_[R_Q2]
                    o, cut, inv_q0 = e_[R_O], e_[R_CUT], e_[R_INVQ0]
                    c0 = e_[R_FEAT] if n_feat > 0 else zero
                    c1 = e_[R_FEAT + 1] if n_feat > 1 else zero
                    c2 = e_[R_FEAT + 2] if n_feat > 2 else zero
                    c3 = e_[R_FEAT + 3] if n_feat > 3 else zero
                    # three passes per entry: (1) the candidates (sigma within the cut, pixel not stopped), compacted
                    # without branches; (2) their exp, a loop with nothing else live across libm's call (in one loop
                    # with the compositing, the call's clobbered registers made every value a stack reload: 21.2 ->
                    # 16.9 ms at 100k x 256², one thread); (3) the compositing of the candidates, in the same
                    # (row-major) order as a per-pixel loop: the same arithmetic, results and recorded pairs. The
                    # narrow and the spanned boxes are separate loop nests (a per-row choice cost ~1 ms there).
                    n = np.uintp(0)
                    if x1 - x0 <= NARROW_BOX:
                        for py in range(y0, y1):
                            dy = yc[py - y_lo] - my
                            n = _row_candidates(py - y_lo, dy, x0, x1, x_lo, tw, xc, mx, q0, q1, q2, cut, half, zero,
                                                done, cp, cq, cs, n)
                    else:
                        for py in range(y0, y1):
                            dy = yc[py - y_lo] - my
                            rx0, rx1 = _row_span(dy, mx, q0, inv_q0, q1, q2, cut, half, zero, two, x0, x1)
                            n = _row_candidates(py - y_lo, dy, rx0, rx1, x_lo, tw, xc, mx, q0, q1, q2, cut, half, zero,
                                                done, cp, cq, cs, n)
                    for i in range(n):
                        cs[i] = math.exp(-cs[i])
                    # one loop per feature count (RGB, RGB + depth unrolled): no per-pair test of the count
                    # (measured: 18.1 -> 17.4 ms RGB, 18.0 -> 17.4 ms SH3 + RGB+ED, one thread, medians of 15)
                    if n_feat == 3:
                        for i in range(n):
                            p = cp[i]
                            w, tp, state = _pair_weight(p, cs[i], o, alpha_clamp, athr, tstop, one, zero, T, done)
                            if state != 2:
                                n_done += state  # 1: the pixel stopped here
                                continue
                            b3 = p * _U3
                            acc[b3] += w * c0
                            acc[b3 + _U1] += w * c1
                            acc[b3 + _U2] += w * c2
                            if record:
                                _record_pair(pix, pes, pts, np.uintp(j), cq[i], cs[i], tp)
                                j += 1
                    elif n_feat == 4:
                        for i in range(n):
                            p = cp[i]
                            w, tp, state = _pair_weight(p, cs[i], o, alpha_clamp, athr, tstop, one, zero, T, done)
                            if state != 2:
                                n_done += state  # 1: the pixel stopped here
                                continue
                            b4 = p * _U4
                            acc[b4] += w * c0
                            acc[b4 + _U1] += w * c1
                            acc[b4 + _U2] += w * c2
                            acc[b4 + _U3] += w * c3
                            if record:
                                _record_pair(pix, pes, pts, np.uintp(j), cq[i], cs[i], tp)
                                j += 1
                    else:
                        for i in range(n):
                            p = cp[i]
                            w, tp, state = _pair_weight(p, cs[i], o, alpha_clamp, athr, tstop, one, zero, T, done)
                            if state != 2:
                                n_done += state  # 1: the pixel stopped here
                                continue
                            for f in range(n_feat):
                                acc[p * np.uintp(n_feat) + np.uintp(f)] += w * e_[R_FEAT + f]
                            if record:
                                _record_pair(pix, pes, pts, np.uintp(j), cq[i], cs[i], tp)
                                j += 1
                pend[k] = j
            for py in range(y_lo, y_hi):
                for px in range(x_lo, x_hi):
                    p = (py - y_lo) * tw + (px - x_lo)
                    for f in range(n_feat):
                        render[c, py, px, f] = acc[p * n_feat + f] + (T[p] * backgrounds[c, f] if use_bg else zero)
                    t_final[c, py, px] = T[p]
            if ed:  # a loop of its own (in the loop above, its test cost ~0.8 ms per call at 100k x 256²)
                for py in range(y_lo, y_hi):
                    for px in range(x_lo, x_hi):
                        # one division (fast-math leaves it one: no reciprocal, nothing to contract)
                        edv = render[c, py, px, n_feat - 1] / max(one - t_final[c, py, px], ed_min)
                        render[c, py, px, n_feat - 1] = edv
                        ed_val[c, py, px] = edv


@_pfjit
def composite_backward(ent, offsets, width, height, tile_size, tile_w, cst, backgrounds, use_bg, v_render, v_alphas,
                       pbase, pend, pix, pes, pts, slots, ed, t_final, ed_val):
    """Gradients of each list entry (tile, Gaussian) into the slots [n_isects, 6 + D] (a tile writes only its
    own entries; :func:`gather_slots` sums them per Gaussian). The tile's list is walked back to front over the
    pairs forward recorded (``composite_forward``'s ``record``: pixel, ``exp(-sigma)`` and the transmittance
    ``T_i`` in front of the pair), so each pixel sees its contributions in reverse order.

    The colour and alpha terms of ``dL/dalpha_i`` need, per pixel, only one scalar: with ``v`` the pixel's
    ``dL/dfeature``, ``d_i = v . c_i`` and ``S_i = v . (background T_final + sum_{j > i} w_j c_j) - dL/dalpha_out
    T_final`` (what lies behind pair ``i``), ``dL/dalpha_i = T_i d_i - S_i / (1 - alpha_i)``; the kernel keeps
    ``B = S_i / T_{i+1}`` instead, which starts at ``v . background - dL/dalpha_out`` and steps back as ``B <- B
    (1 - alpha_i) + alpha_i d_i``, so ``dL/dalpha_i = T_i (d_i - B)``: no division, no feature-sized state per
    pixel, no transmittance recovered by division (the same gradients up to rounding as gsplat's per-feature
    ``buffer`` form).
    Per-entry sums are in the compositing dtype (float32 in a fit); :func:`gather_slots` adds the entries of a
    Gaussian in float64. With ``ed`` (``composite_forward``'s), the last feature's gradient is the expected
    depth's, taken back to the accumulated depth and the alpha (``_ed_backward``, from ``t_final`` and ``ed_val``)."""
    alpha_clamp, half, one, zero, ed_min = cst[0], cst[3], cst[4], cst[5], cst[7]
    n_cam = v_render.shape[0]
    n_feat = v_render.shape[3]
    tile_h = (height + tile_size - 1) // tile_size
    n_tiles = tile_w * tile_h
    n_all = n_cam * n_tiles
    nxt = np.zeros(1, np.int64)  # the next tile (_take)
    for _ in numba.prange(n_all):  # each iteration takes tiles until none is left (the later ones find none)
        while True:
            t = _take(nxt)
            if t >= n_all:
                break
            c, x_lo, x_hi, y_lo, y_hi = _tile(t, n_tiles, tile_w, tile_size, width, height)
            lo, hi = offsets[t], offsets[t + 1]
            tw = x_hi - x_lo
            n_px = tw * (y_hi - y_lo)
            B = np.empty(n_px, cst.dtype)
            vr = np.empty(n_px * n_feat, cst.dtype)
            gcol = np.empty(n_feat, cst.dtype)
            utw, unf = np.uintp(tw), np.uintp(n_feat)
            xc = np.empty(tw, cst.dtype)
            for i in range(tw):
                xc[i] = x_lo + i + 0.5
            yc = np.empty(y_hi - y_lo, cst.dtype)
            for i in range(y_hi - y_lo):
                yc[i] = y_lo + i + 0.5
            for py in range(y_lo, y_hi):
                for px in range(x_lo, x_hi):
                    p = (py - y_lo) * tw + (px - x_lo)
                    va, v_last = v_alphas[c, py, px], (v_render[c, py, px, n_feat - 1] if n_feat > 0 else zero)
                    if ed:
                        v_last, va = _ed_backward(v_last, va, t_final[c, py, px], ed_val[c, py, px], one, zero,
                                                  ed_min)
                    bp = -va
                    for f in range(n_feat):
                        vf = v_render[c, py, px, f] if f < n_feat - 1 else v_last
                        vr[p * n_feat + f] = vf
                        if use_bg:
                            bp += vf * backgrounds[c, f]
                    B[p] = bp
            for k in range(hi - 1, lo - 1, -1):
                # per-entry sums in the compositing dtype (float32 in a fit: ~12 pairs per entry at 100k x 256²; no
                # float64 conversion and add per term), summed over entries in float64 by gather_slots
                g_mx = g_my = g_q0 = g_q1 = g_q2 = g_o = zero
                g0 = g1 = g2 = g3 = zero  # the unrolled features' sums (gcol otherwise)
                for f in range(n_feat):
                    gcol[f] = zero
                j0 = pend[k - 1] if k > lo else pbase[t]
                j1 = pend[k]
                if j1 > j0:
                    e_ = ent[k]
                    mx, my, q0, q1, q2 = e_[R_MX], e_[R_MY], e_[R_Q0], e_[R_Q1], e_[R_Q2]
                    o = e_[R_O]
                    c0 = e_[R_FEAT] if n_feat > 0 else zero
                    c1 = e_[R_FEAT + 1] if n_feat > 1 else zero
                    c2 = e_[R_FEAT + 2] if n_feat > 2 else zero
                    c3 = e_[R_FEAT + 3] if n_feat > 3 else zero
                    for jj in range(j0, j1):
                        j = np.uintp(jj)  # unsigned indices: no negative-index wraparound on every access
                        pv = np.uintp(pix[j])
                        lx, ly = pv & _UFFFF, pv >> _U16
                        p = ly * utw + lx
                        e = pes[j]
                        Ti = pts[j]
                        raw = o * e
                        alpha = min(alpha_clamp, raw)
                        w = alpha * Ti
                        if n_feat == 3 or n_feat == 4:  # RGB, RGB + depth: unrolled
                            b = p * unf
                            vc0, vc1, vc2 = vr[b], vr[b + _U1], vr[b + _U2]
                            g0 += w * vc0
                            g1 += w * vc1
                            g2 += w * vc2
                            d = vc0 * c0 + vc1 * c1 + vc2 * c2
                            if n_feat == 4:
                                vc3 = vr[b + _U3]
                                g3 += w * vc3
                                d += vc3 * c3
                        else:
                            d = zero
                            for f in range(n_feat):
                                vc = vr[p * unf + np.uintp(f)]
                                gcol[f] += w * vc
                                d += vc * e_[R_FEAT + f]
                        bp = B[p]
                        diff = d - bp
                        B[p] = bp + alpha * diff
                        if raw <= alpha_clamp:
                            v_alpha = Ti * diff
                            g_o += v_alpha * e
                            v_sigma = -v_alpha * alpha
                            hv = half * v_sigma
                            dx = xc[lx] - mx
                            dy = yc[ly] - my
                            g_q0 += hv * dx * dx
                            g_q1 += v_sigma * dx * dy
                            g_q2 += hv * dy * dy
                            g_mx -= v_sigma * (q0 * dx + q1 * dy)
                            g_my -= v_sigma * (q1 * dx + q2 * dy)
                slots[k, 0], slots[k, 1], slots[k, 2], slots[k, 3], slots[k, 4] = g_mx, g_my, g_q0, g_q1, g_q2
                slots[k, 5] = g_o
                if n_feat == 3 or n_feat == 4:
                    gcol[0], gcol[1], gcol[2] = g0, g1, g2
                    if n_feat == 4:
                        gcol[3] = g3
                for f in range(n_feat):
                    slots[k, 6 + f] = gcol[f]


@_pjit
def gather_slots(order, roff, epos, slots, grads):
    """``grads`` [C, N, 6 + D] (2D mean, conic, opacity, features; the caller zero-fills it: Gaussians without
    entries keep their zeros) = the sums of the list entries' ``slots`` [n_isects, 6 + D] per (camera,
    Gaussian), in float64 over its entries in row-major tile order (:func:`bin_gaussians`' ``order``, ``roff``,
    ``epos``): deterministic for any thread count. Walked in depth order: each tile's entries are then read in
    list order (near-sequential), and the scattered accesses are one row written per Gaussian instead of one
    read per entry."""
    n_s = np.uintp(slots.shape[1])
    n_cam, n = order.shape
    total = n_cam * n
    sf, gf = slots.reshape(-1), grads.reshape(-1)  # flat, unsigned offsets: 3.19 -> 2.92 ms (RGB, one thread)
    for ch in numba.prange((total + CHUNK - 1) // CHUNK):
        acc = np.empty(n_s)
        idx0 = ch * CHUNK
        c = idx0 // n  # one division per chunk (a 64-bit division costs tens of cycles)
        r = idx0 - c * n
        for idx in range(idx0, min(idx0 + CHUNK, total)):
            g = order[c, r]
            i0, i1 = roff[idx], roff[idx + 1]
            if g >= 0:
                dst = np.uintp(c * n + g) * n_s
                if i1 == i0 + 1:  # one entry (most Gaussians at 64-px tiles): its row as the sum
                    src = np.uintp(epos[i0]) * n_s
                    for j in range(n_s):
                        gf[dst + j] = 0.0 + sf[src + j]  # what the float64 sum from zero gives (-0.0 -> +0.0)
                else:
                    for j in range(n_s):
                        acc[j] = 0.0
                    for i in range(i0, i1):
                        src = np.uintp(epos[i]) * n_s
                        for j in range(n_s):
                            acc[j] += sf[src + j]
                    for j in range(n_s):
                        gf[dst + j] = acc[j]
            r += 1
            if r == n:
                r, c = 0, c + 1


# Four float64 lanes in one SIMD register (LLVM's <4 x double>), for the SH kernels: a coefficient's three channels
# side by side (the fourth lane unused), so one instruction does what three scalar ones did. numba runs no SLP
# vectoriser (NUMBA_SLP_VECTORIZE is off: turned on for the process, it left these sums scalar and slowed the SH
# forward 2.4 -> 3.3 ms), and the loop vectoriser unrolls three-iteration channel loops instead, so the lanes are
# written out with these intrinsics. Each lane's arithmetic is the scalar code's (llvm.fma is the fused multiply-add
# that LLVM contracted the scalar sums into): the same bits.
class _V4Type(types.Type):
    def __init__(self):
        super().__init__(name="V4f64")


_V4 = _V4Type()
_V4_IR = ir.VectorType(ir.DoubleType(), 4)


@register_model(_V4Type)
class _V4Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _V4_IR)


def _load_lanes(context, builder, sig, args, n_load):
    aryty = sig.args[0]
    elt = context.get_data_type(aryty.dtype)
    arr = context.make_array(aryty)(context, builder, args[0])
    ptr = builder.gep(arr.data, [args[1]])
    if n_load == 4:  # one unaligned 4-element load
        v = builder.load(builder.bitcast(ptr, ir.VectorType(elt, 4).as_pointer()), align=1)
    else:
        v = ir.Constant(ir.VectorType(elt, 4), [0.0] * 4)
        for j in range(3):
            x = builder.load(builder.gep(ptr, [ir.Constant(ir.IntType(64), j)]))
            v = builder.insert_element(v, x, ir.Constant(ir.IntType(32), j))
    return builder.fpext(v, _V4_IR) if aryty.dtype == types.float32 else v


def _is_flat_float(arr):
    return (isinstance(arr, types.Array) and arr.dtype in (types.float32, types.float64) and arr.ndim == 1
            and arr.layout == "C")  # the lanes are consecutive elements


def _lanes_intrinsic(name, n, store, doc):
    """A numba intrinsic ``name(arr, idx)`` loading (``store`` False: lanes from elements ``idx ..``) or
    ``name(arr, idx, v)`` storing ``n`` lanes (3 or 4) of a C-contiguous 1-D float32 / float64 array."""
    if store:
        def impl(typingctx, arr, idx, v):
            if not _is_flat_float(arr):
                return None
            return types.none(arr, idx, v), lambda context, builder, sig, args: _store_lanes(context, builder, sig,
                                                                                            args, n)
    else:
        def impl(typingctx, arr, idx):
            if not _is_flat_float(arr):
                return None
            return _V4(arr, idx), lambda context, builder, sig, args: _load_lanes(context, builder, sig, args, n)
    impl.__name__ = impl.__qualname__ = name
    impl.__doc__ = doc
    return intrinsic(impl)


_v3_load = _lanes_intrinsic("_v3_load", 3, False, "Elements ``idx .. idx + 2`` of a 1-D array (float32 or float64) "
                            "as float64 lanes 0-2 (lane 3 zero).")
_v4_load = _lanes_intrinsic("_v4_load", 4, False, "Elements ``idx .. idx + 3`` of a 1-D array as float64 lanes, in "
                            "one load: lanes 0-2 as _v3_load's, lane 3 whatever follows (the caller knows ``idx + 3`` "
                            "is in the array and ignores that lane).")


def _store_lanes(context, builder, sig, args, n_store):
    aryty = sig.args[0]
    vec = args[2]
    if aryty.dtype == types.float32:
        vec = builder.fptrunc(vec, ir.VectorType(ir.FloatType(), 4))
    arr = context.make_array(aryty)(context, builder, args[0])
    ptr = builder.gep(arr.data, [args[1]])
    if n_store == 4:
        builder.store(vec, builder.bitcast(ptr, vec.type.as_pointer()), align=1)
    else:
        for j in range(3):
            builder.store(builder.extract_element(vec, ir.Constant(ir.IntType(32), j)),
                          builder.gep(ptr, [ir.Constant(ir.IntType(64), j)]))
    return context.get_dummy_value()


_v3_store = _lanes_intrinsic("_v3_store", 3, True, "Lanes 0-2 of ``v`` into elements ``idx .. idx + 2`` of a "
                             "1-D array (rounded to its dtype).")
_v4_store = _lanes_intrinsic("_v4_store", 4, True, "The four lanes into elements ``idx .. idx + 3`` in one store "
                             "(lane 3 lands on ``idx + 3``, which the caller writes again after).")


def _llvm_fma(builder, ty, suffix):
    """LLVM's fused multiply-add on ``ty`` (``llvm.fma.<suffix>``, rounded once), declared in the builder's module."""
    return cgutils.get_or_insert_function(builder.module, ir.FunctionType(ty, [ty] * 3), f"llvm.fma.{suffix}")


def _fma_v4(builder):
    """LLVM's lane-wise fused multiply-add on <4 x double> (``llvm.fma.v4f64``)."""
    return _llvm_fma(builder, _V4_IR, "v4f64")


@intrinsic
def _v4_dot4(typingctx, ca, cb, cc, cd, v):
    """The four coefficients' weights ``c . v`` (lanes 0-2 of ``ca`` .. ``cd`` with those of ``v``) as lanes:
    lane i ``fma(c_2, v_2, fma(c_1, v_1, c_0 v_0))`` of the i-th coefficient (a 4 x 4 transpose, three vector ops)."""
    def codegen(context, builder, sig, args):
        i32 = ir.IntType(32)
        fma = _fma_v4(builder)
        rows = []
        for j in range(3):
            lo = builder.shuffle_vector(args[0], args[1], ir.Constant(ir.VectorType(i32, 4), [j, 4 + j, j, 4 + j]))
            hi = builder.shuffle_vector(args[2], args[3], ir.Constant(ir.VectorType(i32, 4), [j, 4 + j, j, 4 + j]))
            col = builder.shuffle_vector(lo, hi, ir.Constant(ir.VectorType(i32, 4), [0, 1, 4, 5]))
            vj = builder.shuffle_vector(args[4], args[4], ir.Constant(ir.VectorType(i32, 4), [j] * 4))
            rows.append((col, vj))
        acc = builder.fmul(rows[0][0], rows[0][1])
        acc = builder.call(fma, [rows[1][0], rows[1][1], acc])
        return builder.call(fma, [rows[2][0], rows[2][1], acc])

    return _V4(_V4, _V4, _V4, _V4, _V4), codegen


@intrinsic
def _v4_colour(typingctx, acc, depth):
    """``max(acc + 0.5, 0)`` in lanes 0-2 (``max``'s operands as the scalar ``max(a + 0.5, 0.0)``'s: a NaN stays),
    ``depth`` in lane 3."""
    def codegen(context, builder, sig, args):
        a = builder.fadd(args[0], ir.Constant(_V4_IR, [0.5] * 4))
        zero = ir.Constant(_V4_IR, [0.0] * 4)
        v = builder.select(builder.fcmp_ordered(">", zero, a), zero, a)
        return builder.insert_element(v, args[1], ir.Constant(ir.IntType(32), 3))

    return _V4(_V4, types.float64), codegen


@intrinsic
def _v4_cut(typingctx, acc):
    """Bit j (j < 3) set where lane j's ``acc + 0.5 < 0``: :func:`sh_forward`'s ``cut``."""
    def codegen(context, builder, sig, args):
        a = builder.fadd(args[0], ir.Constant(_V4_IR, [0.5] * 4))
        neg = builder.fcmp_ordered("<", a, ir.Constant(_V4_IR, [0.0] * 4))
        bits = builder.zext(builder.bitcast(neg, ir.IntType(4)), ir.IntType(8))
        return builder.and_(bits, ir.Constant(ir.IntType(8), 7))

    return types.uint8(_V4), codegen


@intrinsic
def _v4_splat(typingctx, x):
    """``x`` (float64) in all four lanes."""
    def codegen(context, builder, sig, args):
        v = builder.insert_element(ir.Constant(_V4_IR, None), args[0], ir.Constant(ir.IntType(32), 0))
        lanes = ir.Constant(ir.VectorType(ir.IntType(32), 4), [0] * 4)
        return builder.shuffle_vector(v, ir.Constant(_V4_IR, None), lanes)

    return _V4(types.float64), codegen


@intrinsic
def _v4_set(typingctx, x, y, z):
    """(x, y, z, 0) as lanes."""
    def codegen(context, builder, sig, args):
        v = ir.Constant(_V4_IR, [0.0] * 4)
        for j in range(3):
            v = builder.insert_element(v, args[j], ir.Constant(ir.IntType(32), j))
        return v

    return _V4(types.float64, types.float64, types.float64), codegen


@intrinsic
def _v4_mul(typingctx, a, b):
    def codegen(context, builder, sig, args):
        return builder.fmul(args[0], args[1])

    return _V4(_V4, _V4), codegen


@intrinsic
def _v4_fma(typingctx, a, b, c):
    """``a * b + c`` lane by lane, rounded once (llvm.fma)."""
    def codegen(context, builder, sig, args):
        return builder.call(_fma_v4(builder), args)

    return _V4(_V4, _V4, _V4), codegen


@intrinsic
def _v4_get(typingctx, v, j):
    """Lane ``j`` (a constant) of ``v``."""
    if not isinstance(j, types.IntegerLiteral):
        return None

    def codegen(context, builder, sig, args):
        return builder.extract_element(args[0], ir.Constant(ir.IntType(32), sig.args[1].literal_value))

    return types.float64(v, j), codegen


# --------------------------------------------------------------------------------------------------
# Spherical harmonics (the 3DGS convention of models/gaussians/sh.py)
# --------------------------------------------------------------------------------------------------
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
       1.445305721320277, -0.5900435899266435)


@_ifjit
def _sh_basis(degree, x, y, z, b, db):
    """The ``(degree + 1)^2`` basis values at the unit direction (x, y, z) into ``b`` [16] and, when ``db`` has
    rows, their derivatives into ``db`` [16, 3] (sh.py's ``sh_basis`` term by term)."""
    grad = db.shape[0] > 0
    b[0] = _C0
    if grad:
        for i in range(16):
            db[i, 0] = db[i, 1] = db[i, 2] = 0.0
    if degree >= 1:
        b[1], b[2], b[3] = -_C1 * y, _C1 * z, -_C1 * x
        if grad:
            db[1, 1], db[2, 2], db[3, 0] = -_C1, _C1, -_C1
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b[4] = _C2[0] * x * y
        b[5] = _C2[1] * y * z
        b[6] = _C2[2] * (2.0 * zz - xx - yy)
        b[7] = _C2[3] * x * z
        b[8] = _C2[4] * (xx - yy)
        if grad:
            db[4, 0], db[4, 1] = _C2[0] * y, _C2[0] * x
            db[5, 1], db[5, 2] = _C2[1] * z, _C2[1] * y
            db[6, 0], db[6, 1], db[6, 2] = -2.0 * _C2[2] * x, -2.0 * _C2[2] * y, 4.0 * _C2[2] * z
            db[7, 0], db[7, 2] = _C2[3] * z, _C2[3] * x
            db[8, 0], db[8, 1] = 2.0 * _C2[4] * x, -2.0 * _C2[4] * y
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        b[9] = _C3[0] * y * (3.0 * xx - yy)
        b[10] = _C3[1] * x * y * z
        b[11] = _C3[2] * y * (4.0 * zz - xx - yy)
        b[12] = _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        b[13] = _C3[4] * x * (4.0 * zz - xx - yy)
        b[14] = _C3[5] * z * (xx - yy)
        b[15] = _C3[6] * x * (xx - 3.0 * yy)
        if grad:
            db[9, 0], db[9, 1] = _C3[0] * 6.0 * x * y, _C3[0] * (3.0 * xx - 3.0 * yy)
            db[10, 0], db[10, 1], db[10, 2] = _C3[1] * y * z, _C3[1] * x * z, _C3[1] * x * y
            db[11, 0], db[11, 1], db[11, 2] = (-2.0 * _C3[2] * x * y, _C3[2] * (4.0 * zz - xx - 3.0 * yy),
                                               8.0 * _C3[2] * y * z)
            db[12, 0], db[12, 1], db[12, 2] = (-6.0 * _C3[3] * x * z, -6.0 * _C3[3] * y * z,
                                               _C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy))
            db[13, 0], db[13, 1], db[13, 2] = (_C3[4] * (4.0 * zz - 3.0 * xx - yy), -2.0 * _C3[4] * x * y,
                                               8.0 * _C3[4] * x * z)
            db[14, 0], db[14, 1], db[14, 2] = 2.0 * _C3[5] * x * z, -2.0 * _C3[5] * y * z, _C3[5] * (xx - yy)
            db[15, 0], db[15, 1] = _C3[6] * (3.0 * xx - 3.0 * yy), -6.0 * _C3[6] * x * y


@_ifjit
def _unit_dir(means, campos, c, g):
    dx, dy, dz = (float(means[g, 0]) - campos[c, 0], float(means[g, 1]) - campos[c, 1],
                  float(means[g, 2]) - campos[c, 2])
    nrm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)  # torch.nn.functional.normalize's eps
    return dx / nrm, dy / nrm, dz / nrm, nrm


# The SH kernels read the coefficients as rows: ``dc`` [N, >= 3] holds coefficient 0 in its first three columns,
# ``rest`` [N, r0 + 3 (K - 1)] coefficient k >= 1's channel j in column ``r0 + 3 (k - 1) + j`` -- a fit's
# ``sh_dc`` / ``sh_rest`` reshaped (r0 = 0), or one [N, K, 3] array reshaped to [N, 3 K] and passed as both (r0 = 3).
# Contiguous rows and an unsigned column: a coefficient's address is the row's plus a constant (the unrolled
# degree-3 forward on [N, K, 3] strided views computed each address from the strides: 3.55 ms, not 3.26, at 100k).
@_ifjit
def _unit_dirs(means, campos, c, g0, m, D):
    """:func:`_unit_dir` of Gaussians ``g0 .. g0 + m - 1`` from camera c into ``D`` [4, >= m] (rows x, y, z, norm):
    one loop of the same expressions that LLVM vectorises (the square root and the division, ~10 ns a Gaussian
    one at a time, in SIMD registers; correctly rounded either way: the same bits)."""
    cx, cy, cz = campos[c, 0], campos[c, 1], campos[c, 2]
    for i in range(m):
        iu = np.uintp(i)
        g = np.uintp(g0) + iu
        dx, dy, dz = float(means[g, 0]) - cx, float(means[g, 1]) - cy, float(means[g, 2]) - cz
        nrm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        D[0, iu], D[1, iu], D[2, iu], D[3, iu] = dx / nrm, dy / nrm, dz / nrm, nrm


@_ifjit
def _coef(dc, rest, r0, g, k, j):
    """Coefficient ``k`` of channel ``j`` of Gaussian g (``r0``: uintp, see above)."""
    return dc[g, j] if k == 0 else rest[g, r0 + np.uintp(3 * (k - 1) + j)]


@_ifjit
def _set_coef(v_dc, v_rest, r0, g, k, x, y, z):
    """Writes coefficient ``k``'s gradient (x, y, z) of Gaussian g into ``v_dc`` (k = 0) or ``v_rest`` (rows as
    the coefficients')."""
    if k == 0:
        v_dc[g, 0], v_dc[g, 1], v_dc[g, 2] = x, y, z
    else:
        col = r0 + np.uintp(3 * (k - 1))
        v_rest[g, col], v_rest[g, col + _U1], v_rest[g, col + _U2] = x, y, z


@_ifjit
def _sh3_basis(x, y, z):
    """The 16 degree-3 basis values at the unit direction (x, y, z) as a tuple: :func:`_sh_basis`' values, the same
    expressions, held in registers (no [16] array, no degree tests)."""
    xx, yy, zz = x * x, y * y, z * z
    return (_C0, -_C1 * y, _C1 * z, -_C1 * x,
            _C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2.0 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy),
            _C3[0] * y * (3.0 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4.0 * zz - xx - yy),
            _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), _C3[4] * x * (4.0 * zz - xx - yy), _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3.0 * yy))


@_ifjit
def _sh3_rgb(b, fd, fr, od, r):
    """The three channels' ``sum_k b[k] c_k`` of one Gaussian over the 16 coefficients, from zero in k's order, as
    lanes: ``fd`` / ``fr`` are ``dc`` / ``rest`` flat, ``od`` / ``r`` the row's first column in each (uintp);
    straight-line code (literal offsets, no ``k == 0`` test)."""
    acc = _v4_mul(_v4_splat(b[0]), _v3_load(fd, od))
    acc = _v4_fma(_v4_splat(b[1]), _v4_load(fr, r), acc)
    acc = _v4_fma(_v4_splat(b[2]), _v4_load(fr, r + np.uintp(3)), acc)
    acc = _v4_fma(_v4_splat(b[3]), _v4_load(fr, r + np.uintp(6)), acc)
    acc = _v4_fma(_v4_splat(b[4]), _v4_load(fr, r + np.uintp(9)), acc)
    acc = _v4_fma(_v4_splat(b[5]), _v4_load(fr, r + np.uintp(12)), acc)
    acc = _v4_fma(_v4_splat(b[6]), _v4_load(fr, r + np.uintp(15)), acc)
    acc = _v4_fma(_v4_splat(b[7]), _v4_load(fr, r + np.uintp(18)), acc)
    acc = _v4_fma(_v4_splat(b[8]), _v4_load(fr, r + np.uintp(21)), acc)
    acc = _v4_fma(_v4_splat(b[9]), _v4_load(fr, r + np.uintp(24)), acc)
    acc = _v4_fma(_v4_splat(b[10]), _v4_load(fr, r + np.uintp(27)), acc)
    acc = _v4_fma(_v4_splat(b[11]), _v4_load(fr, r + np.uintp(30)), acc)
    acc = _v4_fma(_v4_splat(b[12]), _v4_load(fr, r + np.uintp(33)), acc)
    acc = _v4_fma(_v4_splat(b[13]), _v4_load(fr, r + np.uintp(36)), acc)
    acc = _v4_fma(_v4_splat(b[14]), _v4_load(fr, r + np.uintp(39)), acc)
    return _v4_fma(_v4_splat(b[15]), _v3_load(fr, r + np.uintp(42)), acc)


@_ifjit
def _sh_store(frgb, cut, depths, culled, with_depth, c, g, o, acc):
    """Gaussian g's colour in camera c from its sums ``acc`` (lanes) into ``frgb`` (``rgb`` flat) at ``o``, with its
    depth beside when ``with_depth`` (one 4-lane store: 1.92 -> 1.70 ms for the degree-3 forward at 100k, one thread,
    against the four scalar stores and the branches on the clamp), and its ``cut`` bits (none where ``culled``)."""
    bits = np.uint8(0) if culled else _v4_cut(acc)
    if with_depth:
        _v4_store(frgb, o, _v4_colour(acc, float(depths[c, g])))
    else:
        _v3_store(frgb, o, _v4_colour(acc, 0.0))
    cut[c, g] = bits


@_pfjit
def sh_forward(degree, means, campos, dc, rest, r0, radii, depths, rgb, cut):
    """``rgb`` [C, N, 3] = ``max(sum_k Y_k(d) c_k + 0.5, 0)`` of the shared coefficients, rows ``dc`` (k = 0)
    and ``rest`` from column ``r0`` (uintp; the layout above :func:`_coef`; float32 or float64, read as they are;
    float64 arithmetic) along the unit direction ``d`` from camera centre ``campos`` [C, 3] to each mean (sh.py's
    ``sh_to_rgb``);
    ``cut`` [C, N] (uint8) gets bit j set where channel j's sum + 0.5 < 0 (the clamp stops its gradient).

    The compositing's features, when ``radii`` [C, N] has rows (the projection's): a Gaussian culled in a camera
    (radius 0, never composited) gets zeros there, without its SH; with ``rgb`` [C, N, 4] its last column is
    ``depths`` [C, N] (the "RGB+D" modes' features in one array). ``radii`` [0, 0]: every colour evaluated.
    The three channels' sums run side by side in SIMD lanes (:func:`_v4_fma`; each lane's the scalar sum's
    operations: the same bits; 2.35 -> 1.92 ms at degree 3, 100k, one thread, against one scalar sum per channel);
    degree 3 runs straight-line code (:func:`_sh3_basis`, :func:`_sh3_rgb`: the loop's expressions and sums).
    (Not kept: two Gaussians per iteration, for two chains of fused multiply-adds in flight: 1.70 vs 1.70 ms; the
    chunk's basis in a vectorised loop into [16, chunk + 8] rows, read back as broadcasts: 2.51 ms.)"""
    n_cam, n = campos.shape[0], means.shape[0]
    nb = (degree + 1) * (degree + 1)
    culls = radii.shape[0] > 0
    with_depth = rgb.shape[2] == 4
    deg3 = degree == 3
    fd, fr = dc.reshape(-1), rest.reshape(-1)
    sd, sr = np.uintp(dc.shape[1]), np.uintp(rest.shape[1])
    frgb, n_f = rgb.reshape(-1), np.uintp(rgb.shape[2])
    for ch in numba.prange((n + CHUNK - 1) // CHUNK):
        b, db, D = np.empty(16), np.empty((0, 3)), np.empty((4, CHUNK))
        g0, g1 = ch * CHUNK, min((ch + 1) * CHUNK, n)
        for c in range(n_cam):  # each (camera, Gaussian) on its own: cameras first, the chunk's directions at once
            _unit_dirs(means, campos, c, g0, g1 - g0, D)
            for g in range(g0, g1):
                iu, gu = np.uintp(g - g0), np.uintp(g)
                od, r = gu * sd, gu * sr + r0
                culled = culls and radii[c, g] == 0
                if culled:
                    acc = _v4_splat(-0.5)  # colour max(-0.5 + 0.5, 0) = 0, no cut bits
                elif deg3:  # straight-line code: the basis in registers, the 16 terms unrolled (same sums)
                    acc = _sh3_rgb(_sh3_basis(D[0, iu], D[1, iu], D[2, iu]), fd, fr, od, r)
                else:
                    _sh_basis(degree, D[0, iu], D[1, iu], D[2, iu], b, db)
                    acc = _v4_mul(_v4_splat(b[0]), _v3_load(fd, od))  # each channel's sum in k's order
                    for k in range(1, nb):
                        acc = _v4_fma(_v4_splat(b[k]), _v3_load(fr, r + np.uintp(3 * (k - 1))), acc)
                _sh_store(frgb, cut, depths, culled, with_depth, c, g, (np.uintp(c * n) + gu) * n_f, acc)


@_ifjit
def _sh_dir_grad(degree, x, y, z, w):
    """``sum_k w[k] dY_k / d(x, y, z)`` at the direction (x, y, z): :func:`_sh_basis`' derivatives contracted
    with the weights ``w`` [16] (each basis function's coefficient gradient), without the [16, 3] table."""
    g0 = g1 = g2 = 0.0
    if degree >= 1:
        g0 -= _C1 * w[3]
        g1 -= _C1 * w[1]
        g2 += _C1 * w[2]
    if degree >= 2:
        g0 += _C2[0] * y * w[4] - 2.0 * _C2[2] * x * w[6] + _C2[3] * z * w[7] + 2.0 * _C2[4] * x * w[8]
        g1 += _C2[0] * x * w[4] + _C2[1] * z * w[5] - 2.0 * _C2[2] * y * w[6] - 2.0 * _C2[4] * y * w[8]
        g2 += _C2[1] * y * w[5] + 4.0 * _C2[2] * z * w[6] + _C2[3] * x * w[7]
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        g0 += (_C3[0] * 6.0 * x * y * w[9] + _C3[1] * y * z * w[10] - 2.0 * _C3[2] * x * y * w[11]
               - 6.0 * _C3[3] * x * z * w[12] + _C3[4] * (4.0 * zz - 3.0 * xx - yy) * w[13]
               + 2.0 * _C3[5] * x * z * w[14] + _C3[6] * (3.0 * xx - 3.0 * yy) * w[15])
        g1 += (_C3[0] * (3.0 * xx - 3.0 * yy) * w[9] + _C3[1] * x * z * w[10]
               + _C3[2] * (4.0 * zz - xx - 3.0 * yy) * w[11] - 6.0 * _C3[3] * y * z * w[12]
               - 2.0 * _C3[4] * x * y * w[13] - 2.0 * _C3[5] * y * z * w[14] - 6.0 * _C3[6] * x * y * w[15])
        g2 += (_C3[1] * x * y * w[10] + 8.0 * _C3[2] * y * z * w[11] + _C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * w[12]
               + 8.0 * _C3[4] * x * z * w[13] + _C3[5] * (xx - yy) * w[14])
    return g0, g1, g2


@_ifjit
def _sh3_backward_one(D, iu, g, culled, cg, r0v, r1v, r2v, fd, fr, fvd, fvr, od, r, v_means):
    """:func:`sh_backward` of Gaussian g at degree 3, one camera: its direction ``D[:, iu]`` (x, y, z, norm), its
    coefficient rows at ``od`` / ``r`` of the flat ``fd`` / ``fr`` (the gradients into the same places of ``fvd`` /
    ``fvr``, each coefficient's three as one 4-lane store whose fourth lane the next store overwrites). The weights
    ``c_k . v`` four coefficients at a time (:func:`_v4_dot4`), the coefficients' gradients ``b_k v`` as lanes, the
    direction's gradient in scalar code on the weights held in registers (no [16] array)."""
    if culled:
        zero = _v4_splat(0.0)
        _v3_store(fvd, od, zero)
        for k in range(14):
            _v4_store(fvr, r + np.uintp(3 * k), zero)
        _v3_store(fvr, r + np.uintp(42), zero)
        v_means[g, 0] = v_means[g, 1] = v_means[g, 2] = 0.0
        return
    x, y, z, nrm = D[0, iu], D[1, iu], D[2, iu], D[3, iu]
    v0 = float(r0v) if not cg & 1 else 0.0
    v1 = float(r1v) if not cg & 2 else 0.0
    v2 = float(r2v) if not cg & 4 else 0.0
    v = _v4_set(v0, v1, v2)
    w0 = _v4_dot4(_v3_load(fd, od), _v4_load(fr, r), _v4_load(fr, r + np.uintp(3)), _v4_load(fr, r + np.uintp(6)), v)
    w1 = _v4_dot4(_v4_load(fr, r + np.uintp(9)), _v4_load(fr, r + np.uintp(12)), _v4_load(fr, r + np.uintp(15)),
                  _v4_load(fr, r + np.uintp(18)), v)
    w2 = _v4_dot4(_v4_load(fr, r + np.uintp(21)), _v4_load(fr, r + np.uintp(24)), _v4_load(fr, r + np.uintp(27)),
                  _v4_load(fr, r + np.uintp(30)), v)
    w3 = _v4_dot4(_v4_load(fr, r + np.uintp(33)), _v4_load(fr, r + np.uintp(36)), _v4_load(fr, r + np.uintp(39)),
                  _v3_load(fr, r + np.uintp(42)), v)
    b = _sh3_basis(x, y, z)
    _v3_store(fvd, od, _v4_mul(_v4_splat(b[0]), v))
    _v4_store(fvr, r, _v4_mul(_v4_splat(b[1]), v))
    _v4_store(fvr, r + np.uintp(3), _v4_mul(_v4_splat(b[2]), v))
    _v4_store(fvr, r + np.uintp(6), _v4_mul(_v4_splat(b[3]), v))
    _v4_store(fvr, r + np.uintp(9), _v4_mul(_v4_splat(b[4]), v))
    _v4_store(fvr, r + np.uintp(12), _v4_mul(_v4_splat(b[5]), v))
    _v4_store(fvr, r + np.uintp(15), _v4_mul(_v4_splat(b[6]), v))
    _v4_store(fvr, r + np.uintp(18), _v4_mul(_v4_splat(b[7]), v))
    _v4_store(fvr, r + np.uintp(21), _v4_mul(_v4_splat(b[8]), v))
    _v4_store(fvr, r + np.uintp(24), _v4_mul(_v4_splat(b[9]), v))
    _v4_store(fvr, r + np.uintp(27), _v4_mul(_v4_splat(b[10]), v))
    _v4_store(fvr, r + np.uintp(30), _v4_mul(_v4_splat(b[11]), v))
    _v4_store(fvr, r + np.uintp(33), _v4_mul(_v4_splat(b[12]), v))
    _v4_store(fvr, r + np.uintp(36), _v4_mul(_v4_splat(b[13]), v))
    _v4_store(fvr, r + np.uintp(39), _v4_mul(_v4_splat(b[14]), v))
    _v3_store(fvr, r + np.uintp(42), _v4_mul(_v4_splat(b[15]), v))
    w = (_v4_get(w0, 0), _v4_get(w0, 1), _v4_get(w0, 2), _v4_get(w0, 3), _v4_get(w1, 0), _v4_get(w1, 1),
         _v4_get(w1, 2), _v4_get(w1, 3), _v4_get(w2, 0), _v4_get(w2, 1), _v4_get(w2, 2), _v4_get(w2, 3),
         _v4_get(w3, 0), _v4_get(w3, 1), _v4_get(w3, 2), _v4_get(w3, 3))
    vd0, vd1, vd2 = _sh_dir_grad(3, x, y, z, w)
    dot = x * vd0 + y * vd1 + z * vd2
    v_means[g, 0] = 0.0 + (vd0 - x * dot) / nrm
    v_means[g, 1] = 0.0 + (vd1 - y * dot) / nrm
    v_means[g, 2] = 0.0 + (vd2 - z * dot) / nrm


@_pfjit
def sh_backward(degree, means, campos, dc, rest, r0, radii, cut, v_rgb, v_means, v_dc, v_rest):
    """Gradients of :func:`sh_forward` into ``v_means`` [N, 3] and the coefficients' rows ``v_dc`` and ``v_rest``
    (laid out as ``dc`` and ``rest``, the same ``r0``; every coefficient written) (cameras summed in order, in
    float64, whatever the dtype of the coefficients and their gradients; the clamp passes the gradient where its
    input is >= 0, as ``torch.clamp_min``: where :func:`sh_forward`'s ``cut`` bit is not set, so the sums are not
    made again). The direction's gradient contracts the basis derivatives with each basis function's coefficient
    gradient (:func:`_sh_dir_grad`) instead of a [16, 3] table per pair. ``v_rgb``'s first three columns are read
    (any strides). With ``radii`` rows (:func:`sh_forward`'s): a camera where the Gaussian was culled adds nothing
    (its colour was never composited: the compositing gives it a zero gradient, which would add zeros), so a
    Gaussian culled everywhere gets zeros. Degree 3 with one camera (a fit's renders) and no coefficients above it:
    :func:`_sh3_backward_one` in SIMD lanes (4.5 -> 3.2 ms at 100k, one thread). (Unrolled like :func:`sh_forward`'s
    degree 3 with scalar code it ran slower: 5.1 -> 5.5 ms. The means' gradient in a vectorised loop over the chunk
    after the weights, kept [16, chunk]: 3.5 ms, 7.0 ms with the rows 4 KiB apart, 3.8 ms in blocks of 64, against
    3.2 inline; the degree-3 direction gradient gathered by monomial: 3.34 vs 3.25 ms.)"""
    n_cam, n = campos.shape[0], means.shape[0]
    nb = (degree + 1) * (degree + 1)
    n_k = (v_rest.shape[1] - r0) // 3 + 1
    culls = radii.shape[0] > 0
    one_cam = n_cam == 1  # one camera (a fit's renders): no float64 sums over cameras to keep
    if degree == 3 and one_cam and n_k == 16:
        fd, fr = dc.reshape(-1), rest.reshape(-1)
        fvd, fvr = v_dc.reshape(-1), v_rest.reshape(-1)
        sd, sr = np.uintp(dc.shape[1]), np.uintp(rest.shape[1])
        for ch in numba.prange((n + CHUNK - 1) // CHUNK):
            D = np.empty((4, CHUNK))
            g0, g1 = ch * CHUNK, min((ch + 1) * CHUNK, n)
            _unit_dirs(means, campos, 0, g0, g1 - g0, D)
            for g in range(g0, g1):
                gu = np.uintp(g)
                _sh3_backward_one(D, np.uintp(g - g0), gu, culls and radii[0, g] == 0, cut[0, g], v_rgb[0, g, 0],
                                  v_rgb[0, g, 1], v_rgb[0, g, 2], fd, fr, fvd, fvr, gu * sd, gu * sr + r0, v_means)
        return
    for ch in numba.prange((n + CHUNK - 1) // CHUNK):
        b, db, w = np.empty(16), np.empty((0, 3)), np.zeros(16)
        vco = np.empty((n_k, 3))
        for g in range(ch * CHUNK, min((ch + 1) * CHUNK, n)):
            if not one_cam:
                for k in range(n_k):
                    vco[k, 0] = vco[k, 1] = vco[k, 2] = 0.0
            vm0 = vm1 = vm2 = 0.0  # float64 sums over the cameras, written once in the output's dtype
            for c in range(n_cam):
                if culls and radii[c, g] == 0:
                    if one_cam:
                        for k in range(nb):
                            _set_coef(v_dc, v_rest, r0, g, k, 0.0, 0.0, 0.0)
                    continue
                x, y, z, nrm = _unit_dir(means, campos, c, g)
                _sh_basis(degree, x, y, z, b, db)
                cg = cut[c, g]
                v0 = float(v_rgb[c, g, 0]) if not cg & 1 else 0.0
                v1 = float(v_rgb[c, g, 1]) if not cg & 2 else 0.0
                v2 = float(v_rgb[c, g, 2]) if not cg & 4 else 0.0
                # each coefficient's weight first, the gradients after: reading the coefficients in a loop of its
                # own, not between the gradients' stores (which may alias them for all LLVM knows), ran 5.06 -> 4.7
                # ms at 100k, one thread
                for k in range(nb):
                    w[k] = (_coef(dc, rest, r0, g, k, 0) * v0 + _coef(dc, rest, r0, g, k, 1) * v1
                            + _coef(dc, rest, r0, g, k, 2) * v2)
                if one_cam:  # the coefficients' gradient written as it is made (the float64 sum from zero's value)
                    for k in range(nb):
                        bk = b[k]
                        _set_coef(v_dc, v_rest, r0, g, k, 0.0 + bk * v0, 0.0 + bk * v1, 0.0 + bk * v2)
                else:
                    for k in range(nb):
                        vco[k, 0] += b[k] * v0
                        vco[k, 1] += b[k] * v1
                        vco[k, 2] += b[k] * v2
                vd0, vd1, vd2 = _sh_dir_grad(degree, x, y, z, w)
                # through the normalisation d = r / |r|: (v - d (d . v)) / |r|
                dot = x * vd0 + y * vd1 + z * vd2
                vm0 += (vd0 - x * dot) / nrm
                vm1 += (vd1 - y * dot) / nrm
                vm2 += (vd2 - z * dot) / nrm
            v_means[g, 0], v_means[g, 1], v_means[g, 2] = vm0, vm1, vm2
            if one_cam:
                for k in range(nb, n_k):  # coefficients above the degree: zero gradient
                    _set_coef(v_dc, v_rest, r0, g, k, 0.0, 0.0, 0.0)
            else:
                for k in range(n_k):
                    _set_coef(v_dc, v_rest, r0, g, k, vco[k, 0], vco[k, 1], vco[k, 2])


# --------------------------------------------------------------------------------------------------
# Density control's statistics (models.gaussians.densify.DefaultStrategy, on the CPU)
# --------------------------------------------------------------------------------------------------
@intrinsic
def _fma_f32(typingctx, a, b, c):
    """``a * b + c`` in float32, rounded once (llvm.fma.f32)."""
    if not all(t == types.float32 for t in (a, b, c)):
        return None

    def codegen(context, builder, sig, args):
        return builder.call(_llvm_fma(builder, ir.FloatType(), "f32"), args)

    return types.float32(types.float32, types.float32, types.float32), codegen


@_jit
def accumulate_grad2d(grads, radii, sx, sy, grad2d, count):
    """``grad2d[g] += sum_c |(grads[c, g, 0] * sx, grads[c, g, 1] * sy)|`` over the cameras where
    ``radii[c, g] > 0`` and ``count[g] +=`` their number: the strategy's torch ops (scale, norm, mask, sum over
    cameras, add in float64) in one pass, in their precision, bit for bit: float32 ``grads``, ``sx``, ``sy`` (the
    norm as torch's, ``sqrt(fma(y, y, x * x))``), float64 sums (one pass over 50k Gaussians: ~0.09 ms against
    ~1 ms for ten torch ops, each waking torch's threads)."""
    n_cam, n = radii.shape
    for g in range(n):
        s = np.float32(0.0)
        k = 0
        for c in range(n_cam):
            if radii[c, g] > 0:
                x = grads[c, g, 0] * sx
                y = grads[c, g, 1] * sy
                s += np.sqrt(_fma_f32(y, y, x * x))
                k += 1
        grad2d[g] += float(s)
        count[g] += k


# --------------------------------------------------------------------------------------------------
# The fit's loss terms (models.gaussians.train, on the CPU): L1 on colour, L1 in inverse depth
# --------------------------------------------------------------------------------------------------
@_ijit
def _sgn32(x):
    """torch.sgn of a float32: 1, -1, or 0 (and NaN for NaN)."""
    if x > 0:
        return np.float32(1.0)
    if x < 0:
        return np.float32(-1.0)
    return x * np.float32(0.0)


@_jit
def l1_inverse_depth_forward(rgb, image, depth, ref, alpha, alpha_min, d_min):
    """(sum |rgb - image|, sum over the mask of |1 / max(depth, d_min) - 1 / ref|, the mask's pixel count), the
    mask ``ref > 0 and alpha > alpha_min``; float32 in, the sums in float64 (``ref`` empty: no depth term)."""
    h, w = rgb.shape[0], rgb.shape[1]
    s = 0.0
    for y in range(h):
        for x in range(w):
            for k in range(3):
                s += abs(rgb[y, x, k] - image[y, x, k])
    sd = 0.0
    n = 0
    if ref.shape[0] > 0:
        one = np.float32(1.0)
        for y in range(h):
            for x in range(w):
                r = ref[y, x]
                if r > 0 and alpha[y, x] > alpha_min:
                    sd += abs(one / max(depth[y, x], d_min) - one / r)
                    n += 1
    return s, sd, n


@_jit
def l1_inverse_depth_backward(rgb, image, depth, ref, alpha, alpha_min, d_min, n, g_rgb, g_depth, v_rgb, v_depth):
    """The gradients of :func:`l1_inverse_depth_forward`'s terms as means (``g_rgb`` / ``g_depth``: the upstream
    gradients of the two means, float32; ``n``: the forward's mask count), as torch's autograd makes them op by op,
    bit for bit: mean ``g / n``, abs ``* sgn``, reciprocal ``-g * (r * r)``, clamp ``d >= d_min``, the masked
    pixels' scatter ``0 + g``."""
    h, w = rgb.shape[0], rgb.shape[1]
    gm = g_rgb / np.float32(h * w * 3)
    for y in range(h):
        for x in range(w):
            for k in range(3):
                v_rgb[y, x, k] = gm * _sgn32(rgb[y, x, k] - image[y, x, k])
    v_depth[:] = 0.0
    if ref.shape[0] == 0 or n == 0:
        return
    gd = g_depth / np.float32(n)
    one = np.float32(1.0)
    for y in range(h):
        for x in range(w):
            r = ref[y, x]
            if r > 0 and alpha[y, x] > alpha_min:
                d = depth[y, x]
                inv = one / max(d, d_min)
                g = gd * _sgn32(inv - one / r)
                g = -g * (inv * inv)
                v_depth[y, x] = np.float32(0.0) + (g if d >= d_min else np.float32(0.0))

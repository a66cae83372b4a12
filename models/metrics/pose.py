"""Camera-guidance precision: recover the camera path of a (generated) video with COLMAP and compare
it with the requested one (the paper's RotErr / TransErr, as introduced by CameraCtrl).

**Pose recovery** (:func:`recover_poses`) runs COLMAP's sparse structure-from-motion through pycolmap:

1. the frames are written as PNGs to ``workdir/images`` (``frame_00000.png`` ...);
2. ``pycolmap.extract_features`` computes SIFT features on the CPU into ``workdir/database.db``;
3. features are matched. Short clips (``<= EXHAUSTIVE_MAX_FRAMES`` frames, which covers the 14- and
   25-frame clips of video diffusion models) use **exhaustive** matching: every pair is tried, so
   wide-baseline pairs (first vs. last frame) are available to the mapper's initialisation and to
   triangulation, and the cost is negligible (25 frames = 300 pairs). Longer videos use COLMAP's
   **sequential** matcher (each frame against the next ``overlap`` frames, plus quadratically spaced
   ones), which is COLMAP's recommended mode for ordered video frames;
4. ``pycolmap.incremental_mapping`` reconstructs; when it yields several models, the one with the most
   registered images is used.

Intrinsics: with a known ``K`` the frames share one COLMAP ``PINHOLE`` camera (``fx, fy, cx, cy``) and
bundle adjustment does not refine it (no focal, principal-point or extra-parameter refinement, neither
in bundle adjustment nor in absolute-pose registration). Without ``K`` the frames share one
``SIMPLE_RADIAL`` camera (``f, cx, cy, k``) initialised by COLMAP from the image size
(focal = 1.2 x max(W, H)) and refined by bundle adjustment. COLMAP's pixel convention (pixel centre at
``+0.5``) is navcrafter's, so ``K`` is passed unchanged.

COLMAP stores world-to-camera poses (``Image.cam_from_world()``, a ``Rigid3d``; in pycolmap 4.x it is a
*method*, because an image's pose is derived from its frame/rig) in the OpenCV camera convention (x right,
y down, z forward), the same camera axes as navcrafter; :func:`recover_poses` inverts them to
camera-to-world. The reconstruction's world frame and scale are arbitrary (gauge freedom), which is why
the metrics below are computed relative to the first frame and with the translation scale normalised.

Failure is a result, not an exception: if COLMAP finds no reconstruction, :func:`recover_poses` returns
zero registered frames and a ``reason``.

**Pose errors** (:func:`pose_errors`) follow CameraCtrl (He et al., 2024), adopted by NavCrafter
("align to the first frame, normalise the scale"):

* both trajectories are expressed relative to their first frame, ``P_i = c2w_0^{-1} c2w_i``
  (if frame 0 is not registered, the first *registered* frame is the reference, for both trajectories);
* the translation scale is normalised, by one of two documented modes (``scale=``):

  - ``"lstsq"`` (default): the estimated relative camera centres ``t_est_i`` are scaled by the
    least-squares factor ``s = sum_i <t_gt_i, t_est_i> / sum_i |t_est_i|^2`` that best fits them to the
    requested ones; errors are in the requested trajectory's units (metres in simulation);
  - ``"farthest"``: each trajectory is divided by the distance from its reference camera to its
    farthest camera, so both have unit extent; errors are then unitless fractions of the extent;

* ``RotErr = sum_i arccos((tr(R_est_i R_gt_i^T) - 1) / 2)``, reported in **degrees** (``R_err_deg_sum``,
  ``R_err_deg_mean``) and, for comparison with CameraCtrl's tables, which sum radians, also in radians
  (``R_err_rad_sum``);
* ``TransErr = sum_i |t_gt_i - t_est_i|_2`` (``T_err_sum``, ``T_err_mean``).

Sums run over the registered frames (the reference frame contributes 0); means divide by the number of
registered frames other than the reference. Unregistered frames are excluded and counted
(``n_registered`` of ``n_frames``); as the sums depend on how many frames registered, compare sums only
at equal ``n_registered`` and prefer the means otherwise.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from navcrafter.models.camera.cameras import invert_pose

EXHAUSTIVE_MAX_FRAMES = 25
ScaleMode = Literal["lstsq", "farthest"]
MatcherMode = Literal["auto", "exhaustive", "sequential"]


@dataclass
class PoseRecovery:
    """Camera-to-world poses recovered by COLMAP for each input frame (NaN where not registered)."""

    c2w: np.ndarray  # [N, 4, 4] OpenCV camera-to-world in the reconstruction's (arbitrary) frame and scale
    registered: np.ndarray  # [N] bool
    n_frames: int
    n_registered: int
    n_reconstructions: int = 0
    n_points3d: int = 0
    mean_reprojection_error: float = float("nan")  # pixels
    camera_model: str = ""
    camera_params: list[float] = field(default_factory=list)  # COLMAP's parameters of the shared camera
    matcher: str = ""
    reason: str = ""  # empty on success; otherwise why frames (or all of them) did not register

    def to_dict(self) -> dict:
        return {"n_frames": self.n_frames, "n_registered": self.n_registered,
                "registered": self.registered.tolist(), "n_reconstructions": self.n_reconstructions,
                "n_points3d": self.n_points3d, "mean_reprojection_error": self.mean_reprojection_error,
                "camera_model": self.camera_model, "camera_params": list(self.camera_params),
                "matcher": self.matcher, "reason": self.reason}


def _failed(n: int, reason: str, **kw) -> PoseRecovery:
    return PoseRecovery(np.full((n, 4, 4), np.nan), np.zeros(n, dtype=bool), n, 0, reason=reason, **kw)


def _write_frames(frames: Sequence[np.ndarray] | np.ndarray, folder: Path) -> list[str]:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, frame in enumerate(frames):
        a = np.asarray(frame)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"frame {i}: expected an HxWx3 image, got shape {a.shape}")
        if a.dtype != np.uint8:
            raise ValueError(f"frame {i}: expected uint8, got {a.dtype}")
        name = f"frame_{i:05d}.png"
        Image.fromarray(a).save(folder / name)
        names.append(name)
    return names


def recover_poses(frames: Sequence[np.ndarray] | np.ndarray, K: np.ndarray | None, workdir: str | Path, *,
                  matcher: MatcherMode = "auto", num_threads: int = -1, seed: int = 0,
                  min_model_size: int = 3, max_num_features: int = 8192, quiet: bool = True) -> PoseRecovery:
    """Recover per-frame camera-to-world poses of ``frames`` (``HxWx3`` uint8) with COLMAP.

    ``K``: the frames' shared 3x3 intrinsics (kept fixed), or ``None`` to let COLMAP estimate a shared
    ``SIMPLE_RADIAL`` camera. ``workdir`` is (re)populated with ``images/``, ``database.db`` and
    ``sparse/``; previous contents of those three are removed. ``matcher="auto"`` is exhaustive up to
    ``EXHAUSTIVE_MAX_FRAMES`` frames and sequential beyond. ``num_threads=-1`` uses all cores.
    ``seed`` seeds COLMAP's RANSAC and mapper for repeatable results. Reconstructions with fewer than
    ``min_model_size`` registered images are discarded by COLMAP (its default, 10, would reject short
    clips). ``quiet`` hides COLMAP's INFO log lines (warnings and errors still show) while it runs.
    Never raises for a failed reconstruction: it returns zero registered frames and a reason.
    """
    import pycolmap

    level = pycolmap.logging.minloglevel
    if quiet:
        pycolmap.logging.minloglevel = max(level, int(pycolmap.logging.Level.WARNING.value))
    try:
        return _recover(frames, K, Path(workdir), matcher, num_threads, seed, min_model_size, max_num_features)
    finally:
        pycolmap.logging.minloglevel = level


def _recover(frames: Sequence[np.ndarray] | np.ndarray, K: np.ndarray | None, work: Path, matcher: MatcherMode,
             num_threads: int, seed: int, min_model_size: int, max_num_features: int) -> PoseRecovery:
    import pycolmap

    n = len(frames)
    if n == 0:
        return _failed(0, "no frames")
    if matcher == "auto":
        matcher = "exhaustive" if n <= EXHAUSTIVE_MAX_FRAMES else "sequential"
    if matcher not in ("exhaustive", "sequential"):
        raise ValueError(f"unknown matcher {matcher!r}; use 'auto', 'exhaustive' or 'sequential'")
    image_dir, database, sparse = work / "images", work / "database.db", work / "sparse"
    for p in (image_dir, sparse):
        if p.exists():
            shutil.rmtree(p)
    database.unlink(missing_ok=True)  # COLMAP appends to an existing database: start clean
    sparse.mkdir(parents=True)
    names = _write_frames(frames, image_dir)
    index = {name: i for i, name in enumerate(names)}

    pycolmap.set_random_seed(seed)
    reader = pycolmap.ImageReaderOptions()
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got {K.shape}")
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    else:
        reader.camera_model = "SIMPLE_RADIAL"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = max_num_features
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.num_threads = num_threads
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.min_model_size = min(min_model_size, n)
    opts.extract_colors = False
    if K is not None:  # known intrinsics: keep them fixed
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    info = {"matcher": matcher, "camera_model": reader.camera_model}
    try:
        recs = pycolmap.incremental_mapping(database, image_dir, sparse, options=opts)
    except Exception as e:  # a failed reconstruction is a result, not an error
        return _failed(n, f"COLMAP incremental mapping failed: {type(e).__name__}: {e}", **info)
    if not recs:
        return _failed(n, "COLMAP found no reconstruction (too few matches or too little parallax)", **info)
    rec = max(recs.values(), key=lambda r: r.num_reg_images())

    c2w = np.full((n, 4, 4), np.nan)
    registered = np.zeros(n, dtype=bool)
    for image in rec.images.values():
        i = index.get(image.name)
        if i is None or not image.has_pose:
            continue
        w2c = np.eye(4)
        w2c[:3, :] = image.cam_from_world().matrix()
        c2w[i] = invert_pose(w2c)
        registered[i] = True
    camera = next(iter(rec.cameras.values()))
    k = int(registered.sum())
    reason = "" if k == n else f"{n - k} of {n} frames not registered"
    if k == 0:
        reason = "the reconstruction registered no input frame"
    return PoseRecovery(c2w, registered, n, k, n_reconstructions=len(recs), n_points3d=rec.num_points3D(),
                        mean_reprojection_error=float(rec.compute_mean_reprojection_error()),
                        camera_model=camera.model.name, camera_params=[float(v) for v in camera.params],
                        matcher=matcher, reason=reason)


def _relative(c2w: np.ndarray, ref: int) -> np.ndarray:
    return np.einsum("ij,njk->nik", invert_pose(c2w[ref]), c2w)


def pose_errors(est_c2w: np.ndarray, gt_c2w: np.ndarray, registered: np.ndarray | None = None, *,
                scale: ScaleMode = "lstsq") -> dict:
    """CameraCtrl-style rotation / translation errors between estimated and requested trajectories.

    ``est_c2w`` and ``gt_c2w``: ``[N, 4, 4]`` camera-to-world poses (any world frames and, for
    ``est_c2w``, any scale); ``registered``: ``[N]`` bool (default: frames with finite estimates).
    See the module docstring for the definitions. Returns a dict with ``R_err_deg_sum``,
    ``R_err_deg_mean``, ``R_err_rad_sum``, ``T_err_sum``, ``T_err_mean``, ``n_registered``, ``n_frames``,
    ``ref_index``, ``scale_mode``, ``scale`` (the factor applied to the estimate, or the pair of extents
    for ``"farthest"``), ``gt_extent`` and per-frame ``R_err_deg`` / ``T_err`` lists (NaN where
    unregistered). With fewer than two registered frames the errors are NaN and ``reason`` says why.
    """
    est = np.asarray(est_c2w, dtype=np.float64)
    gt = np.asarray(gt_c2w, dtype=np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"need two [N,4,4] trajectories of equal length, got {est.shape} and {gt.shape}")
    if scale not in ("lstsq", "farthest"):
        raise ValueError(f"unknown scale mode {scale!r}; use 'lstsq' or 'farthest'")
    n = len(est)
    finite = np.isfinite(est).all(axis=(1, 2))
    reg = finite if registered is None else np.asarray(registered, dtype=bool) & finite
    out: dict = {"n_frames": n, "n_registered": int(reg.sum()), "scale_mode": scale, "rotation_unit": "deg",
                 "R_err_deg_sum": float("nan"), "R_err_deg_mean": float("nan"), "R_err_rad_sum": float("nan"),
                 "T_err_sum": float("nan"), "T_err_mean": float("nan"), "ref_index": None, "scale": None,
                 "gt_extent": float("nan"), "R_err_deg": [float("nan")] * n, "T_err": [float("nan")] * n,
                 "reason": ""}
    idx = np.flatnonzero(reg)
    if len(idx) < 2:
        out["reason"] = f"{len(idx)} registered frame(s): need at least 2 to compare trajectories"
        if len(idx) == 1:
            out["ref_index"] = int(idx[0])
        return out
    ref = int(idx[0])
    rel_est = _relative(est[idx], 0)
    rel_gt = _relative(gt[idx], 0)
    t_est, t_gt = rel_est[:, :3, 3], rel_gt[:, :3, 3]
    ext_gt = float(np.linalg.norm(t_gt, axis=1).max())
    if scale == "lstsq":
        den = float((t_est**2).sum())
        s = float((t_gt * t_est).sum() / den) if den > 1e-18 else 0.0
        t_est = s * t_est
        scale_out: float | list[float] = s
    else:
        ext_est = float(np.linalg.norm(t_est, axis=1).max())
        t_est = t_est / ext_est if ext_est > 1e-12 else t_est
        t_gt = t_gt / ext_gt if ext_gt > 1e-12 else t_gt
        scale_out = [ext_est, ext_gt]
    R_rel = np.einsum("nij,nkj->nik", rel_est[:, :3, :3], rel_gt[:, :3, :3])  # R_est R_gt^T
    # arccos((tr - 1) / 2), evaluated as atan2(sin, cos): the same angle, but accurate near 0 where
    # arccos loses half the digits (1e-8 rad of noise for identical rotations)
    cos = (np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0
    skew = R_rel - np.swapaxes(R_rel, 1, 2)
    sin = 0.5 * np.linalg.norm(np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1), axis=1)
    r_rad = np.arctan2(sin, cos)
    t_err = np.linalg.norm(t_gt - t_est, axis=1)
    r_deg_all = np.full(n, np.nan)
    t_all = np.full(n, np.nan)
    r_deg_all[idx] = np.rad2deg(r_rad)
    t_all[idx] = t_err
    m = len(idx) - 1
    out.update({"R_err_deg_sum": float(np.rad2deg(r_rad).sum()), "R_err_deg_mean": float(np.rad2deg(r_rad).sum() / m),
                "R_err_rad_sum": float(r_rad.sum()), "T_err_sum": float(t_err.sum()),
                "T_err_mean": float(t_err.sum() / m), "ref_index": ref, "scale": scale_out, "gt_extent": ext_gt,
                "R_err_deg": r_deg_all.tolist(), "T_err": t_all.tolist()})
    return out


def camera_guidance_precision(frames: Sequence[np.ndarray] | np.ndarray, requested_c2w: np.ndarray,
                              K: np.ndarray | None, workdir: str | Path, *, scale: ScaleMode = "lstsq",
                              **recover_kwargs) -> dict:
    """Recover the camera path of ``frames`` with COLMAP and compare it with ``requested_c2w``.

    Returns :func:`pose_errors`' dict plus ``"recovery"`` (:meth:`PoseRecovery.to_dict`) and
    ``"reason"`` (empty on success; why COLMAP or the comparison failed, or how many frames were lost).
    ``recover_kwargs`` go to :func:`recover_poses`.
    """
    requested = np.asarray(requested_c2w, dtype=np.float64)
    if len(requested) != len(frames):
        raise ValueError(f"{len(frames)} frames but {len(requested)} requested poses")
    rec = recover_poses(frames, K, workdir, **recover_kwargs)
    out = pose_errors(rec.c2w, requested, rec.registered, scale=scale)
    out["recovery"] = rec.to_dict()
    out["reason"] = "; ".join(r for r in (rec.reason, out["reason"]) if r)
    return out

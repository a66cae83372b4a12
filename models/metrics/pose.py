"""Camera-guidance precision: the camera path of a (generated) video, recovered by structure from motion
(:func:`~navcrafter.models.reconstruction.sfm.recover_poses`: COLMAP, its retry ladder and the rotation-only model;
see that module), compared with the requested one (the paper's RotErr / TransErr, as introduced by CameraCtrl).

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

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from navcrafter.models.camera.cameras import invert_pose
from navcrafter.models.reconstruction.sfm import Attempt, PoseRecovery, recover_poses

__all__ = ["Attempt", "PoseRecovery", "ScaleMode", "camera_guidance_precision", "pose_errors", "recover_poses"]

ScaleMode = Literal["lstsq", "farthest"]


def _relative(c2w: np.ndarray, ref: int) -> np.ndarray:
    return np.einsum("ij,njk->nik", invert_pose(c2w[ref]), c2w)


def pose_errors(est_c2w: np.ndarray, gt_c2w: np.ndarray, registered: np.ndarray | None = None, *,
                scale: ScaleMode = "lstsq") -> dict:
    """CameraCtrl-style rotation / translation errors between estimated and requested trajectories.

    ``est_c2w`` and ``gt_c2w``: ``[N, 4, 4]`` camera-to-world poses (any world frames and, for
    ``est_c2w``, any scale); ``registered``: ``[N]`` bool (default: frames with finite estimates).
    See the module docstring for the definitions. Returns a dict with ``R_err_deg_sum``,
    ``R_err_deg_mean``, ``R_err_rad_sum``, ``R_err_rad_mean``, ``T_err_sum``, ``T_err_mean``, ``n_registered``,
    ``n_frames``,
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
                 "R_err_rad_mean": float("nan"),
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
                "R_err_rad_sum": float(r_rad.sum()), "R_err_rad_mean": float(r_rad.sum() / m),
                "T_err_sum": float(t_err.sum()),
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

"""Camera files: the parsers of RealEstate10K pose files and nerfstudio ``transforms.json`` (the one parser of each
format; the dataset readers of schemas/datasets and the trajectory files of models/camera/trajectories use them).

Errors: a bad file raises ``DatasetError`` (a ``ValueError``) naming the file (and line) and the fix.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


class DatasetError(ValueError):
    """A dataset file or folder cannot be used; the message names it and says how to fix it."""


def _natural_key(s: str) -> list:
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", s)]


def _floats(tokens: Sequence[str], where: str) -> list[float]:
    try:
        out = [float(t) for t in tokens]
    except ValueError as e:
        raise DatasetError(f"{where}: expected numbers, got {' '.join(tokens)!r} ({e})") from None
    if not all(math.isfinite(v) for v in out):
        raise DatasetError(f"{where}: non-finite number in {' '.join(tokens)!r}")
    return out


def _check_rigid(T: np.ndarray, where: str, tol: float = 1e-2) -> None:
    R = T[:3, :3]
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DatasetError(f"{where}: last row of the pose is {T[3].tolist()}, expected [0, 0, 0, 1]")
    if np.abs(R.T @ R - np.eye(3)).max() > tol or np.linalg.det(R) < 0:
        raise DatasetError(f"{where}: the pose's 3x3 block is not a rotation (R^T R != I or det < 0); "
                           "the file is corrupt or not in the expected format")


def _read_lines(path: Path, what: str) -> list[str]:
    """The lines of a text file, or a ``DatasetError`` naming ``what`` and the file."""
    try:
        return path.read_text().splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"cannot read {what} {path}: {e}") from None


@dataclass
class RE10KCameras:
    url: str
    timestamps_us: np.ndarray   # [N] int64
    intrinsics: np.ndarray      # [N, 4] normalised fx, fy, cx, cy
    distortion: np.ndarray      # [N, 2]
    w2c: np.ndarray             # [N, 4, 4]

    def rows(self) -> np.ndarray:
        """The frame lines as numbers, ``[N, 19]``: timestamp, normalised fx fy cx cy, k1 k2, the 3x4
        world-to-camera matrix row-major (the rows VideoX-Fun's ``process_pose_params`` takes)."""
        return np.concatenate([self.timestamps_us[:, None].astype(np.float64), self.intrinsics, self.distortion,
                               self.w2c[:, :3, :].reshape(len(self.w2c), 12)], axis=1)


def read_re10k_cameras(path: str | Path) -> RE10KCameras:
    """Parse a RealEstate10K camera file (URL line, then 19 numbers per frame; see the module doc)."""
    path = Path(path)
    lines = _read_lines(path, "RealEstate10K camera file")
    if not lines or not lines[0].strip():
        raise DatasetError(f"{path}: empty file; a RealEstate10K camera file starts with the video URL line")
    url = lines[0].strip()
    first = url.split()
    if len(first) > 1 and re.fullmatch(r"[-+0-9.eE]+", first[0]):
        raise DatasetError(f"{path}:1: the first line should be the YouTube URL but holds numbers; "
                           "restore the URL line (the file may have been truncated or re-written)")
    ts, intr, dist, w2c = [], [], [], []
    for n, line in enumerate(lines[1:], start=2):
        tok = line.split()
        if not tok:
            continue
        where = f"{path}:{n}"
        if len(tok) != 19:
            raise DatasetError(f"{where}: expected 19 numbers (timestamp fx fy cx cy k1 k2 and a 3x4 "
                               f"world-to-camera matrix), got {len(tok)}; the line is malformed")
        try:
            t = int(tok[0])
        except ValueError:
            raise DatasetError(f"{where}: the timestamp {tok[0]!r} is not an integer (microseconds)") from None
        vals = _floats(tok[1:], where)
        if min(vals[0], vals[1]) <= 0:
            raise DatasetError(f"{where}: focal lengths must be positive, got fx={vals[0]}, fy={vals[1]}")
        T = np.eye(4)
        T[:3, :] = np.reshape(vals[6:], (3, 4))
        _check_rigid(T, where)
        ts.append(t)
        intr.append(vals[:4])
        dist.append(vals[4:6])
        w2c.append(T)
    if not ts:
        raise DatasetError(f"{path}: no frame lines after the URL line")
    ts_arr = np.asarray(ts, dtype=np.int64)
    if np.any(np.diff(ts_arr) <= 0):
        k = int(np.flatnonzero(np.diff(ts_arr) <= 0)[0])
        raise DatasetError(f"{path}: timestamps must increase, but line {k + 3} ({ts_arr[k + 1]}) follows "
                           f"{ts_arr[k]}; the file is corrupt")
    return RE10KCameras(url, ts_arr, np.asarray(intr), np.asarray(dist), np.stack(w2c))


@dataclass
class NerfstudioFrame:
    file_path: str
    c2w_gl: np.ndarray              # [4, 4] as stored (OpenGL camera axes)
    fx: float
    fy: float
    cx: float | None
    cy: float | None
    w: int | None
    h: int | None
    extra: dict[str, Any]


_NS_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_NS_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _frame_or_global(frame: dict, meta: dict) -> Callable[[str], Any]:
    return lambda k: frame.get(k, meta.get(k))


def read_nerfstudio_transforms(path: str | Path) -> tuple[list[NerfstudioFrame], dict[str, Any]]:
    """Parse a nerfstudio ``transforms.json``: frames sorted by ``file_path``, plus the top-level keys."""
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path} does not exist; each DL3DV scene needs a nerfstudio transforms.json") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: not valid JSON ({e}); re-download the scene's transforms.json") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DatasetError(f"{path}: no 'frames' list; a nerfstudio transforms.json has "
                           "'frames': [{'file_path': ..., 'transform_matrix': ...}, ...]")
    model = str(meta.get("camera_model", "OPENCV")).upper()
    if "FISHEYE" in model or "EQUIRECT" in model:
        raise DatasetError(f"{path}: camera_model {model} is not a pinhole model; undistort the images first")
    frames = []
    for i, fr in enumerate(meta["frames"]):
        where = f"{path}: frames[{i}]"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise DatasetError(f"{where}: needs 'file_path' and 'transform_matrix'")
        try:
            M = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise DatasetError(f"{where}: transform_matrix is not a numeric matrix") from None
        if M.shape == (3, 4):
            M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise DatasetError(f"{where}: transform_matrix must be a finite 4x4 (or 3x4) matrix, got shape {M.shape}")
        _check_rigid(M, where)
        get = _frame_or_global(fr, meta)
        fx = get("fl_x")
        if fx is None:
            raise DatasetError(f"{where}: no focal length 'fl_x' (neither per frame nor global)")
        fy = get("fl_y") if get("fl_y") is not None else fx
        try:
            fx, fy = float(fx), float(fy)
            cx = None if get("cx") is None else float(get("cx"))
            cy = None if get("cy") is None else float(get("cy"))
            w = None if get("w") is None else int(get("w"))
            h = None if get("h") is None else int(get("h"))
        except (TypeError, ValueError):
            raise DatasetError(f"{where}: intrinsics (fl_x, fl_y, cx, cy, w, h) must be numbers") from None
        if fx <= 0 or fy <= 0:
            raise DatasetError(f"{where}: focal lengths must be positive, got fl_x={fx}, fl_y={fy}")
        extra = {k: get(k) for k in _NS_DISTORTION_KEYS if get(k) is not None}
        frames.append(NerfstudioFrame(str(fr["file_path"]), M, fx, fy, cx, cy, w, h, extra))
    frames.sort(key=lambda f: _natural_key(f.file_path))
    top = {k: v for k, v in meta.items() if k != "frames"}
    return frames, top

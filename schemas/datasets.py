"""Readers for the public evaluation datasets: RealEstate10K, DL3DV (nerfstudio format), Tanks and Temples.

Every reader yields ``Sample`` clips in navcrafter's camera convention (see ``models/camera/cameras.py``):
**OpenCV camera-to-world** 4x4 poses (x right, y down, z forward) and **pixel** intrinsics of the frames
as returned (after resizing/cropping). One entry point: ``open_dataset(kind, root, **options)``.

Formats (as documented by the datasets) and the folder layouts expected here
============================================================================

**RealEstate10K** (``kind="re10k"``). The release is one camera file per video, ``<sequence>.txt``:
the first line is the YouTube URL, then one line per frame::

    timestamp_us fx fy cx cy k1 k2 r00 r01 r02 t0 r10 r11 r12 t1 r20 r21 r22 t2

``timestamp_us`` is the frame's time in the video (integer microseconds); ``fx, cx`` are normalised by
the image width and ``fy, cy`` by its height (so they hold for any extraction resolution); ``k1 k2``
are distortion terms (zero in the release; ignored here); the 12 numbers are the **world-to-camera**
3x4 matrix, row-major, OpenCV camera axes. The reader inverts it to camera-to-world and multiplies the
intrinsics by the size of the extracted frame. The images are not part of the release: users extract
them from the videos. Expected layout (``split=None`` drops the split level; ``cameras_dir`` and
``frames_dir`` override the two folders, ``frame_name`` the file stem)::

    <root>/<split>/<sequence>.txt                     camera file (cameras_dir = <root>/<split>)
    <root>/<split>/<sequence>/<timestamp_us>.png      one frame per line (frames_dir = <root>/<split>)
                                                      (.png, .jpg or .jpeg; frame_name="{timestamp}",
                                                      "{index}" = 0-based line number is also available)

Every line of the camera file must have its frame (``missing_frames="drop"`` drops lines without one).

**DL3DV** (``kind="dl3dv"``), nerfstudio format. Per scene, ``transforms.json``::

    {"w": 3840, "h": 2160, "fl_x": ..., "fl_y": ..., "cx": ..., "cy": ..., "k1": ..., "camera_model": "OPENCV",
     "frames": [{"file_path": "images/frame_00001.png", "transform_matrix": [[4 x 4]]}, ...]}

Intrinsics are in pixels of an image of ``w x h``, given globally and/or per frame (per-frame keys win;
``fl_y`` defaults to ``fl_x``, ``cx, cy`` to the image centre). ``transform_matrix`` is camera-to-world
in the **OpenGL/nerfstudio** camera convention (x right, y up, z backwards); the reader converts it to
OpenCV by flipping the camera's y and z axes (``c2w @ diag(1, -1, -1, 1)``). Distortion terms are
ignored (recorded in ``Sample.meta``). Frames are sorted by ``file_path`` (natural order), as nerfstudio
does. Image paths are relative to the json's folder. DL3DV's downscaled releases keep
``file_path = images/...`` and full-resolution intrinsics but ship the frames in ``images_4/`` (etc.):
pass ``images_dir="images_4"`` to replace the first folder of every ``file_path``; intrinsics are always
rescaled from ``w x h`` to the size of the image actually read. Expected layout::

    <root>/<scene>/transforms.json           (or <root>/<scene>/nerfstudio/transforms.json, as in
    <root>/<scene>/images[_4]/frame_00001.png  DL3DV-Benchmark); <root> itself may be one scene

**Tanks and Temples** (``kind="tnt"``). Camera poses in the TnT/Redwood trajectory ``.log`` format:
blocks of five lines, one metadata line of three integers (``id id frame``) and four lines holding a
4x4 **camera-to-world** matrix (OpenCV camera axes, as reconstructed by COLMAP)::

    0 0 0
    r00 r01 r02 t0
    r10 r11 r12 t1
    r20 r21 r22 t2
    0 0 0 1

The k-th block is the k-th image of the scene in natural file-name order (their counts must match).
The log holds no intrinsics: they come from ``intrinsics=`` (an ``Intrinsics`` for all scenes, or a
mapping scene -> ``Intrinsics``; its width/height say which image size it describes, and it is rescaled
to the images read), else from a COLMAP ``cameras.txt`` (``cameras_txt=`` or found at
``<scene>/cameras.txt``, ``<scene>/sparse/0/cameras.txt``, ``<scene>/sparse/cameras.txt``); with
neither, loading the scene raises a ``DatasetError`` naming the log and the fix. Expected layout::

    <root>/<scene>/<scene>_COLMAP_SfM.log    (any single *.log; with several, *_COLMAP_SfM.log, or log_name=)
    <root>/<scene>/images/000001.jpg          (images_dir="images"; images directly in <scene>/ also work)
    <root>/<scene>/sparse/0/cameras.txt       optional; <root> itself may be one scene

Sampling protocol (the paper's)
===============================
A clip is a conditioning frame and the ``num_frames`` (14) frames after it, every ``stride`` (1) frames:
``T = num_frames + 1`` frames at sequence indices ``start + stride * k``, ``k = 0..num_frames``. Frames are
resized (aspect ratio kept) to cover ``resolution`` = ``(height, width)`` and centre-cropped, with the
intrinsics adjusted exactly (``resize_center_crop``); ``resolution=None`` keeps the native frames.

``clips_per_dataset`` clips (``None``: one per sequence) are drawn deterministically from ``seed``: the
sequences are visited in a seeded permutation of their sorted names, each gives one clip per round (a
start drawn without replacement from its valid starts by a generator seeded with ``(seed, crc32(name))``,
so a sequence's clips do not depend on the other sequences), and rounds repeat until enough clips are
drawn or every sequence is exhausted (fewer clips are then yielded). ``start="first"`` conditions on each
sequence's first frame (one clip per sequence). The first ``n`` clips of a draw do not depend on
``clips_per_dataset`` beyond ``n``.

Errors: a bad file raises ``DatasetError`` naming the file (and line) and the fix when read directly
(``reader.sequence(name)``, ``reader.clip(name, start)``). Iterating a reader skips a bad sequence and
records why in ``reader.skipped`` (``{sequence: reason}``) unless ``strict=True``; if nothing at all can be
read, iteration raises with the reasons. Iteration is lazy: a sequence's metadata is parsed when first
visited and each ``Sample`` holds its decoded frames (uint8 arrays) only once it is yielded.
"""

from __future__ import annotations

import json
import math
import re
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from PIL import Image

from navcrafter.models.camera.cameras import Intrinsics

__all__ = [
    "DatasetError", "Sample", "SequenceInfo", "DatasetReader", "RealEstate10KReader", "DL3DVReader",
    "TanksAndTemplesReader", "open_dataset", "resize_center_crop", "read_re10k_cameras",
    "read_nerfstudio_transforms", "read_trajectory_log", "read_colmap_cameras", "opengl_to_opencv",
    "DATASET_KINDS",
]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
#: Right-multiplying a camera-to-world matrix by this flips the camera's y and z axes (OpenGL <-> OpenCV).
GL_CV_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
StartMode = Literal["random", "first"]


class DatasetError(ValueError):
    """A dataset file or folder cannot be used; the message names it and says how to fix it."""


# --------------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------------
@dataclass(eq=False)
class Sample:
    """One evaluation clip: a conditioning frame and the ground-truth frames after it.

    ``T = len(c2w)`` frames in all; index 0 is the conditioning frame.
    """

    dataset: str                      # "re10k" | "dl3dv" | "tnt"
    sequence: str                     # video id / scene name
    image: np.ndarray                 # [H, W, 3] uint8, the conditioning frame
    frames: np.ndarray                # [T-1, H, W, 3] uint8, the frames after it (decoded, not lazy)
    c2w: np.ndarray                   # [T, 4, 4] float64, OpenCV camera-to-world, dataset world frame
    K: np.ndarray                     # [T, 3, 3] float64, pixels of the returned frames
    frame_ids: list[str]              # [T] file stems (RE10K: the timestamps)
    indices: np.ndarray               # [T] int, positions of the frames in the sequence
    timestamps_us: np.ndarray | None  # [T] int64 video time in microseconds (RE10K), else None
    paths: list[Path]                 # [T] source image files
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        """All frames, conditioning frame included (``T``)."""
        return int(self.c2w.shape[0])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def start(self) -> int:
        return int(self.indices[0])

    @property
    def clip_id(self) -> str:
        """A stable name for the clip: ``<dataset>/<sequence>@<start>``."""
        return f"{self.dataset}/{self.sequence}@{self.start}"

    @property
    def images(self) -> np.ndarray:
        """All ``T`` frames ``[T, H, W, 3]``, the conditioning frame first."""
        return np.concatenate([self.image[None], self.frames], axis=0)

    def intrinsics(self, i: int = 0) -> Intrinsics:
        return Intrinsics.from_matrix(self.K[i], self.width, self.height)

    def relative_c2w(self) -> np.ndarray:
        """Poses in the conditioning camera's frame (``c2w[0]`` becomes the identity), navcrafter's
        scene convention. Units stay the dataset's (arbitrary scale for SfM-posed datasets)."""
        return np.linalg.inv(self.c2w[0]) @ self.c2w


@dataclass(eq=False)
class SequenceInfo:
    """Metadata of a whole sequence, frames not loaded. ``K`` is in pixels of an image of ``sizes[i]``
    (``(width, height)``); it is rescaled to the size of the image actually read."""

    name: str
    c2w: np.ndarray                   # [N, 4, 4] OpenCV camera-to-world
    K: np.ndarray                     # [N, 3, 3]
    sizes: np.ndarray                 # [N, 2] int (width, height) the intrinsics refer to
    paths: list[Path]                 # [N]
    frame_ids: list[str]              # [N]
    timestamps_us: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.paths)


# --------------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------------
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


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """OpenGL/nerfstudio camera-to-world (x right, y up, z back) -> OpenCV (x right, y down, z forward).

    Flips the camera's y and z axes: ``c2w @ diag(1, -1, -1, 1)`` (its own inverse). Batched.
    """
    return np.asarray(c2w, dtype=np.float64) @ GL_CV_FLIP


def _image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` from the image header."""
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except FileNotFoundError:
        raise DatasetError(f"image {path} does not exist") from None
    except Exception as e:  # PIL raises many types for bad files
        raise DatasetError(f"cannot read image {path} (corrupt or truncated?): {e}; re-extract or remove it") from None


def _read_image(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except FileNotFoundError:
        raise DatasetError(f"image {path} does not exist") from None
    except Exception as e:
        raise DatasetError(f"cannot read image {path} (corrupt or truncated?): {e}; re-extract or remove it") from None


def _read_lines(path: Path, what: str) -> list[str]:
    """The lines of a text file, or a ``DatasetError`` naming ``what`` and the file."""
    try:
        return path.read_text().splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"cannot read {what} {path}: {e}") from None


def _rescale_K(K: np.ndarray, size_from: tuple[int, int], size_to: tuple[int, int], where: str) -> np.ndarray:
    """Intrinsics of an image of ``size_from`` resampled (whole extent) to ``size_to`` (width, height)."""
    (w0, h0), (w1, h1) = size_from, size_to
    if (w0, h0) == (w1, h1):
        return np.asarray(K, dtype=np.float64).copy()
    # a downscaled copy keeps the aspect ratio up to rounding of its size
    if abs(h1 - h0 * w1 / w0) > 1.0 + 1e-6 and abs(w1 - w0 * h1 / h0) > 1.0 + 1e-6:
        raise DatasetError(f"{where}: the image is {w1}x{h1} but its intrinsics are for {w0}x{h0} (a different "
                           "aspect ratio); check that the image belongs to this camera file, or give intrinsics "
                           "for this image size")
    return Intrinsics.from_matrix(K, w0, h0).resize(w1, h1).K


def resize_center_crop(image: np.ndarray, K: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Scale ``image`` uniformly to cover ``height x width``, keep the centred part, adjust ``K``.

    With ``s = max(width / w, height / h)`` the kept source region is the centred box of
    ``(width / s) x (height / s)`` pixels, starting at pixel edge ``(x0, y0) = ((w - width/s) / 2,
    (h - height/s) / 2)`` (fractional in general); it is resampled (Lanczos) to ``width x height``. Hence
    ``fx' = s fx``, ``fy' = s fy``, ``cx' = s (cx - x0)``, ``cy' = s (cy - y0)``: a 3D point projects with the
    new ``K`` onto the same image content as before, and the image centre stays the centre.
    """
    h, w = image.shape[:2]
    s = max(width / w, height / h)
    bw, bh = width / s, height / s
    x0, y0 = (w - bw) / 2, (h - bh) / 2
    K = np.asarray(K, dtype=np.float64)
    K2 = np.array([[s * K[0, 0], s * K[0, 1], s * (K[0, 2] - x0)],
                   [0.0, s * K[1, 1], s * (K[1, 2] - y0)],
                   [0.0, 0.0, 1.0]])
    if (w, h) == (width, height):
        return np.ascontiguousarray(image, dtype=np.uint8), K2
    pil = Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8))
    pil = pil.resize((width, height), Image.Resampling.LANCZOS, box=(x0, y0, x0 + bw, y0 + bh))
    return np.asarray(pil, dtype=np.uint8), K2


# --------------------------------------------------------------------------------------------------
# File parsers
# --------------------------------------------------------------------------------------------------
@dataclass
class RE10KCameras:
    url: str
    timestamps_us: np.ndarray   # [N] int64
    intrinsics: np.ndarray      # [N, 4] normalised fx, fy, cx, cy
    distortion: np.ndarray      # [N, 2]
    w2c: np.ndarray             # [N, 4, 4]


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


def read_trajectory_log(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Parse a TnT/Redwood ``.log``: metadata ``[N, 3]`` int and camera-to-world ``[N, 4, 4]``."""
    path = Path(path)
    raw = _read_lines(path, "camera log")
    lines = [(n, ln.split()) for n, ln in enumerate(raw, start=1) if ln.strip()]
    if not lines:
        raise DatasetError(f"{path}: empty camera log")
    if len(lines) % 5:
        raise DatasetError(f"{path}: {len(lines)} non-empty lines is not a multiple of 5 (each camera is one "
                           "metadata line and 4 matrix lines); the file is truncated or malformed")
    ids, poses = [], []
    for b in range(0, len(lines), 5):
        n, head = lines[b]
        if len(head) != 3:
            raise DatasetError(f"{path}:{n}: expected a metadata line of 3 integers, got {' '.join(head)!r}")
        try:
            ids.append([int(x) for x in head])
        except ValueError:
            raise DatasetError(f"{path}:{n}: metadata line {' '.join(head)!r} is not 3 integers") from None
        rows = []
        for n, tok in lines[b + 1:b + 5]:
            if len(tok) != 4:
                raise DatasetError(f"{path}:{n}: expected 4 numbers of a 4x4 matrix row, got {len(tok)}")
            rows.append(_floats(tok, f"{path}:{n}"))
        T = np.asarray(rows)
        _check_rigid(T, f"{path}:{lines[b + 1][0]}")
        poses.append(T)
    return np.asarray(ids, dtype=np.int64), np.stack(poses)


# COLMAP camera models -> how to read fx, fy, cx, cy from PARAMS (and how many params there are)
_COLMAP_MODELS: dict[str, tuple[int, str]] = {
    "SIMPLE_PINHOLE": (3, "f"), "PINHOLE": (4, "fxfy"), "SIMPLE_RADIAL": (4, "f"), "RADIAL": (5, "f"),
    "OPENCV": (8, "fxfy"), "FULL_OPENCV": (12, "fxfy"),
}


def read_colmap_cameras(path: str | Path) -> dict[int, tuple[str, Intrinsics]]:
    """Parse COLMAP ``cameras.txt`` (``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``): id -> (model, pinhole part).

    Distortion parameters are dropped; fisheye models are refused. COLMAP's pixel convention (centre of
    the top-left pixel at (0.5, 0.5)) is navcrafter's, so ``cx, cy`` are used as they are.
    """
    path = Path(path)
    raw = _read_lines(path, "COLMAP cameras file")
    out: dict[int, tuple[str, Intrinsics]] = {}
    for n, line in enumerate(raw, start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        where = f"{path}:{n}"
        if len(tok) < 5:
            raise DatasetError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {line.strip()!r}")
        model = tok[1].upper()
        if model not in _COLMAP_MODELS:
            raise DatasetError(f"{where}: camera model {model} is not supported (pinhole-like models only: "
                               f"{', '.join(_COLMAP_MODELS)}); undistort the images with COLMAP first")
        nparams, kind = _COLMAP_MODELS[model]
        if len(tok) != 4 + nparams:
            raise DatasetError(f"{where}: model {model} has {nparams} parameters, got {len(tok) - 4}")
        try:
            cam_id, w, h = int(tok[0]), int(tok[2]), int(tok[3])
        except ValueError:
            raise DatasetError(f"{where}: CAMERA_ID, WIDTH and HEIGHT must be integers") from None
        p = _floats(tok[4:], where)
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if kind == "f" else (p[0], p[1], p[2], p[3])
        try:
            out[cam_id] = (model, Intrinsics(fx, fy, cx, cy, w, h))
        except ValueError as e:
            raise DatasetError(f"{where}: {e}") from None
    if not out:
        raise DatasetError(f"{path}: no camera lines")
    return out


# --------------------------------------------------------------------------------------------------
# Reader base: the sampling protocol
# --------------------------------------------------------------------------------------------------
class DatasetReader:
    """Base of the readers: sequence discovery and metadata are per format, the protocol is shared.

    Protocol options (all readers): ``num_frames`` frames after the conditioning frame (T = num_frames+1),
    ``stride`` between frames, ``clips_per_dataset`` (``None``: one clip per sequence), ``seed``,
    ``resolution`` (``int`` -> square, ``(height, width)``, or ``None`` for native frames), ``start``
    (``"random"`` or ``"first"``), ``sequences`` (only these names), ``strict`` (raise instead of skipping).
    """

    kind: ClassVar[str] = ""

    def __init__(self, root: str | Path, *, num_frames: int = 14, stride: int = 1,
                 clips_per_dataset: int | None = None, seed: int = 0,
                 resolution: int | tuple[int, int] | None = (256, 256), start: StartMode = "random",
                 sequences: Sequence[str] | None = None, strict: bool = False) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.kind} root {self.root} is not a folder")
        if num_frames < 1 or stride < 1:
            raise ValueError(f"num_frames and stride must be >= 1, got {num_frames}, {stride}")
        if clips_per_dataset is not None and clips_per_dataset < 1:
            raise ValueError(f"clips_per_dataset must be >= 1 or None, got {clips_per_dataset}")
        if start not in ("random", "first"):
            raise ValueError(f"start must be 'random' or 'first', got {start!r}")
        if isinstance(resolution, int):
            resolution = (resolution, resolution)
        if resolution is not None and (len(resolution) != 2 or min(resolution) < 1):
            raise ValueError(f"resolution must be (height, width) of positive ints or None, got {resolution}")
        self.num_frames = int(num_frames)
        self.stride = int(stride)
        self.clips_per_dataset = clips_per_dataset
        self.seed = int(seed)
        self.resolution = None if resolution is None else (int(resolution[0]), int(resolution[1]))
        self.start = start
        self.only = None if sequences is None else [str(s) for s in sequences]
        self.strict = strict
        self.skipped: dict[str, str] = {}
        self._cache: dict[str, SequenceInfo] = {}

    # ---- per format -------------------------------------------------------------------------------
    def _discover(self) -> list[str]:
        raise NotImplementedError

    def _load(self, name: str) -> SequenceInfo:
        raise NotImplementedError

    # ---- public -----------------------------------------------------------------------------------
    @property
    def clip_length(self) -> int:
        """Frames a clip spans in its sequence: ``1 + num_frames * stride``."""
        return 1 + self.num_frames * self.stride

    def sequence_names(self) -> list[str]:
        """All sequence names, sorted (natural order)."""
        names = sorted(self._discover(), key=_natural_key)
        if self.only is not None:
            missing = [s for s in self.only if s not in names]
            if missing:
                raise DatasetError(f"{self.kind} sequences not found under {self.root}: {', '.join(missing)}")
            names = [s for s in names if s in set(self.only)]
        return names

    def sequence(self, name: str) -> SequenceInfo:
        """Metadata of one sequence (cached); raises ``DatasetError`` for a bad one."""
        if name not in self._cache:
            self._cache[name] = self._load(name)
        return self._cache[name]

    def valid_starts(self, info: SequenceInfo) -> np.ndarray:
        n = len(info)
        if n < self.clip_length:
            raise DatasetError(f"{self.kind} sequence {info.name!r} has {n} frames but a clip needs "
                               f"{self.clip_length} (1 + num_frames={self.num_frames} x stride={self.stride}); "
                               "lower num_frames/stride or leave the sequence out")
        return np.arange(n - self.clip_length + 1)

    def starts_for(self, info: SequenceInfo) -> list[int]:
        """The sequence's clip starts in draw order (deterministic in ``seed`` and the name)."""
        valid = self.valid_starts(info)
        if self.start == "first":
            return [0]
        rng = np.random.default_rng([self.seed, zlib.crc32(info.name.encode())])
        return [int(s) for s in rng.permutation(valid)]

    def clip(self, sequence: str | SequenceInfo, start: int) -> Sample:
        """Load the clip of ``sequence`` conditioned on its frame ``start``."""
        info = self.sequence(sequence) if isinstance(sequence, str) else sequence
        idx = start + self.stride * np.arange(self.num_frames + 1)
        if start < 0 or idx[-1] >= len(info):
            raise DatasetError(f"{self.kind} sequence {info.name!r}: a clip from frame {start} needs frames "
                               f"{start}..{idx[-1]} but the sequence has {len(info)}")
        images, Ks = [], []
        for i in idx:
            img = _read_image(info.paths[i])
            size = (img.shape[1], img.shape[0])
            K = _rescale_K(info.K[i], tuple(info.sizes[i]), size, str(info.paths[i]))
            if self.resolution is not None:
                img, K = resize_center_crop(img, K, *self.resolution)
            images.append(img)
            Ks.append(K)
        shapes = {im.shape for im in images}
        if len(shapes) > 1:
            raise DatasetError(f"{self.kind} sequence {info.name!r}: frames of one clip differ in size {shapes}; "
                               "set a resolution to resize them")
        stack = np.stack(images)
        return Sample(
            dataset=self.kind, sequence=info.name, image=stack[0], frames=stack[1:],
            c2w=info.c2w[idx].copy(), K=np.stack(Ks), frame_ids=[info.frame_ids[i] for i in idx],
            indices=idx.astype(np.int64),
            timestamps_us=None if info.timestamps_us is None else info.timestamps_us[idx].copy(),
            paths=[info.paths[i] for i in idx],
            meta={**info.meta, "start": int(start), "stride": self.stride, "num_frames": self.num_frames},
        )

    def _order(self) -> list[str]:
        names = self.sequence_names()
        if not names:
            raise DatasetError(f"no {self.kind} sequences found under {self.root}; see the expected folder layout "
                               "in navcrafter.schemas.datasets")
        rng = np.random.default_rng(self.seed)
        return [names[i] for i in rng.permutation(len(names))]

    def _skip(self, name: str, err: DatasetError) -> None:
        if self.strict:
            raise err
        self.skipped[name] = str(err)

    def _candidates(self, bad: set[str]) -> Iterator[tuple[SequenceInfo, int]]:
        """(sequence, start) in draw order: round r takes each good sequence's r-th start."""
        good: list[tuple[SequenceInfo, list[int]]] = []
        for name in self._order():
            try:
                info = self.sequence(name)
                starts = self.starts_for(info)
            except DatasetError as e:
                self._skip(name, e)
                continue
            good.append((info, starts))
            yield info, starts[0]
        r = 1
        while True:
            more = [(info, s[r]) for info, s in good if len(s) > r and info.name not in bad]
            if not more:
                return
            for info, start in more:
                if info.name not in bad:
                    yield info, start
            r += 1

    def plan(self) -> list[tuple[str, int]]:
        """The ``(sequence, start)`` pairs iteration would load, without loading frames (a sequence whose
        frames turn out unreadable is skipped by iteration, which then draws further clips)."""
        self.skipped = {}
        limit = self.clips_per_dataset
        out: list[tuple[str, int]] = []
        for info, start in self._candidates(set()):
            if limit is not None and len(out) >= limit:
                break
            if limit is None and any(n == info.name for n, _ in out):
                break
            out.append((info.name, start))
        return out

    def __iter__(self) -> Iterator[Sample]:
        self.skipped = {}
        bad: set[str] = set()
        limit = self.clips_per_dataset
        done: set[str] = set()
        count = 0
        for info, start in self._candidates(bad):
            if limit is not None and count >= limit:
                return
            if limit is None and info.name in done:
                return  # one clip per sequence: the second round begins
            try:
                sample = self.clip(info, start)
            except DatasetError as e:
                bad.add(info.name)
                self._skip(info.name, e)
                continue
            done.add(info.name)
            count += 1
            yield sample
        if count == 0 and self.skipped:
            reasons = "\n  ".join(f"{k}: {v}" for k, v in self.skipped.items())
            raise DatasetError(f"no usable {self.kind} clip under {self.root}; every sequence was skipped:\n  "
                               f"{reasons}")

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.root)!r}, num_frames={self.num_frames}, stride={self.stride}, "
                f"clips_per_dataset={self.clips_per_dataset}, seed={self.seed}, resolution={self.resolution})")


def _list_images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS),
                  key=lambda p: _natural_key(p.name))


def _subfolders(root: Path) -> list[str]:
    return [p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith((".", "_"))]


# --------------------------------------------------------------------------------------------------
# RealEstate10K
# --------------------------------------------------------------------------------------------------
class RealEstate10KReader(DatasetReader):
    """RealEstate10K camera files + user-extracted frames (layout in the module docstring)."""

    kind = "re10k"

    def __init__(self, root: str | Path, *, split: str | None = "test", cameras_dir: str | Path | None = None,
                 frames_dir: str | Path | None = None, frame_name: str = "{timestamp}",
                 extensions: Sequence[str] = IMAGE_EXTENSIONS, missing_frames: Literal["error", "drop"] = "error",
                 **protocol: Any) -> None:
        super().__init__(root, **protocol)
        base = self.root if split is None else self.root / split
        self.cameras_dir = Path(cameras_dir) if cameras_dir is not None else base
        self.frames_dir = Path(frames_dir) if frames_dir is not None else base
        self.frame_name = frame_name
        self.extensions = tuple(e if e.startswith(".") else "." + e for e in extensions)
        if missing_frames not in ("error", "drop"):
            raise ValueError(f"missing_frames must be 'error' or 'drop', got {missing_frames!r}")
        self.missing_frames = missing_frames
        if not self.cameras_dir.is_dir():
            raise DatasetError(f"RealEstate10K camera folder {self.cameras_dir} does not exist; expected "
                               "<root>/<split>/<sequence>.txt (set split= or cameras_dir=)")

    def _discover(self) -> list[str]:
        return [p.stem for p in self.cameras_dir.glob("*.txt") if p.is_file()]

    def _load(self, name: str) -> SequenceInfo:
        txt = self.cameras_dir / f"{name}.txt"
        cams = read_re10k_cameras(txt)
        folder = self.frames_dir / name
        if not folder.is_dir():
            raise DatasetError(f"RealEstate10K sequence {name!r}: no frames folder {folder}; extract the frames of "
                               f"{cams.url} there as <timestamp_us>.png (or set frames_dir= / frame_name=)")
        files = [p for p in folder.iterdir() if p.suffix.lower() in self.extensions]
        by_stem: dict[str, Path] = {}
        for p in sorted(files, key=lambda p: -self.extensions.index(p.suffix.lower())):
            by_stem[p.stem] = p  # the earliest extension in `extensions` wins
        keep, paths, ids = [], [], []
        missing: list[str] = []
        for i, t in enumerate(cams.timestamps_us):
            stem = self.frame_name.format(timestamp=int(t), index=i)
            p = by_stem.get(stem)
            if p is None:
                missing.append(stem)
                continue
            keep.append(i)
            paths.append(p)
            ids.append(stem)
        if missing and self.missing_frames == "error":
            raise DatasetError(f"RealEstate10K sequence {name!r}: {len(missing)} of {len(cams.timestamps_us)} frames "
                               f"of {txt.name} have no image in {folder} (first: {missing[0]}{self.extensions[0]}); "
                               "extract every frame listed, or pass missing_frames='drop'")
        if not keep:
            raise DatasetError(f"RealEstate10K sequence {name!r}: no frame images in {folder}")
        keep_a = np.asarray(keep)
        size = _image_size(paths[0])
        wh = np.array(size, dtype=np.float64)
        K = np.tile(np.eye(3), (len(keep), 1, 1))
        nrm = cams.intrinsics[keep_a]
        K[:, 0, 0], K[:, 1, 1] = nrm[:, 0] * wh[0], nrm[:, 1] * wh[1]
        K[:, 0, 2], K[:, 1, 2] = nrm[:, 2] * wh[0], nrm[:, 3] * wh[1]
        c2w = np.linalg.inv(cams.w2c[keep_a])
        c2w[:, 3] = [0.0, 0.0, 0.0, 1.0]
        return SequenceInfo(name, c2w, K, np.tile(size, (len(keep), 1)), paths, ids, cams.timestamps_us[keep_a],
                            meta={"url": cams.url, "camera_file": str(txt), "missing_frames": len(missing)})


# --------------------------------------------------------------------------------------------------
# DL3DV (nerfstudio)
# --------------------------------------------------------------------------------------------------
class DL3DVReader(DatasetReader):
    """DL3DV scenes in nerfstudio format (layout in the module docstring)."""

    kind = "dl3dv"

    def __init__(self, root: str | Path, *, transforms_name: str = "transforms.json", images_dir: str | None = None,
                 **protocol: Any) -> None:
        super().__init__(root, **protocol)
        self.transforms_name = transforms_name
        self.images_dir = images_dir

    def _json_of(self, scene_dir: Path) -> Path | None:
        for cand in (scene_dir / self.transforms_name, scene_dir / "nerfstudio" / self.transforms_name):
            if cand.is_file():
                return cand
        return None

    def _single(self) -> bool:
        return self._json_of(self.root) is not None

    def _scene_dir(self, name: str) -> Path:
        return self.root if self._single() and name == self.root.name else self.root / name

    def _discover(self) -> list[str]:
        return [self.root.name] if self._single() else _subfolders(self.root)

    def _image_path(self, base: Path, file_path: str) -> Path:
        if self.images_dir is None:
            return base / file_path
        parts = Path(file_path).parts
        rest = parts[1:] if len(parts) > 1 else parts
        return base / self.images_dir / Path(*rest)

    def _load(self, name: str) -> SequenceInfo:
        scene = self._scene_dir(name)
        js = self._json_of(scene)
        if js is None:
            raise DatasetError(f"DL3DV scene {name!r}: no {self.transforms_name} in {scene} (nor in its nerfstudio/ "
                               "folder); download the scene's poses (nerfstudio format) or remove the folder")
        frames, top = read_nerfstudio_transforms(js)
        base = js.parent
        paths = [self._image_path(base, f.file_path) for f in frames]
        absent = [p for p in paths if not p.is_file()]
        if absent:
            found = sorted(p.name for p in base.iterdir() if p.is_dir() and p.name.startswith("images"))
            hint = (f"; image folders present: {', '.join(found)} - pass images_dir= to read one of them"
                    if found else "")
            raise DatasetError(f"DL3DV scene {name!r}: {len(absent)} of {len(paths)} images listed in {js} are "
                               f"missing (first: {absent[0]}){hint}")
        N = len(frames)
        K = np.tile(np.eye(3), (N, 1, 1))
        sizes = np.zeros((N, 2), dtype=np.int64)
        for i, (f, p) in enumerate(zip(frames, paths)):
            if f.w is None or f.h is None:
                w, h = _image_size(p)  # intrinsics given for the image as stored
            else:
                w, h = f.w, f.h
            sizes[i] = (w, h)
            K[i, 0, 0], K[i, 1, 1] = f.fx, f.fy
            K[i, 0, 2] = w / 2 if f.cx is None else f.cx
            K[i, 1, 2] = h / 2 if f.cy is None else f.cy
        c2w = opengl_to_opencv(np.stack([f.c2w_gl for f in frames]))
        distortion = {k: v for k, v in frames[0].extra.items() if v}
        return SequenceInfo(name, c2w, K, sizes, paths, [p.stem for p in paths], None,
                            meta={"transforms": str(js), "camera_model": top.get("camera_model"),
                                  "distortion_ignored": distortion})


# --------------------------------------------------------------------------------------------------
# Tanks and Temples
# --------------------------------------------------------------------------------------------------
class TanksAndTemplesReader(DatasetReader):
    """Tanks and Temples scenes: images + TnT ``.log`` trajectory + intrinsics (module docstring)."""

    kind = "tnt"
    CAMERAS_TXT_PLACES = ("cameras.txt", "sparse/0/cameras.txt", "sparse/cameras.txt")

    def __init__(self, root: str | Path, *, intrinsics: Intrinsics | Mapping[str, Any] | None = None,
                 cameras_txt: str | Path | None = None, log_name: str | None = None, images_dir: str = "images",
                 **protocol: Any) -> None:
        super().__init__(root, **protocol)
        self.intrinsics = intrinsics
        self.cameras_txt = None if cameras_txt is None else Path(cameras_txt)
        self.log_name = log_name
        self.images_dir = images_dir

    def _single(self) -> bool:
        return any(self.root.glob("*.log"))

    def _scene_dir(self, name: str) -> Path:
        return self.root if self._single() and name == self.root.name else self.root / name

    def _discover(self) -> list[str]:
        return [self.root.name] if self._single() else _subfolders(self.root)

    def _log_of(self, name: str, scene: Path) -> Path:
        if self.log_name is not None:
            p = scene / self.log_name
            if not p.is_file():
                raise DatasetError(f"Tanks and Temples scene {name!r}: camera log {p} does not exist")
            return p
        logs = sorted(scene.glob("*.log"))
        if len(logs) > 1:
            logs = [p for p in logs if p.name.endswith("_COLMAP_SfM.log")] or logs
        if not logs:
            raise DatasetError(f"Tanks and Temples scene {name!r}: no camera log (*.log) in {scene}; put the scene's "
                               "<scene>_COLMAP_SfM.log there")
        if len(logs) > 1:
            raise DatasetError(f"Tanks and Temples scene {name!r}: several camera logs in {scene} "
                               f"({', '.join(p.name for p in logs)}); pass log_name= to choose one")
        return logs[0]

    def _intrinsics_for(self, name: str, scene: Path, log: Path) -> tuple[Intrinsics, str]:
        given = self.intrinsics
        if isinstance(given, Intrinsics):
            return given, "given"
        if isinstance(given, Mapping) and "fx" in given:
            return Intrinsics.from_dict(given), "given"
        if isinstance(given, Mapping) and name in given:
            intr = given[name]
            return (intr if isinstance(intr, Intrinsics) else Intrinsics.from_dict(intr)), "given"
        if self.cameras_txt is not None:
            places = [self.cameras_txt if self.cameras_txt.is_absolute() else scene / self.cameras_txt]
        else:
            places = [scene / p for p in self.CAMERAS_TXT_PLACES]
        for p in places:
            if p.is_file():
                cams = read_colmap_cameras(p)
                distinct = {(m, i) for m, i in cams.values()}
                if len(distinct) > 1:
                    raise DatasetError(f"{p}: {len(cams)} different cameras; the .log does not say which image uses "
                                       "which, so pass intrinsics= for this scene")
                return next(iter(distinct))[1], str(p)
        raise DatasetError(
            f"Tanks and Temples scene {name!r}: the camera log {log} has no intrinsics and no COLMAP cameras.txt was "
            f"found (looked for {', '.join(str(p) for p in places)}). Fix: pass intrinsics=Intrinsics(fx, fy, cx, cy, "
            "width, height) (or {scene: Intrinsics}) to open_dataset('tnt', ...), or cameras_txt='path/to/cameras.txt'")

    def _load(self, name: str) -> SequenceInfo:
        scene = self._scene_dir(name)
        log = self._log_of(name, scene)
        ids, c2w = read_trajectory_log(log)
        folder = scene / self.images_dir if (scene / self.images_dir).is_dir() else scene
        paths = _list_images(folder)
        if len(paths) != len(c2w):
            raise DatasetError(f"Tanks and Temples scene {name!r}: {log.name} has {len(c2w)} cameras but {folder} has "
                               f"{len(paths)} images; the k-th camera is the k-th image in name order, so the folder "
                               "must hold exactly the images the log describes (set images_dir= if they are elsewhere)")
        intr, source = self._intrinsics_for(name, scene, log)
        N = len(paths)
        return SequenceInfo(name, c2w, np.tile(intr.K, (N, 1, 1)), np.tile([intr.width, intr.height], (N, 1)),
                            paths, [p.stem for p in paths], None,
                            meta={"log": str(log), "log_ids": ids.tolist(), "intrinsics_from": source})


# --------------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------------
DATASET_KINDS: dict[str, type[DatasetReader]] = {
    "re10k": RealEstate10KReader, "realestate10k": RealEstate10KReader,
    "dl3dv": DL3DVReader, "dl3dv10k": DL3DVReader,
    "tnt": TanksAndTemplesReader, "tanksandtemples": TanksAndTemplesReader,
}


def open_dataset(kind: str, root: str | Path, **options: Any) -> DatasetReader:
    """A reader for ``kind`` (``"re10k"``, ``"dl3dv"`` or ``"tnt"``) over ``root``.

    ``options`` are the protocol options of ``DatasetReader`` plus the format's own (see each reader).
    Iterate the reader for ``Sample`` clips; ``reader.skipped`` then says which sequences were left out.
    """
    key = re.sub(r"[^a-z0-9]", "", kind.lower())
    if key not in DATASET_KINDS:
        raise ValueError(f"unknown dataset kind {kind!r}; use 're10k', 'dl3dv' or 'tnt'")
    return DATASET_KINDS[key](root, **options)

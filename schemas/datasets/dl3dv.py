"""DL3DV: scenes in nerfstudio format (``transforms.json`` + images), OpenGL camera axes.

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
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .base import (
    DatasetError,
    DatasetReader,
    SequenceInfo,
    _check_rigid,
    _image_size,
    _natural_key,
    _subfolders,
    opengl_to_opencv,
)


# --------------------------------------------------------------------------------------------------
# File parser
# --------------------------------------------------------------------------------------------------
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

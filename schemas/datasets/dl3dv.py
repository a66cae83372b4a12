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

from pathlib import Path
from typing import Any

import numpy as np

from navcrafter.models.camera.camerafiles import NerfstudioFrame as NerfstudioFrame
from navcrafter.models.camera.camerafiles import read_nerfstudio_transforms

from .base import (
    DatasetError,
    DatasetReader,
    SequenceInfo,
    _image_size,
    _subfolders,
    opengl_to_opencv,
)

# --------------------------------------------------------------------------------------------------
# File parser
# --------------------------------------------------------------------------------------------------

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

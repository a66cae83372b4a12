"""RealEstate10K: one camera file per YouTube video, frames extracted by the user.

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
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from navcrafter.models.camera.camerafiles import RE10KCameras as RE10KCameras
from navcrafter.models.camera.camerafiles import read_re10k_cameras

from .base import (
    IMAGE_EXTENSIONS,
    DatasetError,
    DatasetReader,
    SequenceInfo,
    _image_size,
)

# --------------------------------------------------------------------------------------------------
# File parser
# --------------------------------------------------------------------------------------------------

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

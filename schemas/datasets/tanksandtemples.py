"""Tanks and Temples: images + a TnT/Redwood trajectory ``.log`` (camera-to-world) + intrinsics.

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
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics

from .base import (
    DatasetError,
    DatasetReader,
    SequenceInfo,
    _check_rigid,
    _floats,
    _list_images,
    _read_lines,
    _subfolders,
)
from .colmap import read_colmap_cameras


# --------------------------------------------------------------------------------------------------
# File parser
# --------------------------------------------------------------------------------------------------
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

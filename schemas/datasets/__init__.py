"""Readers for the public evaluation datasets: RealEstate10K, DL3DV (nerfstudio format), Tanks and Temples.

Every reader yields ``Sample`` clips in navcrafter's camera convention (see ``models/camera/cameras.py``):
**OpenCV camera-to-world** 4x4 poses (x right, y down, z forward) and **pixel** intrinsics of the frames
as returned (after resizing/cropping). One entry point: ``open_dataset(kind, root, **options)``.

Formats (as documented by the datasets) and the folder layouts expected here
============================================================================
One module per format; its docstring describes the files on disk (layout, conventions, units) and the
reader's options for them:

- ``realestate10k``: **RealEstate10K** (``kind="re10k"``), per-video camera ``.txt`` + extracted frames.
- ``dl3dv``: **DL3DV** (``kind="dl3dv"``), nerfstudio ``transforms.json`` + images.
- ``tanksandtemples``: **Tanks and Temples** (``kind="tnt"``), trajectory ``.log`` + images, intrinsics
  given or from a COLMAP ``cameras.txt`` (``colmap``).

``base`` holds what they share: ``DatasetError``, the records (``Sample``, ``SequenceInfo``), the image and
camera helpers (``resize_center_crop``, ``opengl_to_opencv``) and ``DatasetReader``, which implements the
sampling protocol (the paper's: a conditioning frame and the ``num_frames`` after it, clips drawn
deterministically from ``seed``) and the error rules (bad sequences are skipped and recorded in
``reader.skipped`` unless ``strict=True``); both are described in its docstring.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from .base import GL_CV_FLIP as GL_CV_FLIP
from .base import IMAGE_EXTENSIONS as IMAGE_EXTENSIONS
from .base import DatasetError, DatasetReader, Sample, SequenceInfo, opengl_to_opencv, resize_center_crop
from .base import StartMode as StartMode
from .colmap import read_colmap_cameras
from .dl3dv import DL3DVReader, read_nerfstudio_transforms
from .dl3dv import NerfstudioFrame as NerfstudioFrame
from .realestate10k import RE10KCameras as RE10KCameras
from .realestate10k import RealEstate10KReader, read_re10k_cameras
from .tanksandtemples import TanksAndTemplesReader, read_trajectory_log

__all__ = [
    "DatasetError", "Sample", "SequenceInfo", "DatasetReader", "RealEstate10KReader", "DL3DVReader",
    "TanksAndTemplesReader", "open_dataset", "resize_center_crop", "read_re10k_cameras",
    "read_nerfstudio_transforms", "read_trajectory_log", "read_colmap_cameras", "opengl_to_opencv",
    "DATASET_KINDS",
]


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

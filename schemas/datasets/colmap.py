"""COLMAP ``cameras.txt``: the intrinsics of a COLMAP reconstruction (text export), pinhole part only.

One camera per line, ``#`` lines are comments::

    CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]

``WIDTH HEIGHT`` is the size in pixels of the images the camera describes and ``PARAMS`` are in pixels of
that size, as many as the model has. The models read here are the pinhole-like ones::

    SIMPLE_PINHOLE  f cx cy                  SIMPLE_RADIAL  f cx cy k
    PINHOLE         fx fy cx cy              RADIAL         f cx cy k1 k2
    OPENCV          fx fy cx cy k1 k2 p1 p2  FULL_OPENCV    fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6

Their distortion parameters are dropped (``fy = fx = f`` for the single-focal models); other models
(fisheye, ...) are refused: undistort the images with COLMAP first. COLMAP's pixel convention (centre of
the top-left pixel at (0.5, 0.5)) is navcrafter's, so ``cx, cy`` are used as they are. Used by the
Tanks and Temples reader when no intrinsics are given (its ``.log`` holds none).
"""

from __future__ import annotations

from pathlib import Path

from navcrafter.models.camera.cameras import Intrinsics

from .base import DatasetError, _floats, _read_lines

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

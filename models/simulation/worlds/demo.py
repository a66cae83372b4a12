"""A demo collection from real scans (``navcrafter demo-data OUT --world FILE``): start views of each world
rendered as input photos, with the hidden ground truth written as the generated demo writes it.

Layout::

    OUT/scan-<world>-v<k>.png                        the "photo" of start view k of the world
    OUT/.groundtruth/scan-<world>-v<k>/scene.json    spec (kind "scan", the world file and its sha256), the
                                                     photo's camera and sha256, the world's info (source file,
                                                     scale, up axis, colour mode, warnings)
    OUT/.groundtruth/scan-<world>-v<k>/mesh.ply      the true surfaces (a link to the world's)
    OUT/.groundtruth/worlds/<world>/world.npz        the world (ground-truth frame), once per world
    OUT/.groundtruth/worlds/<world>/mesh.ply
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from PIL import Image

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.simulation import GROUNDTRUTH_DIR
from navcrafter.models.simulation.render import photo_finish, render
from navcrafter.models.simulation.worlds import LABEL, SCAN_KIND, WORLD_VERSION, WORLDS_DIR, WorldError
from navcrafter.models.simulation.worlds.load import load_world
from navcrafter.models.simulation.worlds.scene import ScanScene
from navcrafter.models.simulation.worlds.views import check_start, start_views

FOV_X_DEG = 65.0  # the generated demo rooms use 60-72 degrees


@dataclass
class StartCameras:
    """Start cameras given by the user, in the scan file's own coordinates and units (OpenCV c2w), with
    optional intrinsics ``K [N, 3, 3]`` at the photo size."""

    source: str
    c2w: np.ndarray
    K: np.ndarray | None = None


def world_name(path: str | Path, taken: set[str]) -> str:
    p = Path(path)
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", p.name if p.is_dir() else p.stem).strip("._") or "world"
    name, i = stem, 1
    while name in taken:
        i += 1
        name = f"{stem}_{i}"
    taken.add(name)
    return name


def to_world(c2w_file: np.ndarray, file_to_world: np.ndarray) -> np.ndarray:
    """Camera-to-world poses in the scan file's frame to the ground-truth frame (rotation, scale, shift)."""
    M = np.asarray(file_to_world, dtype=np.float64)
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    R = M[:3, :3] / s
    out = np.array(c2w_file, dtype=np.float64, copy=True)
    out[:, :3, :3] = R @ out[:, :3, :3]
    out[:, :3, 3] = out[:, :3, 3] @ M[:3, :3].T + M[:3, 3]
    return out


def _link(src: Path, dst: Path) -> None:
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        dst.write_bytes(src.read_bytes())


def write_world_collection(folder: str | Path, worlds: list[str | Path], views: int = 3, *, up: str = "auto",
                           scale: float = 1.0, starts: list[StartCameras | None] | None = None,
                           r_safe_m: float = 0.25, width: int = 640, height: int = 480,
                           supersample: int = 2) -> list[Path]:
    """Photos of start views of each world, with hidden ground truth (module docstring); returns the photos."""
    folder = Path(folder)
    starts = starts or [None] * len(worlds)
    if len(starts) != len(worlds):
        raise WorldError(f"{len(starts)} start-camera files for {len(worlds)} worlds; give one --start per --world "
                         f"(or none)")
    out, taken = [], set()
    for wf, start in zip(worlds, starts, strict=True):
        world = load_world(wf, scale=scale, up=up, name=None)
        name = world_name(wf, taken)
        world.name = name
        wdir = folder / GROUNDTRUTH_DIR / WORLDS_DIR / name
        sha = world.save(wdir / "world.npz")
        o3d.io.write_triangle_mesh(str(wdir / "mesh.ply"), world.merged_mesh(), write_ascii=False)
        scene = ScanScene(world, source=str(wdir / "world.npz"))
        Ks: list[Intrinsics]
        if start is not None:
            poses = to_world(start.c2w, world.info["file_to_world"])
            for i, c2w in enumerate(poses):
                check_start(scene, c2w, r_safe_m, f"{start.source}[{i}]")
            Ks = [Intrinsics.from_matrix(start.K[i], width, height) if start.K is not None else
                  Intrinsics.from_fov(FOV_X_DEG, width, height) for i in range(len(poses))]
        else:
            poses = start_views(scene, views, r_safe_m, FOV_X_DEG, source=str(wf))
            Ks = [Intrinsics.from_fov(FOV_X_DEG, width, height)] * len(poses)
        for v, (c2w, K) in enumerate(zip(poses, Ks, strict=True)):
            r = render(scene, c2w, K, supersample=supersample)
            rgb = photo_finish(r.rgb, np.random.default_rng([v, zlib.crc32(name.encode())]))
            buf = io.BytesIO()
            Image.fromarray(rgb).save(buf, format="PNG")
            data = buf.getvalue()
            stem = f"scan-{name}-v{v}"
            photo = folder / f"{stem}.png"
            photo.write_bytes(data)
            gt = folder / GROUNDTRUTH_DIR / stem
            gt.mkdir(parents=True, exist_ok=True)
            record = {"note": LABEL,
                      "scene": {"kind": SCAN_KIND, "name": name, "world": f"../{WORLDS_DIR}/{name}/world.npz",
                                "world_sha256": sha, "world_version": WORLD_VERSION},
                      "photo": {"file": photo.name, "sha256": hashlib.sha256(data).hexdigest(),
                                "c2w": np.asarray(c2w).tolist(), "intrinsics": K.to_dict(),
                                "valid_fraction": float(r.hit.mean())},
                      "world": world.info,
                      "frame": "ground truth: z up, floor at z = 0, metres; cameras OpenCV camera-to-world"}
            (gt / "scene.json").write_text(json.dumps(record, indent=1))
            _link(wdir / "mesh.ply", gt / "mesh.ply")
            out.append(photo)
    return out

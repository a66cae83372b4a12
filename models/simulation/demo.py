"""The demo collection: photo-like renders of generated scenes, with their hidden ground truth.

Layout written by ``write_demo_collection(folder)``::

    folder/<kind>-<seed>.png                    the "photo" (what a user would supply)
    folder/.groundtruth/<kind>-<seed>/scene.json generator spec, photo camera, photo sha256
    folder/.groundtruth/<kind>-<seed>/mesh.ply   the true surfaces (vertex-coloured triangles)

Ingest finds the ground truth beside a photo (and checks the photo's sha256), so the simulation
backend can stand in for the learned models on exactly these images.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np
import open3d as o3d
from PIL import Image

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.simulation import GROUNDTRUTH_DIR, LABEL
from navcrafter.models.simulation.render import photo_finish, render
from navcrafter.models.simulation.scenes import KINDS, generate_scene


def write_demo_collection(folder: str | Path, kinds: tuple[str, ...] = KINDS, per_kind: int = 1,
                          seed: int = 0, width: int = 640, height: int = 480,
                          supersample: int = 2) -> list[Path]:
    """Render one photo per (kind, seed) into ``folder``; returns the photo paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for kind in kinds:
        for i in range(per_kind):
            s = seed + i
            scene = generate_scene(kind, s)
            K = Intrinsics.from_fov(scene.camera_fov_x_deg, width, height)
            r = render(scene, scene.camera_c2w, K, supersample=supersample)
            rgb = photo_finish(r.rgb, np.random.default_rng([s, KINDS.index(kind)]))
            buf = io.BytesIO()
            Image.fromarray(rgb).save(buf, format="PNG")
            data = buf.getvalue()
            name = f"{kind}-{s}"
            photo = folder / f"{name}.png"
            photo.write_bytes(data)
            gt = folder / GROUNDTRUTH_DIR / name
            gt.mkdir(parents=True, exist_ok=True)
            record = {"note": LABEL, "scene": scene.spec,
                      "photo": {"file": photo.name, "sha256": hashlib.sha256(data).hexdigest(),
                                "c2w": scene.camera_c2w.tolist(), "intrinsics": K.to_dict()},
                      "frame": "ground truth: z up, metres; cameras OpenCV camera-to-world"}
            (gt / "scene.json").write_text(json.dumps(record, indent=1))
            o3d.io.write_triangle_mesh(str(gt / "mesh.ply"), scene.merged_mesh(), write_ascii=False)
            out.append(photo)
    return out

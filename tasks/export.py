"""Export: the user-facing files of a scene, stored in its ``exports/`` directory.

* ``cloud.ply``          the fused cloud (binary PLY: x y z, RGB, confidence), world frame;
* ``video.mp4``          every synthesized clip, in iteration order (H.264, ``synthesis.fps``);
* ``trajectory.json``    per frame: iteration, index, OpenCV camera-to-world pose, intrinsics;
* ``trajectory.parquet`` the same rows with the ``schemas.tables.TRAJECTORIES`` schema;
* when the fit ran (``fit.enabled``): ``gaussians.ply`` (the standard 3DGS PLY, ``models/gaussians/ply.py``)
  and ``flythrough.mp4`` (the Gaussians rendered along the explored trajectory at the fit's cameras and
  resolution, each distinct frame once; the held-out frames' renders the fit (or refine) step stored are reused,
  not rendered again: :func:`flythrough_frames`).

Outputs of the simulation backend say so: a PLY header comment (both PLYs), a label burnt into the videos,
a ``backend``/``label`` field in the JSON and a ``backend`` column in the table.
"""

from __future__ import annotations

import io
import json
import os
import tempfile

import numpy as np

from navcrafter.models.gaussians.ply import save_ply
from navcrafter.models.gaussians.train import render_model
from navcrafter.models.media import encode_mp4, label_frames
from navcrafter.models.reconstruction.pointcloud import ply_bytes
from navcrafter.models.threads import one_openmp_thread
from navcrafter.schemas.layout import FIT, REFINE, SYNTHESIZE
from navcrafter.schemas.tables import to_table
from navcrafter.tasks.backends import run_band
from navcrafter.tasks.readers import (
    CameraPath,
    camera_path,
    load_gaussians,
    load_refined_gaussians,
    scene_run_label,
)
from navcrafter.tasks.steps import StepContext


def trajectory_rows(path: CameraPath, scene_id: str, backend: str) -> list[dict]:
    """One row per frame of the camera path (``schemas.tables.TRAJECTORIES``)."""
    rows = []
    for f, (k, i) in enumerate(path.refs):
        K = path.intrinsics(f)
        rows.append({"scene_id": scene_id, "iteration": k, "frame": i, "c2w": path.c2w[f],
                     "fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "width": path.width, "height": path.height,
                     "backend": backend})
    return rows


def write_gaussian_exports(writer, scene, comments: list[str], band: str | None, fps: int,
                           refined: bool = False) -> None:
    """``gaussians.ply`` and ``flythrough.mp4`` of the fitted model (``gaussians`` group), or of the refined
    one (``renders`` group) when ``refined``."""
    model = load_refined_gaussians(scene) if refined else load_gaussians(scene)
    fd, ply = tempfile.mkstemp(suffix=".ply")
    os.close(fd)
    try:
        step = "fit and refine steps" if refined else "fit step"
        save_ply(ply, model, comments=[*comments, f"3D Gaussian Splatting (navcrafter {step})"])
        with open(ply, "rb") as fh:
            writer.write_file("gaussians.ply", fh.read())
    finally:
        if os.path.exists(ply):
            os.unlink(ply)
    frames = flythrough_frames(scene, model, refined)
    writer.write_file("flythrough.mp4", encode_mp4(label_frames(frames, band) if band else frames, fps))


FLYTHROUGH_BATCH = 8  # cameras per rasterizer call


def flythrough_frames(scene, model, refined: bool) -> np.ndarray:
    """``model`` rendered at every camera of the fit (the explored trajectory as the geometry model estimated
    it, the cameras the Gaussians were fitted at, each distinct frame once) at the fit's resolution: the
    held-out frames' renders of the same model are the fit's ``holdout_renders`` (the refine step's when
    ``refined``), reused as stored; the other frames are rendered in batches."""

    g = scene.read_all(FIT)
    w, h = scene.status(FIT).attrs["resolution"]
    held = np.asarray(g["holdout"], dtype=bool)
    stored = scene.read(REFINE, None, "holdout_renders") if refined else g["holdout_renders"]
    frames = np.empty((len(held), h, w, 3), dtype=np.uint8)
    frames[held] = stored
    rest = np.nonzero(~held)[0]
    frames[rest] = render_model(model, g["c2w"][rest], g["K"][rest], w, h, batch=FLYTHROUGH_BATCH)
    return frames


def export(ctx: StepContext) -> dict:
    config, scene, scene_id, writer = ctx.config, ctx.scene, ctx.scene_id, ctx.writer
    N = config.iterations
    store = scene.store
    label = scene_run_label(scene, config)  # a scanned world's label names the scan
    band = run_band(config)  # every rendered frame of a labelled run carries a band
    cloud = ctx.cloud(N)
    comments = [f"navcrafter scene {scene_id}", f"backend {config.backend}",
                "frame: world = input camera (OpenCV: x right, y down, z forward)"]
    if label:
        comments.append(label)
    writer.write_file("cloud.ply", ply_bytes(cloud, comments))
    path = camera_path(scene, config)
    rows = trajectory_rows(path, scene_id, config.backend)
    if N > 0:
        frames = np.concatenate([scene.read(SYNTHESIZE, k, "frames") for k in range(1, N + 1)])
        frames = label_frames(frames, band) if band else frames
        writer.write_file("video.mp4", encode_mp4(frames, config.synthesis.fps))
    doc = {"scene_id": scene_id, "backend": config.backend,
           "convention": "OpenCV camera-to-world (x right, y down, z forward); world = input camera",
           "frames": [{"iteration": r["iteration"], "frame": r["frame"], "c2w": r["c2w"].tolist(),
                       "intrinsics": {k: r[k] for k in ("fx", "fy", "cx", "cy", "width", "height")}}
                      for r in rows]}
    if label:
        doc["label"] = label
    writer.write_file("trajectory.json", json.dumps(doc, indent=1).encode())
    if config.fit.enabled:
        with one_openmp_thread():  # torch's kernels around the rasterizer on this scene's thread alone
            write_gaussian_exports(writer, scene, comments, band,
                                   config.synthesis.fps, refined=config.refine.enabled)
    table = to_table("trajectories", rows)
    buf = io.BytesIO()
    import pyarrow.parquet as pq

    pq.write_table(table, buf)
    writer.write_file("trajectory.parquet", buf.getvalue())
    store.tables.write("trajectories", table, part=f"scene-{scene_id}")
    return {"n_points": len(cloud), "num_frames": len(rows), "label": label or ""}

"""Interchange with other tools: a scene's frames, cameras and cloud for nerfstudio / gsplat / COLMAP-reading
trainers (``navcrafter export``), and a point cloud scored against a reference cloud (``navcrafter evaluate-cloud``).

**Frames and cameras.** Every distinct synthesized frame (``readers.CameraPath.distinct``: frame 0 of clip k >= 2
repeats the last frame of clip k-1 and is left out), as a PNG at the synthesis resolution, at the cameras the fit
used: the fit step's stored ``c2w`` / ``K`` / ``frame_ref`` (``gaussians`` group; its K, at the fit's resolution,
is scaled to the image size) when it ran, otherwise the estimated camera path the fit would use
(``readers.camera_path(cameras="estimated")``). Initial points: the fused scene cloud after the last iteration (the
export step's ``cloud.ply``).

* ``nerfstudio``: ``transforms.json`` (``camera_model`` OPENCV with zero distortion, intrinsics ``fl_x fl_y cx cy
  w h`` at the top when every frame shares them, else per frame; per frame ``file_path`` and ``transform_matrix``,
  the OpenGL camera-to-world nerfstudio expects: our OpenCV c2w with its camera y and z axes negated), images in
  ``images/``, initial points ``sparse_pc.ply`` (``ply_file_path``; x y z + uchar RGB, read with Open3D by
  nerfstudio's splatfacto).
* ``colmap``: a COLMAP text model ``sparse/0/{cameras,images,points3D}.txt`` (one PINHOLE camera per distinct
  intrinsics; per image the world-to-camera rotation as quaternion ``QW QX QY QZ`` and translation ``TX TY TZ`` in
  OpenCV camera axes, which are COLMAP's, and an empty 2D-points line; points with RGB, error 0 and no track),
  images in ``images/``. COLMAP's pixel convention (pixel centres at +0.5) is ours: K is written as is.
* both: ``navcrafter_export.json``: scene id, backend, label (a simulation or random-weights run says so), the
  world frame and units, which cameras were used, and per image its (iteration, frame) and fit split.

The world frame is the scene's: the input camera's OpenCV frame (x right, y down, z forward; world up is -y for
an upright photo); units are the geometry model's (metres for metric models; the simulation backend's world is
``simulation_world_scale`` units per metre, recorded in the JSON).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics, invert_pose, matrix_to_quat
from navcrafter.models.camera.trajectories import GL_CV_FLIP
from navcrafter.models.metrics import cloud_files
from navcrafter.models.metrics.cloud_files import MESH_POINTS
from navcrafter.models.reconstruction.pointcloud import ply_bytes
from navcrafter.schemas.layout import EXPORT, FIT, GEOMETRY, LIFT, SYNTHESIZE
from navcrafter.schemas.store import Store, StoreError
from navcrafter.tasks.common import load_cloud
from navcrafter.tasks.readers import (
    SceneNotFound,
    camera_path,
    export_record,
    resolve_scene,
    scene_label,
    scene_run_config,
    scene_run_label,
    stored_run_config,
)

if TYPE_CHECKING:
    from navcrafter.schemas.config import RunConfig
    from navcrafter.schemas.store import SceneStore

FORMATS = ("nerfstudio", "colmap")
WORLD_CONVENTION = ("world = the input camera's frame, OpenCV axes (x right, y down, z forward; world up is -y for "
                    "an upright photo)")


class InterchangeError(ValueError):
    """A user's mistake (unknown scene, unfinished scene, unreadable file): the CLI prints it and exits 2."""


# --------------------------------------------------------------------------------------------------
# The scene's frames and cameras
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExportFrames:
    """The exported frames: (k, i) refs, OpenCV c2w ``[F, 4, 4]``, K ``[F, 3, 3]`` at ``width`` x ``height`` (the
    frames' resolution), which cameras these are (``"fit"`` or ``"estimated"``) and the fit's split (or None)."""

    refs: list[tuple[int, int]]
    c2w: np.ndarray
    K: np.ndarray
    width: int
    height: int
    cameras: str
    holdout: np.ndarray | None = None
    train: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.refs)

    @property
    def names(self) -> list[str]:
        return [f"frame_{f:05d}.png" for f in range(len(self))]


def finished_scene(store_uri: str, scene_id: str) -> SceneStore:
    """The scene ``scene_id`` names (an id, a unique id prefix or the photo's file name: ``readers.resolve_scene``)
    of a store, which must have finished exploring (its export step complete)."""

    try:
        store = Store(store_uri, create=False)
        sid = resolve_scene(store, scene_id)
    except (StoreError, SceneNotFound) as exc:
        raise InterchangeError(str(exc)) from None
    scene = store.scene(sid)
    if not scene.status(EXPORT).complete:
        raise InterchangeError(f"scene {sid[:12]} of {store_uri} has not finished exploring (its export step "
                               f"has not completed); finish it first with `navcrafter explore PHOTOS --store "
                               f"{store_uri}` (same config), then export again")
    return scene


def scene_config(scene: SceneStore) -> RunConfig:
    """The config the scene's run stored (``readers.scene_run_config``). For a scene written before runs stored it,
    the fallback reconstruction takes the iterations its export covered (a warning says so)."""

    if stored_run_config(scene) is not None:
        return scene_run_config(scene)
    frames = export_record(scene).get("frames", [])
    if frames:
        iterations = max(int(f["iteration"]) for f in frames)
    else:  # an export without its trajectory: the complete lift steps from 1 on
        iterations = 0
        while scene.status(LIFT, iterations + 1).complete:
            iterations += 1
    return scene_run_config(scene, iterations)


def export_frames(scene: SceneStore, config: RunConfig) -> ExportFrames:
    """The frames to export at the fit's cameras (fit step complete), else at the estimated camera path."""

    W, H = int(config.synthesis.width), int(config.synthesis.height)
    st = scene.status(FIT)
    if st.complete:
        g = scene.read_all(FIT)
        w, h = st.attrs["resolution"]
        K = np.stack([Intrinsics.from_matrix(k, w, h).resize(W, H).K for k in np.asarray(g["K"], dtype=np.float64)])
        refs = [(int(k), int(i)) for k, i in np.asarray(g["frame_ref"])]
        return ExportFrames(refs, np.asarray(g["c2w"], dtype=np.float64), K, W, H, "fit",
                            np.asarray(g["holdout"], dtype=bool), np.asarray(g["train"], dtype=bool))
    path = camera_path(scene, config, cameras="estimated").distinct()
    return ExportFrames(path.refs, path.c2w, path.K, path.width, path.height, "estimated")


def _labels(scene: SceneStore, config: RunConfig | None) -> tuple[str, str | None]:
    """The run's backend and label: as its export step recorded them, else from ``config``
    (``readers.scene_label``: the one label reader)."""

    st = scene.status(EXPORT)
    backend = st.attrs.get("backend") or (config.backend if config is not None else "unknown")
    label = st.attrs.get("label") or scene_label(scene)
    if not label and config is not None:
        label = scene_run_label(scene, config)
    return backend, label or None


def _write_images(scene: SceneStore, frames: ExportFrames, folder: Path, label: str | None) -> None:
    """The frames as PNGs; a labelled run's label goes in a PNG text chunk, not into the pixels trainers learn."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo


    folder.mkdir(parents=True, exist_ok=True)
    info = None
    if label:
        info = PngInfo()
        info.add_text("navcrafter", label)
    by_clip: dict[int, list[int]] = {}
    for f, (k, _) in enumerate(frames.refs):
        by_clip.setdefault(k, []).append(f)
    names = frames.names
    for k, fs in by_clip.items():  # one clip's frames in memory at a time
        clip = scene.read_rows(SYNTHESIZE, k, "frames", [frames.refs[f][1] for f in fs])
        for img, f in zip(clip, fs):
            if img.shape[:2] != (frames.height, frames.width):
                raise InterchangeError(f"scene {scene.scene_id[:12]}: frame {frames.refs[f]} is {img.shape[1]}x"
                                       f"{img.shape[0]}, the cameras are for {frames.width}x{frames.height}")
            Image.fromarray(np.ascontiguousarray(img)).save(folder / names[f], pnginfo=info)


def _prepare(store_uri: str, scene_id: str, out: Path, config: RunConfig | None):
    scene = finished_scene(store_uri, scene_id)
    cfg = config if config is not None else scene_config(scene)
    frames = export_frames(scene, cfg)
    if len(frames) == 0:
        raise InterchangeError(f"scene {scene.scene_id[:12]} has no synthesized frames to export")
    backend, label = _labels(scene, config)
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InterchangeError(f"cannot create {out}: {exc}") from None
    _write_images(scene, frames, out / "images", label)
    return scene, cfg, frames, backend, label, out


def _cloud(scene: SceneStore, config: RunConfig):

    return load_cloud(scene, config.iterations)


def _comments(scene: SceneStore, backend: str, label: str | None) -> list[str]:
    return [f"navcrafter scene {scene.scene_id}", f"backend {backend}",
            "frame: world = input camera (OpenCV: x right, y down, z forward)", *([label] if label else [])]


def _manifest(scene: SceneStore, fmt: str, frames: ExportFrames, backend: str, label: str | None, files: dict,
              n_points: int) -> dict:

    scale = scene.status(GEOMETRY).attrs.get("simulation_world_scale")
    units = "the geometry model's (metres for metric models)"
    if scale is not None:
        units = f"simulation world units: {float(scale)} per metre (the simulated geometry model's scale)"
    doc = {"format": fmt, "scene_id": scene.scene_id, "backend": backend,
           "world": WORLD_CONVENTION, "units": units,
           "cameras": frames.cameras,
           "cameras_doc": ("the fit step's cameras (gaussians/c2w, K scaled to the frames' size)" if frames.cameras
                           == "fit" else "the estimated camera path (lift step's poses, interpolated between them)"),
           "width": frames.width, "height": frames.height, "n_frames": len(frames), "n_points": n_points,
           "files": files,
           "frames": [{"file": f"images/{name}", "iteration": k, "frame": i,
                       **({"holdout": bool(frames.holdout[f]), "train": bool(frames.train[f])}
                          if frames.holdout is not None else {})}
                      for f, (name, (k, i)) in enumerate(zip(frames.names, frames.refs))]}
    if scale is not None:
        doc["world_units_per_metre"] = float(scale)
    if label:
        doc["label"] = label
    return doc


# --------------------------------------------------------------------------------------------------
# nerfstudio
# --------------------------------------------------------------------------------------------------
def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world with OpenCV camera axes -> with OpenGL's (nerfstudio, Blender): y and z axes negated."""

    return np.asarray(c2w, dtype=np.float64) @ GL_CV_FLIP


def nerfstudio_transforms(frames: ExportFrames, ply_name: str = "sparse_pc.ply") -> dict:
    """nerfstudio's ``transforms.json`` for ``frames`` (images under ``images/``)."""
    keys = ("fl_x", "fl_y", "cx", "cy")
    intr = [dict(zip(keys, (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])))) for K in frames.K]
    shared = all(d == intr[0] for d in intr)
    doc: dict = {"camera_model": "OPENCV", **(intr[0] if shared else {}), "w": frames.width, "h": frames.height,
                 "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                 "frames": [{"file_path": f"images/{name}", "transform_matrix": opencv_to_opengl(c2w).tolist(),
                             **({} if shared else intr[f])}
                            for f, (name, c2w) in enumerate(zip(frames.names, frames.c2w))],
                 "ply_file_path": ply_name}
    return doc


def export_nerfstudio(store_uri: str, scene_id: str, out: str | Path, config: RunConfig | None = None) -> dict:
    """Write a nerfstudio dataset of a finished scene to ``out``; returns ``navcrafter_export.json``'s content.
    ``config`` (optional) gives the iterations and synthesis size; by default they are read from the scene."""

    scene, cfg, frames, backend, label, out = _prepare(store_uri, scene_id, out, config)
    cloud = _cloud(scene, cfg)
    (out / "sparse_pc.ply").write_bytes(ply_bytes(cloud, _comments(scene, backend, label)))
    (out / "transforms.json").write_text(json.dumps(nerfstudio_transforms(frames), indent=1))
    files = {"transforms": "transforms.json", "points": "sparse_pc.ply", "images": "images/"}
    doc = _manifest(scene, "nerfstudio", frames, backend, label, files, len(cloud))
    doc["nerfstudio"] = ("transform_matrix: OpenGL camera-to-world (camera x right, y up, z back) in the world "
                         "above; nerfstudio re-orients and re-scales the poses (and sparse_pc.ply with them) itself")
    (out / "navcrafter_export.json").write_text(json.dumps(doc, indent=1))
    return doc


# --------------------------------------------------------------------------------------------------
# COLMAP
# --------------------------------------------------------------------------------------------------
def _num(x: float) -> str:
    return repr(float(x) + 0.0)  # the shortest text that reads back as the same double (-0.0 as 0.0)


def colmap_model_text(frames: ExportFrames, points: np.ndarray, colors: np.ndarray, comment: str = ""
                      ) -> dict[str, str]:
    """The three files of a COLMAP text model: ``cameras.txt``, ``images.txt``, ``points3D.txt``."""

    head = [f"# {line}" for line in comment.splitlines()]
    cams: list[tuple[float, ...]] = []
    cam_of = []
    for K in frames.K:
        params = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        if params not in cams:
            cams.append(params)
        cam_of.append(cams.index(params) + 1)
    cameras = [*head, "# Camera list with one line of data per camera:",
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", f"# Number of cameras: {len(cams)}"]
    cameras += [f"{c + 1} PINHOLE {frames.width} {frames.height} {' '.join(_num(p) for p in params)}"
                for c, params in enumerate(cams)]
    w2c = invert_pose(frames.c2w)
    q = matrix_to_quat(w2c[:, :3, :3])
    images = [*head, "# Image list with two lines of data per image:",
              "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
              "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(frames)}, mean observations per "
              "image: 0"]
    for f, name in enumerate(frames.names):
        images.append(" ".join([str(f + 1), *(_num(v) for v in q[f]), *(_num(v) for v in w2c[f, :3, 3]),
                                str(cam_of[f]), name]))
        images.append("")
    pts = [*head, "# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
           f"# Number of points: {len(points)}, mean track length: 0"]
    P = np.asarray(points, dtype=np.float64)
    C = np.asarray(colors, dtype=np.int64)
    pts += [f"{j + 1} {_num(p[0])} {_num(p[1])} {_num(p[2])} {c[0]} {c[1]} {c[2]} 0" for j, (p, c) in
            enumerate(zip(P, C))]
    return {"cameras.txt": "\n".join(cameras) + "\n", "images.txt": "\n".join(images) + "\n",
            "points3D.txt": "\n".join(pts) + "\n"}


def export_colmap(store_uri: str, scene_id: str, out: str | Path, config: RunConfig | None = None) -> dict:
    """Write a COLMAP text model (``sparse/0``) and the images of a finished scene to ``out``; returns
    ``navcrafter_export.json``'s content."""
    scene, cfg, frames, backend, label, out = _prepare(store_uri, scene_id, out, config)
    cloud = _cloud(scene, cfg)
    sparse = out / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    comment = "\n".join(_comments(scene, backend, label))
    for name, text in colmap_model_text(frames, cloud.points, cloud.colors, comment).items():
        (sparse / name).write_text(text)
    files = {"model": "sparse/0/", "images": "images/"}
    doc = _manifest(scene, "colmap", frames, backend, label, files, len(cloud))
    doc["colmap"] = ("images.txt: world-to-camera rotation (QW QX QY QZ) and translation, OpenCV camera axes "
                     "(COLMAP's); PINHOLE cameras; points without tracks")
    (out / "navcrafter_export.json").write_text(json.dumps(doc, indent=1))
    return doc


EXPORTERS = {"nerfstudio": export_nerfstudio, "colmap": export_colmap}


# --------------------------------------------------------------------------------------------------
# evaluate-cloud: a point cloud against a reference cloud (models.metrics.cloud_files)
# --------------------------------------------------------------------------------------------------
def evaluate_cloud_files(pred: str | Path, gt: str | Path, threshold: float = 0.02, align: bool = False,
                         icp_distance: float | None = None, mesh_points: int = MESH_POINTS) -> dict:
    """``models.metrics.cloud_files.evaluate_cloud_files``; a bad file or option is an ``InterchangeError``."""
    try:
        return cloud_files.evaluate_cloud_files(pred, gt, threshold, align, icp_distance, mesh_points)
    except cloud_files.CloudFileError as exc:
        raise InterchangeError(str(exc)) from None

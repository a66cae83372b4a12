"""Rendering a 3DGS PLY, or the fitted Gaussians of a scene in a store, along a trajectory preset or a camera file
to PNG frames, an MP4 and ``cameras.json`` (``navcrafter render``, whose typer command is ``flows/cli/render.py``).

* ``ply_source`` / ``scene_source``: what is rendered (``Source``: the model, its start camera, the band burnt
  into its frames); a scene is named as every tool names one (``tasks.readers.resolve_scene``);
* ``render_cameras``: the cameras of the render (a preset from the source's framed start view, or a camera file's
  poses and intrinsics) at the render size;
* ``render_frames``: the frames, one at a time, to ``frames/00000.png ...``, ``render.mp4`` and ``cameras.json``.

The trajectories and camera-file parsers are in ``models/camera/trajectories.py``; the rendering is
``models.gaussians.train.render_model``. Bad input raises ``ValueError`` naming it (the CLI prints it, exit 2).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from navcrafter.models.camera import trajectories as tr
from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.ply import load_gaussian_ply, read_ply_header
from navcrafter.models.gaussians.renderer import resolve_backend, resolve_device
from navcrafter.models.gaussians.train import render_model
from navcrafter.models.media import encode_mp4, label_frames
from navcrafter.schemas.layout import FIT, PLAN, REFINE
from navcrafter.schemas.store import Store

DEFAULT_SIZE = 512  # a bare PLY's default width and height
DEFAULT_FOV = 60.0  # a bare PLY's default horizontal field of view, degrees
BANDS_IN_COMMENTS = ("SIMULATION", "RANDOM WEIGHTS", "CAMERA CONTROL UNTRAINED")
_FRAME_PNG = re.compile(r"\d{5}\.png")


class RenderError(ValueError):
    """A render that cannot be written where the user asked (the CLI prints it and exits 2)."""


@dataclass
class Source:
    """What is rendered: the model, its default start camera and intrinsics (None: framed from the Gaussians),
    the point presets move about, and the band burnt into its frames (None: no label)."""

    model: GaussianModel
    name: str
    c2w: np.ndarray | None
    intrinsics: Intrinsics | None
    target: np.ndarray | None
    band: str | None


@dataclass
class Cameras:
    """The render's cameras: OpenCV c2w ``[T, 4, 4]`` and K ``[T, 3, 3]`` at ``width`` x ``height``."""

    c2w: np.ndarray
    K: np.ndarray
    width: int
    height: int


def ply_source(path: Path) -> Source:
    """A bare PLY (checked and normalised by ``load_gaussian_ply``); labelled when its header comments say so."""
    if not path.is_file():
        raise ValueError(f"{path} does not exist or is not a file; give a 3D Gaussian Splatting .ply")
    model = load_gaussian_ply(path)
    comments = " ".join(read_ply_header(path).comments)
    band = next((b for b in BANDS_IN_COMMENTS if b in comments), None)
    return Source(model, str(path), None, None, None, band)


def scene_source(store_uri: str, scene_id: str | None) -> Source:
    """The fitted Gaussians of a scene (refined when the refine step ran, as its exports use), its input camera
    (the first camera of its stored path), that camera's intrinsics at the scene's resolution and the scene
    centre. ``scene_id``: an id, a unique prefix or the photo's file name (``readers.resolve_scene``); None picks the
    store's only scene."""
    # deferred: open3d (tasks.readers, tasks.backends) loads only for a stored scene, not a bare PLY
    from navcrafter.tasks.backends import label_band
    from navcrafter.tasks.readers import (
        camera_path,
        load_final_gaussians,
        resolve_scene,
        scene_label,
        scene_run_config,
    )

    store = Store(store_uri, create=False)
    sid = resolve_scene(store, scene_id, default="only", option="--scene")
    scene = store.scene(sid)
    if not scene.status(FIT).complete:
        raise ValueError(f"scene {sid} has no fitted Gaussians; run explore with fit.enabled=true")
    model, step = load_final_gaussians(scene)
    refined = step == REFINE
    path = camera_path(scene, scene_run_config(scene), iterations=1)
    return Source(model, f"scene {sid[:12]}{' (refined)' if refined else ''}", path.c2w[0], path.intrinsics(0),
                  np.asarray(scene.read(PLAN, 1, "centre"), dtype=np.float64), label_band(scene_label(scene)))


def parse_triple(text: str, option: str) -> np.ndarray:
    """Three comma-separated finite numbers (``option`` names the input in the error)."""
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        values = np.zeros(0)
    if values.shape != (3,) or not np.isfinite(values).all():
        raise ValueError(f"{option} expects three comma-separated numbers, e.g. 0,0,0; got {text!r}")
    return values


def parse_background(text: str) -> tuple[float, float, float]:
    """``r,g,b`` in [0, 1], or in 0..255 when a value exceeds 1."""
    rgb = parse_triple(text, "--background")
    if rgb.max() > 1:
        rgb = rgb / 255.0
    if rgb.min() < 0 or rgb.max() > 1:
        raise ValueError(f"--background values must be in [0, 1] (or 0..255), got {text!r}")
    return float(rgb[0]), float(rgb[1]), float(rgb[2])


def parse_up(text: str) -> np.ndarray:
    """The world's up direction ``x,y,z`` (``--up``), non-zero."""
    up = parse_triple(text, "--up")
    if np.linalg.norm(up) < 1e-9:
        raise ValueError("--up must be a non-zero direction")
    return up


def camera_file(trajectory: str, convention: str = "opencv") -> tr.CameraFile | None:
    """The camera file ``trajectory`` names, or None when it is a preset."""
    if trajectory in tr.PRESETS:
        return None
    if not Path(trajectory).exists():
        raise ValueError(f"--trajectory {trajectory!r} is neither a preset ({', '.join(tr.PRESETS)}) nor an "
                         "existing camera file")
    return tr.read_camera_file(trajectory, convention)


def render_size(default: tuple[int, int], width: int | None, height: int | None) -> tuple[int, int]:
    """The render size: the options, one of them with the default's aspect, else the default; even (H.264)."""
    w0, h0 = default
    for name, value in (("--width", width), ("--height", height)):
        if value is not None and value % 2:
            raise ValueError(f"{name} {value} is odd; the MP4 (H.264, yuv420p) needs an even width and height")
    if width is None and height is None:
        width, height = w0, h0
    elif height is None:
        height = max(2, round(width * h0 / w0))
    elif width is None:
        width = max(2, round(height * w0 / h0))
    return int(width) - int(width) % 2, int(height) - int(height) % 2


def render_cameras(src: Source, trajectory: str, camfile: tr.CameraFile | None, frames: int,
                   degrees: float | None = None, amount: float | None = None, width: int | None = None,
                   height: int | None = None, fov: float | None = None, world_up: np.ndarray | None = None,
                   relative: bool = False) -> Cameras:
    """The cameras of a render. The size: ``width`` / ``height``, else the camera file's, else the source's (a
    scene's input camera; ``DEFAULT_SIZE`` for a bare PLY). A preset (``trajectory``, ``frames``, sized by
    ``degrees`` / ``amount``) starts from the source's start camera, or for a bare PLY from a view that frames its
    Gaussians (``fov``, ``world_up``); a camera file's poses are taken as given, or re-based on its first camera
    and placed at the start view (``relative``), at its own intrinsics when it has them."""
    file_size = camfile.size if camfile is not None and camfile.K is not None else None
    base_size = (src.intrinsics.width, src.intrinsics.height) if src.intrinsics is not None else (
        DEFAULT_SIZE, DEFAULT_SIZE)
    w, h = render_size(file_size or base_size, width, height)
    base_K = (src.intrinsics.resize(w, h) if src.intrinsics is not None
              else Intrinsics.from_fov(DEFAULT_FOV if fov is None else fov, w, h))
    if src.c2w is not None:
        frame = tr.Frame(src.c2w, src.target)
    else:
        up = tr.WORLD_UP if world_up is None else world_up
        frame = tr.frame_bounds(*tr.robust_bounds(src.model.means.numpy(), src.model.opacities.numpy()), base_K, up)
    if camfile is None:
        path = tr.preset_trajectory(trajectory, frame, frames, degrees=degrees, amount=amount)
        return Cameras(path.c2w, path.intrinsics(base_K), w, h)
    if degrees is not None or amount is not None:
        raise ValueError("--degrees / --amount size a preset, not a camera file")
    c2w = tr.rebase_path(camfile.c2w, frame.c2w) if relative else camfile.c2w
    K = camfile.intrinsics_at(w, h)
    return Cameras(c2w, np.repeat(base_K.K[None], len(c2w), axis=0) if K is None else K, w, h)


def render_device(device: str, renderer: str):
    """The torch device of ``device`` (auto, cpu, cuda[:N]), checked against ``renderer``."""
    dev = resolve_device(device)
    resolve_backend(renderer, dev)
    return dev


class PngFrames:
    """The written PNGs as the ``[T, H, W, 3]`` sequence ``encode_mp4`` iterates, read back one at a time (the
    frames are never all in memory)."""

    def __init__(self, paths: list[Path], height: int, width: int) -> None:
        self.paths, self.shape = paths, (len(paths), height, width, 3)

    def __len__(self) -> int:
        return len(self.paths)

    def __iter__(self):
        from PIL import Image

        for p in self.paths:
            with Image.open(p) as im:
                yield np.asarray(im.convert("RGB"))


def render_frames(src: Source, cams: Cameras, background: tuple[float, float, float], out: Path, fps: int,
                  device, renderer: str, trajectory: str, on_frame: Callable[[int], None] | None = None
                  ) -> list[Path]:
    """Render ``src`` at ``cams`` one frame at a time to ``out/frames/00000.png ...`` (the frames of an earlier
    render there are removed), ``out/render.mp4`` and ``out/cameras.json`` (the cameras, OpenCV c2w, and the
    label); each frame is labelled with the source's band. ``on_frame(i)`` after each frame. Returns the PNGs."""
    from PIL import Image

    model = src.model.to(device)  # once: render_model's own move is then a no-op
    frames_dir = out / "frames"
    try:
        frames_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RenderError(f"cannot create {frames_dir}: {exc}") from None
    for old in frames_dir.iterdir():  # the frames of an earlier render, which may have been longer
        if _FRAME_PNG.fullmatch(old.name):
            old.unlink()
    c2w, K, width, height = cams.c2w, cams.K, cams.width, cams.height
    paths = []
    for i in range(len(c2w)):
        img = render_model(model, c2w[i:i + 1], K[i:i + 1], width, height, background, device=str(device),
                           renderer=renderer)
        if src.band:
            img = label_frames(img, src.band)
        paths.append(frames_dir / f"{i:05d}.png")
        Image.fromarray(img[0]).save(paths[-1])
        if on_frame is not None:
            on_frame(i)
    (out / "render.mp4").write_bytes(encode_mp4(PngFrames(paths, height, width), fps))
    doc = {"source": src.name, "trajectory": trajectory, "width": width, "height": height, "fps": fps,
           "convention": "OpenCV camera-to-world (x right, y down, z forward)",
           "frames": [{"c2w": c2w[i].tolist(), "K": K[i].tolist()} for i in range(len(c2w))]}
    if src.band:
        doc["label"] = src.band
    (out / "cameras.json").write_text(json.dumps(doc, indent=1))
    return paths

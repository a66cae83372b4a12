"""``navcrafter render``: a 3DGS PLY, or the fitted Gaussians of a scene in a store, rendered along a trajectory
preset or a camera file to PNG frames and an MP4.

The trajectories and camera-file parsers are in ``models/camera/trajectories.py``; the rendering is
``models.gaussians.train.render_model``, one frame at a time.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import numpy as np
import typer

from navcrafter.flows.cli.options import console, err, fail, usage_errors

if TYPE_CHECKING:
    from navcrafter.models.camera.cameras import Intrinsics
    from navcrafter.models.gaussians.model import GaussianModel

DEFAULT_SIZE = 512  # a bare PLY's default width and height
BANDS_IN_COMMENTS = ("SIMULATION", "RANDOM WEIGHTS", "CAMERA CONTROL UNTRAINED")
_FRAME_PNG = re.compile(r"\d{5}\.png")


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


def ply_source(path: Path) -> Source:
    """A bare PLY (checked and normalised by ``load_gaussian_ply``); labelled when its header comments say so."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.gaussians.ply import load_gaussian_ply, read_ply_header

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
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.schemas.layout import FIT, PLAN, REFINE
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.backends import label_band
    from navcrafter.tasks.readers import (
        camera_path,
        load_gaussians,
        load_refined_gaussians,
        resolve_scene,
        scene_label,
        scene_run_config,
    )

    store = Store(store_uri, create=False)
    sid = resolve_scene(store, scene_id, default="only", option="--scene")
    scene = store.scene(sid)
    if not scene.status(FIT).complete:
        raise ValueError(f"scene {sid} has no fitted Gaussians; run explore with fit.enabled=true")
    refined = scene.status(REFINE).complete
    model = load_refined_gaussians(scene) if refined else load_gaussians(scene)
    path = camera_path(scene, scene_run_config(scene), iterations=1)
    return Source(model, f"scene {sid[:12]}{' (refined)' if refined else ''}", path.c2w[0], path.intrinsics(0),
                  np.asarray(scene.read(PLAN, 1, "centre"), dtype=np.float64), label_band(scene_label(scene)))


def _triple(text: str, option: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        values = np.zeros(0)
    if values.shape != (3,) or not np.isfinite(values).all():
        raise ValueError(f"{option} expects three comma-separated numbers, e.g. 0,0,0; got {text!r}")
    return values


def parse_background(text: str) -> tuple[float, float, float]:
    """``r,g,b`` in [0, 1], or in 0..255 when a value exceeds 1."""
    rgb = _triple(text, "--background")
    if rgb.max() > 1:
        rgb = rgb / 255.0
    if rgb.min() < 0 or rgb.max() > 1:
        raise ValueError(f"--background values must be in [0, 1] (or 0..255), got {text!r}")
    return float(rgb[0]), float(rgb[1]), float(rgb[2])


def _size(default: tuple[int, int], width: int | None, height: int | None) -> tuple[int, int]:
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


def render(
    out: Annotated[Path, typer.Option("--out", help="Folder for frames/00000.png ..., render.mp4 and cameras.json.")],
    ply: Annotated[Optional[Path], typer.Argument(
        help="A 3DGS .ply (navcrafter's, the INRIA 3DGS code's or gsplat's). Leave out with --store.")] = None,
    store: Annotated[Optional[str], typer.Option(
        "--store", help="Render the fitted Gaussians of a scene of this store instead of a PLY.")] = None,
    scene: Annotated[Optional[str], typer.Option(
        "--scene", help="Scene id, a unique id prefix or the photo's file name in --store; optional when the store "
                            "has one scene.")] = None,
    trajectory: Annotated[str, typer.Option(
        "--trajectory", help="A preset (orbit, arc, dolly, pan, tilt, zoom, truck, pedestal, spiral, lookaround) "
                             "or a camera file (RealEstate10K .txt, transforms.json, nerfstudio camera_path.json, "
                             "camera-to-world matrices .npy/.json, see --convention).")
    ] = "orbit",
    convention: Annotated[str, typer.Option(
        help="Camera axes of a matrices file (.npy/.json): opencv (x right, y down, z forward) or opengl (x right, "
             "y up, -z forward); the other formats state their own.")] = "opencv",
    frames: Annotated[int, typer.Option(min=1, help="Frames of a preset.")] = 60,
    fps: Annotated[int, typer.Option(min=1, help="Frames per second of the MP4.")] = 24,
    degrees: Annotated[Optional[float], typer.Option(
        help="Angle of orbit/arc/pan/tilt/lookaround (> 0: right, or up for tilt).")] = None,
    amount: Annotated[Optional[float], typer.Option(
        help="Size of dolly/truck/pedestal/spiral as a fraction of the distance to the target (> 0: in, right, up); "
             "the final focal factor of zoom.")] = None,
    width: Annotated[Optional[int], typer.Option(
        min=2, help="Image width (default: 512 for a PLY, the scene's, or the camera file's).")] = None,
    height: Annotated[Optional[int], typer.Option(min=2, help="Image height (as --width).")] = None,
    fov: Annotated[Optional[float], typer.Option(
        help="Horizontal field of view in degrees, bare PLY only (default 60).")] = None,
    up: Annotated[str, typer.Option(help="World up direction x,y,z of a bare PLY (navcrafter: 0,-1,0).")] = "0,-1,0",
    relative: Annotated[bool, typer.Option(
        "--relative/--absolute", help="--absolute: a camera file's poses as given (its world is the model's); "
                                      "--relative: re-based on its first camera, placed at the start view.")
    ] = False,
    background: Annotated[str, typer.Option(help="Background colour r,g,b in [0, 1] (or 0..255).")] = "0,0,0",
    device: Annotated[str, typer.Option(help="auto (CUDA when available), cpu or cuda[:N].")] = "auto",
    renderer: Annotated[str, typer.Option(help="auto, cpu (compiled kernels), torch or gsplat (CUDA).")] = "auto",
) -> None:
    """Render a 3D Gaussian Splatting PLY, or a scene's fitted Gaussians, along a trajectory to PNGs and an MP4.

    Presets start from a framed view: for a PLY, one that fits its Gaussians; for a scene, its input camera.
    """
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.camera import trajectories as tr
    from navcrafter.models.camera.cameras import Intrinsics

    if (ply is None) == (store is None):
        fail("give either a PLY file or --store STORE [--scene ID], not both" if ply else
             "give a PLY file to render, or --store STORE [--scene ID] for a scene's fitted Gaussians")
    if scene is not None and store is None:
        fail("--scene needs --store STORE")
    if fov is not None and store is not None:
        fail("--fov applies to a bare PLY; a scene renders with its own camera's intrinsics")
    if fov is not None and not 0 < fov < 180:
        fail(f"--fov must be in (0, 180) degrees, got {fov}")
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.schemas.store import StoreError

    with usage_errors(ValueError):
        bg = parse_background(background)
        world_up = _triple(up, "--up")
        if np.linalg.norm(world_up) < 1e-9:
            raise ValueError("--up must be a non-zero direction")
        camfile = None if trajectory in tr.PRESETS else _camera_file(trajectory, tr, convention)
    with usage_errors(ValueError, StoreError):
        src = ply_source(ply) if ply is not None else scene_source(store, scene)
    file_size = camfile.size if camfile is not None and camfile.K is not None else None
    base_size = (src.intrinsics.width, src.intrinsics.height) if src.intrinsics is not None else (
        DEFAULT_SIZE, DEFAULT_SIZE)
    with usage_errors(ValueError):
        w, h = _size(file_size or base_size, width, height)
        base_K = (src.intrinsics.resize(w, h) if src.intrinsics is not None
                  else Intrinsics.from_fov(60.0 if fov is None else fov, w, h))
        if src.c2w is not None:
            frame = tr.Frame(src.c2w, src.target)
        else:
            means = src.model.means.numpy()
            frame = tr.frame_bounds(*tr.robust_bounds(means, src.model.opacities.numpy()), base_K, world_up)
        if camfile is None:
            path = tr.preset_trajectory(trajectory, frame, frames, degrees=degrees, amount=amount)
            c2w, K = path.c2w, path.intrinsics(base_K)
        else:
            if degrees is not None or amount is not None:
                raise ValueError("--degrees / --amount size a preset, not a camera file")
            c2w = camfile.c2w
            if relative:
                c2w = tr.rebase_path(c2w, frame.c2w)
            K = camfile.intrinsics_at(w, h)
            K = np.repeat(base_K.K[None], len(c2w), axis=0) if K is None else K
    _render(src, c2w, K, w, h, bg, out, fps, device, renderer, trajectory)


def _camera_file(trajectory: str, tr, convention: str = "opencv"):
    if not Path(trajectory).exists():
        raise ValueError(f"--trajectory {trajectory!r} is neither a preset ({', '.join(tr.PRESETS)}) nor an "
                         "existing camera file")
    return tr.read_camera_file(trajectory, convention)


def _render(src: Source, c2w: np.ndarray, K: np.ndarray, width: int, height: int, bg, out: Path, fps: int,
            device: str, renderer: str, trajectory: str) -> None:
    from PIL import Image
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.gaussians.renderer import resolve_backend, resolve_device
    from navcrafter.models.gaussians.train import render_model
    from navcrafter.models.media import encode_mp4, label_frames

    with usage_errors(RuntimeError, ValueError):
        dev = resolve_device(device)
        resolve_backend(renderer, dev)
    model = src.model.to(dev)  # once: render_model's own move is then a no-op
    frames_dir = out / "frames"
    try:
        frames_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fail(f"cannot create {frames_dir}: {exc}")
    for old in frames_dir.iterdir():  # the frames of an earlier render, which may have been longer
        if _FRAME_PNG.fullmatch(old.name):
            old.unlink()
    paths = []
    columns = (TextColumn("render"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=err) as bar:
        task = bar.add_task("render", total=len(c2w))
        for i in range(len(c2w)):
            img = render_model(model, c2w[i:i + 1], K[i:i + 1], width, height, bg, device=str(dev),
                               renderer=renderer)
            if src.band:
                img = label_frames(img, src.band)
            paths.append(frames_dir / f"{i:05d}.png")
            Image.fromarray(img[0]).save(paths[-1])
            bar.advance(task)
    (out / "render.mp4").write_bytes(encode_mp4(PngFrames(paths, height, width), fps))
    doc = {"source": src.name, "trajectory": trajectory, "width": width, "height": height, "fps": fps,
           "convention": "OpenCV camera-to-world (x right, y down, z forward)",
           "frames": [{"c2w": c2w[i].tolist(), "K": K[i].tolist()} for i in range(len(c2w))]}
    if src.band:
        doc["label"] = src.band
    (out / "cameras.json").write_text(json.dumps(doc, indent=1))
    console.print(f"{src.name}: {len(paths)} frames at {width}x{height} -> {frames_dir}/, {out / 'render.mp4'}"
                  + (f" (labelled {src.band})" if src.band else ""))

"""``navcrafter render``: a 3DGS PLY, or the fitted Gaussians of a scene in a store, rendered along a trajectory
preset or a camera file to PNG frames and an MP4. The command's options only; the tool is ``flows/tools/render.py``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from navcrafter.flows.cli.options import console, err, fail, usage_errors


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
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from navcrafter.flows.tools import render as rt
    from navcrafter.schemas.store import StoreError

    if (ply is None) == (store is None):
        fail("give either a PLY file or --store STORE [--scene ID], not both" if ply else
             "give a PLY file to render, or --store STORE [--scene ID] for a scene's fitted Gaussians")
    if scene is not None and store is None:
        fail("--scene needs --store STORE")
    if fov is not None and store is not None:
        fail("--fov applies to a bare PLY; a scene renders with its own camera's intrinsics")
    if fov is not None and not 0 < fov < 180:
        fail(f"--fov must be in (0, 180) degrees, got {fov}")
    with usage_errors(ValueError):
        bg = rt.parse_background(background)
        world_up = rt.parse_up(up)
        camfile = rt.camera_file(trajectory, convention)
    with usage_errors(ValueError, StoreError):
        src = rt.ply_source(ply) if ply is not None else rt.scene_source(store, scene)
    with usage_errors(ValueError):
        cams = rt.render_cameras(src, trajectory, camfile, frames, degrees=degrees, amount=amount, width=width,
                                 height=height, fov=fov, world_up=world_up, relative=relative)
    with usage_errors(RuntimeError, ValueError):
        dev = rt.render_device(device, renderer)
    columns = (TextColumn("render"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=err) as bar, usage_errors(rt.RenderError):
        task = bar.add_task("render", total=len(cams.c2w))
        paths = rt.render_frames(src, cams, bg, out, fps, dev, renderer, trajectory,
                                 on_frame=lambda _: bar.advance(task))
    console.print(f"{src.name}: {len(paths)} frames at {cams.width}x{cams.height} -> {out / 'frames'}/, "
                  f"{out / 'render.mp4'}" + (f" (labelled {src.band})" if src.band else ""))

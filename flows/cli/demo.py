"""``navcrafter demo-data``: a photo collection to try the workflow on, with hidden ground truth: photos of
generated scenes, or (``--world``) start views of your own scans (models/simulation/worlds)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from navcrafter.flows.cli.options import console, fail

UP_CHOICES = ("auto", "x", "y", "z", "-x", "-y", "-z")


def demo_data(
    folder: Annotated[Path, typer.Argument(help="Folder to write the demo photos into.")],
    kinds: Annotated[str, typer.Option(help="Comma-separated scene kinds: room, street, tabletop.")] =
        "room,street,tabletop",
    per_kind: Annotated[int, typer.Option(min=1, help="Photos (different seeds) per kind.")] = 1,
    seed: Annotated[int, typer.Option(help="First generator seed.")] = 0,
    width: Annotated[int, typer.Option(min=64)] = 640,
    height: Annotated[int, typer.Option(min=64)] = 480,
    world: Annotated[Optional[list[Path]], typer.Option(
        "--world", help="A scan to use as the ground-truth world instead of generated scenes (repeatable): a "
        "textured mesh (OBJ+MTL, PLY, GLB/glTF), a coloured or plain mesh, a point cloud (PLY, PCD) or a folder "
        "with a posed RGB-D sequence (models/simulation/README.md).")] = None,
    views: Annotated[int, typer.Option(min=1, help="Start views (photos) per world.")] = 3,
    up: Annotated[str, typer.Option(help="Up axis of the scans in their files: auto (the floor, found by RANSAC), "
                                    "x, y, z, -x, -y or -z.")] = "auto",
    scale: Annotated[float, typer.Option(help="Scan units to metres (e.g. 0.001 for millimetres).")] = 1.0,
    start: Annotated[Optional[list[Path]], typer.Option(
        "--start", help="Start cameras of a world (one per --world, in order) instead of chosen ones: a "
        "RealEstate10K .txt, a transforms.json or c2w matrices (.npy/.json), as `explore --trajectory` reads "
        "them, in the scan file's own coordinates and units.")] = None,
) -> None:
    """Write a demo collection: photo-like renders of generated scenes (or of your scans, --world), with hidden
    ground truth."""
    if world:
        return _world_demo(folder, world, views, up, scale, start or [], width, height)
    if start:
        fail("--start needs --world (the scans the cameras start in)")
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.simulation.demo import write_demo_collection
    from navcrafter.models.simulation.scenes import KINDS

    chosen = tuple(k.strip() for k in kinds.split(",") if k.strip())
    if bad := [k for k in chosen if k not in KINDS]:
        fail(f"unknown scene kind(s) {bad}; choose from {list(KINDS)}")
    photos = write_demo_collection(folder, chosen, per_kind, seed, width, height)
    console.print(f"wrote {len(photos)} demo photos to {folder} (ground truth in {folder}/.groundtruth/)")
    for p in photos:
        console.print(f"  {p}")


def _world_demo(folder: Path, worlds: list[Path], views: int, up: str, scale: float, starts: list[Path],
                width: int, height: int) -> None:
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.camera.trajectories import read_camera_file
    from navcrafter.models.simulation.worlds import WorldError
    from navcrafter.models.simulation.worlds.demo import StartCameras, write_world_collection
    from navcrafter.schemas.config import PlanConfig

    if up not in UP_CHOICES:
        fail(f"--up {up!r}: choose from {', '.join(UP_CHOICES)}")
    if starts and len(starts) != len(worlds):
        fail(f"{len(starts)} --start files for {len(worlds)} --world scans: give one per world, in the same order")
    cams = []
    for s in starts:
        try:
            cf = read_camera_file(s)
        except ValueError as exc:
            fail(f"--start {s}: {exc}")
        cams.append(StartCameras(str(s), cf.c2w, cf.intrinsics_at(width, height)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            photos = write_world_collection(folder, worlds, views, up=up, scale=scale, starts=cams or None,
                                            r_safe_m=PlanConfig().safe_radius, width=width, height=height)
        except WorldError as exc:
            fail(str(exc))
    for w in caught:
        console.print(f"[yellow]warning:[/yellow] {escape(str(w.message))}", soft_wrap=True, highlight=False)
    console.print(f"wrote {len(photos)} photos of {len(worlds)} scanned world(s) to {folder} (SIMULATION MODE: "
                  f"ground truth in {folder}/.groundtruth/)")
    for p in photos:
        console.print(f"  {p}")

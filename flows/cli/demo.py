"""``navcrafter demo-data``: a photo collection to try the workflow on, with hidden ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from navcrafter.flows.cli.options import console, fail


def demo_data(
    folder: Annotated[Path, typer.Argument(help="Folder to write the demo photos into.")],
    kinds: Annotated[str, typer.Option(help="Comma-separated scene kinds: room, street, tabletop.")] =
        "room,street,tabletop",
    per_kind: Annotated[int, typer.Option(min=1, help="Photos (different seeds) per kind.")] = 1,
    seed: Annotated[int, typer.Option(help="First generator seed.")] = 0,
    width: Annotated[int, typer.Option(min=64)] = 640,
    height: Annotated[int, typer.Option(min=64)] = 480,
) -> None:
    """Write a demo collection: photo-like renders of generated scenes, with hidden ground truth."""
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

"""``navcrafter export``: a finished scene's frames, cameras and fused cloud for other tools (nerfstudio /
splatfacto, gsplat's and other COLMAP-reading 3DGS trainers). The writers are ``flows/tools/interchange.py``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from navcrafter.flows.cli.options import console, fail, usage_errors


def export(
    store: Annotated[str, typer.Argument(help="Store directory or URL.")],
    scene: Annotated[str, typer.Argument(
        help="Scene id, a unique id prefix or the photo's file name; `navcrafter status STORE` lists them.")],
    out: Annotated[Path, typer.Option("--out", help="Folder to write the dataset to (created).")],
    fmt: Annotated[str, typer.Option(
        "--format", help="nerfstudio (transforms.json, images/, sparse_pc.ply) or colmap (sparse/0/*.txt, "
                         "images/).")] = "nerfstudio",
) -> None:
    """Export a finished scene's frames at the fit's cameras (the estimated camera path when the fit did not run)
    and its fused cloud as initial points, as a nerfstudio or COLMAP dataset, with navcrafter_export.json."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.tools.interchange import EXPORTERS, InterchangeError
    from navcrafter.schemas.store import StoreError

    if fmt not in EXPORTERS:
        fail(f"--format {fmt!r} is not one of {', '.join(EXPORTERS)}")
    with usage_errors(InterchangeError, StoreError):
        doc = EXPORTERS[fmt](store, scene, out)
    console.print(f"scene {doc['scene_id'][:12]}: {doc['n_frames']} frames ({doc['width']}x{doc['height']}, "
                  f"{doc['cameras']} cameras) and {doc['n_points']} points -> {out}/ ({fmt})"
                  + (f" [yellow]({escape(doc['label'])})[/yellow]" if doc.get("label") else ""), soft_wrap=True)

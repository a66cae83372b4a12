"""``navcrafter dataset-clips`` and ``navcrafter evaluate-clips``: the video-generation benchmark on dataset clips
(RealEstate10K, DL3DV, Tanks and Temples), for any generator."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markdown import Markdown

from navcrafter.flows.cli.options import EXIT_PARTIAL, console, err, fail, prefect_env, usage_errors


def dataset_clips(
    kind: Annotated[str, typer.Argument(help="'re10k', 'dl3dv' or 'tnt'.")],
    root: Annotated[Path, typer.Argument(help="The dataset's folder (layouts: schemas/datasets/).")],
    out: Annotated[Path, typer.Option("--out", help="Folder for the clips.")],
    clips: Annotated[Optional[int], typer.Option(help="Clips to draw (default: one per sequence).")] = None,
    frames: Annotated[int, typer.Option(help="Frames after the conditioning image (paper: 14).")] = 14,
    resolution: Annotated[int, typer.Option(help="Square size the frames are resized/cropped to.")] = 256,
    seed: Annotated[int, typer.Option(help="Seed of the clip draw.")] = 0,
) -> None:
    """Write benchmark clips (conditioning image, reference frames, cameras) for a video generator."""
    from navcrafter.schemas.datasets import DatasetError, open_dataset
    from navcrafter.tasks.clips import export_clips

    if not root.is_dir():
        fail(f"{root} is not a folder; give the dataset's root folder")
    with usage_errors(DatasetError, ValueError, FileNotFoundError):
        reader = open_dataset(kind, root, num_frames=frames, clips_per_dataset=clips, seed=seed,
                              resolution=resolution)
        keys = export_clips(reader, out)
    console.print(f"wrote {len(keys)} clips to {out}")
    for name, reason in reader.skipped.items():
        err.print(f"[yellow]skipped {name}[/yellow]: {reason}")


def evaluate_clips(
    clips: Annotated[Path, typer.Argument(help="Clips written by `navcrafter dataset-clips`.")],
    generated: Annotated[Path, typer.Argument(help="Generated frames: GENERATED/<clip>/0001.png ...")],
    out: Annotated[Path, typer.Option("--out", help="Folder for evaluations.parquet and report.md.")],
    eval_weights: Annotated[Optional[Path], typer.Option(
        help="Folder of official evaluation weights (LPIPS, FID Inception, FVD I3D).")] = None,
    camera_guidance: Annotated[bool, typer.Option(help="Run COLMAP for R_err/T_err.")] = True,
) -> None:
    """Score generated clips against their dataset clips: PSNR/SSIM/LPIPS, R_err/T_err, FID/FVD."""
    from navcrafter.schemas.config import EvaluationConfig

    cfg = EvaluationConfig(weights_dir=eval_weights, camera_guidance=camera_guidance)
    from navcrafter.tasks.clips import clip_keys

    with usage_errors(FileNotFoundError):
        clip_keys(clips)
    if not generated.is_dir():
        fail(f"{generated} is not a folder of generated clips (GENERATED/<clip>/0001.png ...)")
    prefect_env()
    from navcrafter.flows.evaluate import evaluate_clips as score_clips

    result = score_clips(str(clips), str(generated), str(out), cfg)
    console.print(Markdown(Path(result.report).read_text()))
    console.print(f"report: {result.report}   table: {out}/evaluations.parquet")
    if result.failed:
        err.print(f"[red]{len(result.failed)} clip(s) could not be scored[/red]: "
                  + "; ".join(f"{k}: {v}" for k, v in result.failed.items()))
        raise typer.Exit(EXIT_PARTIAL)

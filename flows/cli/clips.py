"""``navcrafter dataset-clips``, ``generate-clips`` and ``evaluate-clips``: the video-generation benchmark on dataset
clips (RealEstate10K, DL3DV, Tanks and Temples), for our synthesizers or any other generator."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markdown import Markdown

from navcrafter.flows.cli.options import (
    EXIT_PARTIAL,
    ConfigOption,
    PresetOption,
    SetOption,
    console,
    err,
    fail,
    prefect_env,
    run_config,
    usage_errors,
)


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
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.schemas.datasets import DatasetError, open_dataset
    from navcrafter.tasks.clips import export_clips

    if not root.is_dir():
        fail(f"{root} is not a folder; give the dataset's root folder")
    with usage_errors(DatasetError, ValueError, FileNotFoundError):
        options = {}
        if kind == "re10k" and not (root / "test").is_dir() and any(root.glob("*.txt")):
            options["split"] = None  # camera files directly in ROOT (`navcrafter simulate-datasets` writes so)
        reader = open_dataset(kind, root, num_frames=frames, clips_per_dataset=clips, seed=seed,
                              resolution=resolution, **options)
        keys = export_clips(reader, out)
    console.print(f"wrote {len(keys)} clips to {out}")
    for name, reason in reader.skipped.items():
        err.print(f"[yellow]skipped {name}[/yellow]: {reason}")


def evaluate_clips(
    clips: Annotated[Path, typer.Argument(help="Clips written by `navcrafter dataset-clips`.")],
    generated: Annotated[Path, typer.Argument(help="Generated frames: GENERATED/<clip>/0001.png ...")],
    out: Annotated[Path, typer.Option("--out", help="Folder for evaluations.parquet and report.md.")],
    preset: PresetOption = "paper",
    config: ConfigOption = None,
    set_: SetOption = None,
    eval_weights: Annotated[Optional[Path], typer.Option(
        help="Folder of official evaluation weights (LPIPS, FID Inception, FVD I3D).")] = None,
    camera_guidance: Annotated[bool, typer.Option(help="Run COLMAP for R_err/T_err (Table III).")] = True,
    reconstruction: Annotated[bool, typer.Option(
        help="Table IV: fit 3DGS on each clip's generated frames (fit.* settings) and score it at the dataset's "
             "frames (about 1-2 min per clip on 2 cores at the paper preset).")] = True,
) -> None:
    """Score generated clips against their dataset clips: PSNR/SSIM/LPIPS, FID/FVD, R_err/T_err, 3DGS.

    The paper's Tables I, II, III (R_err in radians and T_err per frame, then per-clip sums) and IV.
    """
    cfg = run_config(preset, config, set_, {"evaluation.weights_dir": str(eval_weights) if eval_weights else None,
                                            "evaluation.camera_guidance": camera_guidance})
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.tasks.clips import clip_keys

    with usage_errors(FileNotFoundError):
        clip_keys(clips)
    if not generated.is_dir():
        fail(f"{generated} is not a folder of generated clips (GENERATED/<clip>/0001.png ...)")
    prefect_env()
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.evaluate import evaluate_clips as score_clips

    result = score_clips(str(clips), str(generated), str(out), cfg, reconstruction=reconstruction)
    console.print(Markdown(Path(result.report).read_text()))
    console.print(f"report: {result.report}   table: {out}/evaluations.parquet")
    if result.failed:
        err.print(f"[red]{len(result.failed)} clip(s) could not be scored[/red]: "
                  + "; ".join(f"{k}: {v}" for k, v in result.failed.items()))
        raise typer.Exit(EXIT_PARTIAL)


def generate_clips(
    clips: Annotated[Path, typer.Argument(help="Clips written by `navcrafter dataset-clips`.")],
    out: Annotated[Path, typer.Option("--out", help="Folder for the generated frames: OUT/<clip>/0001.png ...")],
    preset: PresetOption = "paper",
    config: ConfigOption = None,
    set_: SetOption = None,
    backend: Annotated[Optional[str], typer.Option(help="'simulation' (clips of simulated datasets) or 'onnx'.")
                       ] = None,
    models: Annotated[Optional[Path], typer.Option(help="Directory of exported ONNX models (onnx backend).")] = None,
    parallel: Annotated[Optional[int], typer.Option(min=1, help="Clips generated at once.")] = None,
) -> None:
    """Generate each clip's video with the configured synthesizer (4k + 1 frames: 17 for 15 cameras, the first 15
    kept); score them with `navcrafter evaluate-clips CLIPS OUT`. Reruns skip finished clips."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.simulation import LABEL
    from navcrafter.tasks.clips import clip_keys, load_clip
    from navcrafter.tasks.clips.generation import generation_frames

    with usage_errors(FileNotFoundError):
        keys = clip_keys(clips)
    first = load_clip(clips, keys[0])
    H, W = first["condition"].shape[:2]
    overrides = {"backend": backend, "model_dir": str(models) if models else None, "max_parallel_scenes": parallel}
    cfg = run_config(preset, config, set_, overrides)
    if cfg.backend != "simulation":  # an exported synthesizer makes clips of exactly its exported size
        cfg = run_config(preset, config, set_, {**overrides, "synthesis.num_frames": generation_frames(
            len(first["c2w"])), "synthesis.height": H, "synthesis.width": W})
    if cfg.backend == "simulation":
        console.print(f"[bold yellow]{LABEL}.[/bold yellow]")
    prefect_env()
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.clips import generate_clips_local

    run = generate_clips_local(str(clips), str(out), cfg)
    console.print(f"generated {len(run.generated)} clip(s), {len(run.skipped)} already there, into {out}; "
                  f"score them with `navcrafter evaluate-clips {clips} {out} --out DIR`")
    if run.failed:
        err.print(f"[red]{len(run.failed)} clip(s) failed[/red]: "
                  + "; ".join(f"{k}: {v}" for k, v in run.failed.items()))
        raise typer.Exit(EXIT_PARTIAL)

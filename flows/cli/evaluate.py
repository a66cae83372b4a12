"""``navcrafter evaluate``: the paper's evaluation tables for the finished scenes of a store."""

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


def evaluate(
    store: Annotated[str, typer.Argument(help="Store directory or URL of explored scenes.")],
    preset: PresetOption = "paper",
    config: ConfigOption = None,
    set_: SetOption = None,
    eval_weights: Annotated[Optional[Path], typer.Option(
        help="Folder of official evaluation weights (LPIPS, FID Inception, FVD I3D).")] = None,
    parallel: Annotated[Optional[int], typer.Option(min=1, help="Scenes scored at once.")] = None,
) -> None:
    """Score every finished scene: the paper's Tables I-V as Parquet and Markdown in the store.

    I novel-view synthesis, II FID/FVD, III camera pose errors, IV 3DGS, V planning and runtime.

    Table VI (the 3DGS ablation) is benchmarks/fitting.py.

    Frames: evaluation.frame_choice 'first' (default, the paper's: 14 after the conditioning image) or 'spaced'.

    Give the --preset, --config and --set the scenes were explored with.
    """
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.schemas.store import Store, StoreError

    cfg = run_config(preset, config, set_, {"evaluation.weights_dir": str(eval_weights) if eval_weights else None,
                                            "max_parallel_scenes": parallel})
    with usage_errors(StoreError):
        Store(store, create=False)
    prefect_env()
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.evaluate import evaluable_scenes, evaluate_store_local

    if not evaluable_scenes(store)[0]:
        fail(f"{store} has no finished scenes; run `navcrafter explore PHOTOS --store {store}` first")
    result = evaluate_store_local(store, cfg)
    console.print(Markdown(Store(store, create=False).read_bytes(result.report).decode()))
    console.print(f"report: {store}/{result.report}   table: {store}/tables/evaluations/{result.evaluation_id}.parquet")
    if result.failed:
        err.print(f"[red]{len(result.failed)} scene(s) could not be scored[/red]: "
                  + "; ".join(f"{k[:12]}: {v}" for k, v in result.failed.items()))
        raise typer.Exit(EXIT_PARTIAL)

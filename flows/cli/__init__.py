"""The ``navcrafter`` command line: ``app`` (typer) and ``main`` (the console script).

One module per group of commands; what they share (consoles, exit codes, the config options, turning a user's
mistake into a message and the usage exit code) is in ``options``. Commands import their heavy dependencies
(Prefect, torch, the flows) only when they run, so that ``--help`` and usage errors stay quick.
"""

from __future__ import annotations

import os

import typer

from navcrafter.flows.cli import clips, cloud, demo, evaluate, explore, export, models, render, status, train, view
from navcrafter.flows.cli.options import prefect_env

app = typer.Typer(help="NavCrafter: explore 3D scenes from single images, as a resumable batch workflow.",
                  no_args_is_help=True, add_completion=False)
app.add_typer(models.models_app, name="models")
app.command("demo-data")(demo.demo_data)
app.command()(explore.explore)
app.command()(evaluate.evaluate)
app.command()(render.render)
app.command("dataset-clips")(clips.dataset_clips)
app.command("generate-clips")(clips.generate_clips)
app.command("evaluate-clips")(clips.evaluate_clips)
app.command()(status.status)
app.command()(view.view)
app.command()(explore.submit)
app.command("train-camera")(train.train_camera)
app.command("simulate-datasets")(train.simulate_datasets)
app.command("export")(export.export)
app.command("evaluate-cloud")(cloud.evaluate_cloud)

__all__ = ["app", "main"]


def main() -> None:
    """The ``navcrafter`` console script."""
    # torch's OpenMP threads spin-wait after every parallel region (the default policy); beside the compiled CPU
    # rasterizer's threads that starves both (measured: 9x slower fit iterations on 2 cores). Before torch loads.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    prefect_env()
    app()

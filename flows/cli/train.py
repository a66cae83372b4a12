"""``navcrafter train-camera`` (train the camera control) and ``navcrafter simulate-datasets`` (the simulation
data engine: RealEstate10K- and DL3DV-format datasets rendered from procedural scenes with exact cameras)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from navcrafter.flows.cli.options import SetOption, _parse_sets, _validation_lines, console, fail, usage_errors


def _training_config(config: Path | None, sets: list[str] | None, data: list[str] | None):
    """The CameraTrainingConfig: the --config file, then --data KIND=ROOT sources, then --set overrides."""
    import yaml
    from pydantic import ValidationError

    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.schemas.training import CameraTrainingConfig

    raw: dict = {}
    if config is not None:
        if not config.is_file():
            fail(f"--config {config}: no such file")
        try:
            raw = yaml.safe_load(config.read_text()) or {}
        except yaml.YAMLError as exc:
            fail(f"--config {config}: not valid YAML/JSON ({exc})")
        if not isinstance(raw, dict):
            fail(f"--config {config}: must hold a mapping of config keys")
    for item in data or []:
        kind, sep, root = item.partition("=")
        if not sep:
            fail(f"--data expects KIND=ROOT (e.g. re10k=/data/re10k), got {item!r}")
        raw.setdefault("data", {}).setdefault("sources", [])
        raw["data"]["sources"] = [*raw["data"]["sources"], {"kind": kind.strip(), "root": root.strip()}]
    for key, value in _parse_sets(sets or []).items():
        node = raw
        *parents, last = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                fail(f"--set {key}: {p} is not a section")
        node[last] = value
    try:
        return CameraTrainingConfig.model_validate(raw)
    except ValidationError as exc:
        fail(*(f"invalid training configuration: {line}" for line in _validation_lines(exc, CameraTrainingConfig)))


def train_camera(
    run: Annotated[Path, typer.Argument(help="Run folder (created; an existing run resumes).")],
    config: Annotated[Optional[Path], typer.Option("--config", help="YAML/JSON CameraTrainingConfig "
                                                                     "(schemas/training.py).")] = None,
    data: Annotated[Optional[list[str]], typer.Option("--data", help="A dataset, KIND=ROOT (re10k or dl3dv); "
                                                                      "repeatable.")] = None,
    sets: SetOption = None,
    nproc: Annotated[int, typer.Option("--nproc", min=1, help="DDP processes (torchrun; one per GPU).")] = 1,
) -> None:
    """Train NavCrafter's camera control on RealEstate10K / DL3DV clips (resumable), then export it to RUN/control
    for `navcrafter models export-synthesizer --control RUN/control`."""
    cfg = _training_config(config, sets, data)
    if not cfg.data.sources:
        fail("no training data: give --data KIND=ROOT (e.g. --data re10k=/data/re10k) or data.sources in --config; "
             "`navcrafter simulate-datasets OUT` writes simulated ones")
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.train_camera import train_camera as flow
    from navcrafter.schemas.datasets import DatasetError
    from navcrafter.tasks.training.train import TrainingRunError

    with usage_errors(DatasetError, TrainingRunError, FileNotFoundError):
        result = flow(str(run), cfg, nproc)
    v = result["validation"]
    console.print(f"trained to step {result['training']['steps']}; camera gap on {v['clips']} {v['split']} clips: "
                  f"{v['camera_gap']:+.5f} (loss {v['loss_true_cameras']:.5f} with the clips' cameras, "
                  f"{v['loss_shuffled_cameras']:.5f} with shuffled ones)")
    console.print(f"control weights: {result['control']}")


def simulate_datasets(
    out: Annotated[Path, typer.Argument(help="Folder for the datasets (OUT/re10k, OUT/dl3dv).")],
    kinds: Annotated[Optional[list[str]], typer.Option("--kind", help="re10k and/or dl3dv (default both).")] = None,
    sequences: Annotated[int, typer.Option(min=1, help="Sequences per dataset.")] = 8,
    frames: Annotated[int, typer.Option(min=2, help="Frames per sequence.")] = 40,
    resolution: Annotated[int, typer.Option(min=16, help="Square frame size.")] = 64,
    seed: Annotated[int, typer.Option(help="Seed of scenes and trajectories.")] = 0,
) -> None:
    """Render RealEstate10K- and DL3DV-format datasets from procedural scenes with exact cameras (and depth)."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.simulation.datasets import write_dataset

    for i, kind in enumerate(kinds or ["re10k", "dl3dv"]):
        if kind not in ("re10k", "dl3dv"):
            fail(f"--kind {kind!r}: use re10k or dl3dv")
        with usage_errors(ValueError):
            names = write_dataset(out / kind, kind, sequences=sequences, frames=frames, resolution=resolution,
                                  seed=seed + 1000 * i)
        console.print(f"wrote {len(names)} {kind} sequences to {out / kind}")

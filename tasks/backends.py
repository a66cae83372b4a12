"""Which implementation serves the model roles for a run (the run configuration's side of backends).

``simulation``: procedural ground truth stands in for the learned models (demo images only).
``onnx``: exported models run by onnxruntime from ``model_dir`` (models/zoo/modeldir.py: the directory's layout,
labels and the lazily loaded roles). Every output of a run carries ``run_label`` (SIMULATION, RANDOM WEIGHTS,
CAMERA CONTROL UNTRAINED) where it applies.
"""

from __future__ import annotations

from pathlib import Path

from navcrafter.models.roles import Backend
from navcrafter.models.runtime.onnxio import ModelDirError, load_manifest
from navcrafter.models.simulation import LABEL as SIMULATION_LABEL
from navcrafter.models.simulation import simulation_label
from navcrafter.models.simulation.backend import SimulationError, simulation_backend
from navcrafter.models.zoo.modeldir import (  # noqa: F401  (re-exported: the labels and the model directory's roles)
    BANDS,
    CAMERA_CONTROL_UNTRAINED_LABEL,
    RANDOM_WEIGHTS_LABEL,
    ROLE_DIRS,
    _LazyRole,
    model_dir_label,
    model_manifests,
    onnx_backend,
    role_dir,
)
from navcrafter.schemas.config import RunConfig

_onnx_backend = onnx_backend

def onnx_problems(config: RunConfig) -> list[str]:
    """What is missing or inconsistent in ``config.model_dir`` for this run (checked before any work)."""
    root = Path(config.model_dir)
    if not root.is_dir():
        return [f"model directory {root} does not exist; export models into it with "
                f"`navcrafter models export-all {root}` (see models/runtime/README.md)"]
    needed = (["synthesizer", "geometry"] + (["monodepth"] if config.fit.enabled else [])
              + (["refiner"] if config.fit.enabled and config.refine.enabled else []))
    problems = []
    for role in needed:
        try:
            manifest = load_manifest(role_dir(root, role), role, verify=False)
        except (ModelDirError, ValueError) as exc:
            problems.append(str(exc))
            continue
        if role == "synthesizer":
            want = (config.synthesis.num_frames, config.synthesis.height, config.synthesis.width)
            cfg = manifest.get("config", {})
            have = (cfg.get("num_frames"), cfg.get("height"), cfg.get("width"))
            if None not in have and tuple(have) != want:
                problems.append(
                    f"the synthesizer in {role_dir(root, role)} was exported for {have[0]} frames at "
                    f"{have[2]}x{have[1]}, the run asks for {want[0]} at {want[2]}x{want[1]}: set synthesis."
                    f"num_frames/height/width to match or export it again with those sizes")
            model = cfg.get("model", "navcrafter")
            if model != config.synthesis.model:
                problems.append(
                    f"the synthesizer in {role_dir(root, role)} is {model!r}, the run asks for synthesis.model="
                    f"{config.synthesis.model!r}: set synthesis.model={model!r} or export a {config.synthesis.model!r} "
                    f"synthesizer there (navcrafter models export-synthesizer / export-fun-camera)")
    return problems


def run_label(config: RunConfig, scene: dict | None = None) -> str | None:
    """The label every user-facing output of this run must carry, if any. ``scene``: the ``scene`` spec of the
    scene's simulation truth (``readers.truth_scene``), which names a scanned world in simulation mode
    (``models.simulation.simulation_label``); without it, the generated scenes' label."""
    if config.backend == "simulation":
        return simulation_label(scene)
    if config.backend == "onnx" and config.model_dir is not None:
        return model_dir_label(config.model_dir)
    return None


def label_band(label: str | None) -> str | None:
    """The short form of a run label burnt into frames and figures ("SIMULATION", "RANDOM WEIGHTS", ...)."""
    if not label:
        return None
    if label.startswith("SIMULATION") or label == SIMULATION_LABEL:
        return "SIMULATION"
    return BANDS.get(label, label.split(":")[0][:32])


def run_band(config: RunConfig) -> str | None:
    """The short form of ``run_label`` burnt into the frames of videos and figures ("SIMULATION", ...)."""
    label = run_label(config)
    if label is None:
        return None
    return "SIMULATION" if config.backend == "simulation" else BANDS[label]


def create_backend(config: RunConfig, simulation_truth=None) -> Backend:
    """The role implementations for one scene.

    ``simulation_truth`` (a ``SimulationTruth``) is required by, and only used by, the simulation
    backend.
    """
    if config.backend == "simulation":
        if simulation_truth is None:
            raise SimulationError(
                "this image has no simulation ground truth: the simulation backend can only explore "
                "demo images made by `navcrafter demo-data` (their ground truth sits in "
                "<folder>/.groundtruth/). Real photos need exported models and `--backend onnx`.")
        return simulation_backend(simulation_truth, config.simulation)
    if config.backend == "onnx":
        return onnx_backend(str(Path(config.model_dir).resolve()), config.synthesis.model_dump_json())
    raise ValueError(f"unknown backend {config.backend!r}")

"""Backend selection: which implementation serves the model roles for a run."""

from __future__ import annotations

from navcrafter.models.roles import Backend
from navcrafter.schemas.config import RunConfig

ONNX_NOT_BUILT = (
    "the 'onnx' backend (exported Wan2.1 camera-control synthesizer, VGGT geometry, MoGe-2 depth) is "
    "not built yet; it is tracked as its own issues. Until then navcrafter runs in simulation mode only: "
    "use `--backend simulation` on a demo collection made by `navcrafter demo-data`."
)


def create_backend(config: RunConfig, simulation_truth=None) -> Backend:
    """The role implementations for one scene.

    ``simulation_truth`` (a ``SimulationTruth``) is required by, and only used by, the simulation
    backend.
    """
    if config.backend == "simulation":
        from navcrafter.models.simulation.backend import SimulationError, simulation_backend

        if simulation_truth is None:
            raise SimulationError(
                "this image has no simulation ground truth: the simulation backend can only explore "
                "demo images made by `navcrafter demo-data` (their ground truth sits in "
                "<folder>/.groundtruth/). Real photos need exported models and `--backend onnx`.")
        return simulation_backend(simulation_truth, config.simulation)
    if config.backend == "onnx":
        raise NotImplementedError(ONNX_NOT_BUILT)
    raise ValueError(f"unknown backend {config.backend!r}")

"""What every step shares: opening the store, the step's result and error types, the run logger, and the
readers of what several steps read (the scene cloud, the backend, a demo image's ground truth).

How a step runs (cache keys, skipping, committing) is ``tasks.steps``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any

from navcrafter.models.reconstruction.pointcloud import Cloud
from navcrafter.models.roles import Backend
from navcrafter.models.simulation.backend import SimulationTruth
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import GEOMETRY, INGEST, cloud_step
from navcrafter.schemas.store import SceneStore, Store
from navcrafter.tasks.backends import create_backend

_log = logging.getLogger("navcrafter")


def logger():
    """Prefect's run logger inside a flow/task run (shown in the dashboard), else ``navcrafter``."""
    try:
        from prefect.logging import get_run_logger

        return get_run_logger()
    except Exception:
        return _log


class StepError(RuntimeError):
    """A step failed; the message names the scene, the step and the cause."""

    def __init__(self, scene_id: str, step: str, cause: BaseException) -> None:
        self.scene_id, self.step, self.cause = scene_id, step, cause
        super().__init__(f"scene {scene_id[:12]}: step {step} failed: {type(cause).__name__}: {cause}")


@dataclass(frozen=True)
class StepRef:
    scene_id: str
    step: str  # group path, e.g. "iter_2/lift"
    key: str
    exec_id: str
    skipped: bool
    seconds: float
    info: dict[str, Any] = field(default_factory=dict)


_stores: dict[str, Store] = {}
_stores_lock = threading.Lock()


def open_store(uri: str) -> Store:
    """One ``Store`` object per URI per process."""
    with _stores_lock:
        if uri not in _stores:
            _stores[uri] = Store(uri)
        return _stores[uri]


# --------------------------------------------------------------------------------------------------
# Shared readers
# --------------------------------------------------------------------------------------------------
def load_cloud(scene: SceneStore, k: int) -> Cloud:
    """The scene cloud after iteration ``k`` (0 = initial geometry)."""
    spec, kk = cloud_step(k)
    arrays = scene.read_all(spec, kk)
    return Cloud(arrays["cloud_points"], arrays["cloud_colors"], arrays["cloud_confidence"])


def load_backend(scene: SceneStore, config: RunConfig) -> Backend:
    truth = None
    if config.backend == "simulation":
        truth = simulation_truth(scene)
    return create_backend(config, simulation_truth=truth)


def simulation_truth(scene: SceneStore):
    """The hidden ground truth of a demo image, or ``None`` for any other image."""

    record = scene.require_complete(INGEST).attrs.get("simulation_truth")
    if record is None:
        return None
    geo = scene.status(GEOMETRY)
    scale = geo.attrs.get("simulation_world_scale") if geo.complete else None
    return SimulationTruth.from_record(record, world_scale=scale)

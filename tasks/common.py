"""What every step shares: opening the store, cache keys, seeds, the step protocol, backends.

A step is a plain function ``(store_uri, scene_id, [k,] config, run_id) -> StepRef``. It reads its
inputs from the store and writes its outputs there; the ``StepRef`` it returns is small (ids and
numbers), so orchestration never carries arrays.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from navcrafter.models.backends import create_backend
from navcrafter.models.reconstruction.pointcloud import Cloud
from navcrafter.models.roles import Backend
from navcrafter.schemas.config import RunConfig, stable_hash
from navcrafter.schemas.layout import GEOMETRY, INGEST, SCHEMA_VERSION, StepSpec, cloud_step, dependencies
from navcrafter.schemas.store import SceneStore, StepWriter, Store, StoreFull, store_problem
from navcrafter.schemas.tables import utcnow

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


def step_key(scene: SceneStore, step: StepSpec, k: int | None, config: RunConfig) -> str:
    """Cache key: the step, its config section, and the keys of the upstream outputs it reads."""
    deps = [scene.require_complete(s, kk).key
            for s, kk in dependencies(step.name, k, config.iterations, fit=config.fit.enabled,
                                          refine=config.fit.enabled and config.refine.enabled)]
    return stable_hash({"step": step.name, "k": k, "scene": scene.scene_id, "schema": SCHEMA_VERSION,
                        "config": config.step_config(step.name), "deps": deps}, length=32)


def seed_from_key(key: str) -> int:
    """Every random choice of a step is seeded from its key: (scene, step, config, upstream)."""
    return int(key[:15], 16)


def run_step(store_uri: str, scene_id: str, step: StepSpec, k: int | None, config: RunConfig,
             run_id: str, body: Callable[[StepWriter, int, Any], dict[str, Any]],
             prepare: Callable[[], Any] | None = None) -> StepRef:
    """Run ``body`` unless the step's group is already complete with the same key.

    ``prepare()`` (optional) runs before anything is written; its result is passed to ``body``,
    which writes arrays through the writer and returns extra attributes for the commit.
    Runs under the scene's lock, so two runs over one store never write a scene at once: the
    second waits, then finds the step complete and skips it.

    A store that is down or full (``schemas.store.store_problem``) fails the step with a
    ``StepError`` whose cause names the store and the fix (``StoreUnavailable`` / ``StoreFull``).
    """
    try:
        store = open_store(store_uri)
        with store.scene_lock(scene_id):
            return _run_step_locked(store, scene_id, step, k, config, run_id, body, prepare)
    except StepError:
        raise
    except Exception as exc:  # the store failed outside the step's body (opening, key, status)
        problem = store_problem(store_uri, exc)
        if problem is None:
            raise
        raise StepError(scene_id, step.group_path(k), problem) from exc


def run_step_attrs(store_uri: str, scene_id: str, step: StepSpec, config: RunConfig, run_id: str,
                   body: Callable[[StepWriter, int, Any], dict[str, Any]]) -> dict[str, Any]:
    """``run_step`` for a step whose result is its attributes (evaluation, scores): runs or skips it,
    then returns the committed attributes, read back so that a skipped step returns the same."""
    ref = run_step(store_uri, scene_id, step, None, config, run_id, body)
    status = open_store(store_uri).scene(scene_id).status(step)
    if status.key != ref.key:
        raise RuntimeError(f"scene {scene_id[:12]}: {step.path} changed while being read; run again")
    return status.attrs


def _run_step_locked(store: Store, scene_id: str, step: StepSpec, k: int | None, config: RunConfig,
                     run_id: str, body, prepare) -> StepRef:
    scene = store.scene(scene_id)
    path = step.group_path(k)
    key = step_key(scene, step, k, config)
    status = scene.status(step, k)
    if status.complete and status.key == key:
        _record(store, scene_id, path, "skipped", key, status.attrs.get("exec_id"), run_id, config.backend)
        return StepRef(scene_id, path, key, status.attrs["exec_id"], True, 0.0)
    log = logger()
    if status.exists:
        log.info("scene %s: %s is %s; recomputing", scene_id[:12], path,
                 "stale (inputs or config changed)" if status.complete else "incomplete")
    t0 = time.perf_counter()
    writer = None
    try:
        prepared = prepare() if prepare is not None else None
        writer = scene.begin(step, k, key, config.backend)
        attrs = body(writer, seed_from_key(key), prepared) or {}
        seconds = time.perf_counter() - t0
        writer.commit(seconds, **attrs)
    except Exception as exc:
        problem = None if isinstance(exc, StepError) else store_problem(store.uri, exc)
        if isinstance(problem, StoreFull) and writer is not None and store.local:
            with contextlib.suppress(Exception):  # give the disk back what the failed step wrote
                scene.discard(step, k, writer.exec_id)
        cause = problem or exc
        _record(store, scene_id, path, "failed", key, writer.exec_id if writer else None, run_id,
                config.backend, error=f"{type(cause).__name__}: {cause}")
        if isinstance(exc, StepError):
            raise
        raise StepError(scene_id, path, cause) from exc
    _record(store, scene_id, path, "completed", key, writer.exec_id, run_id, config.backend, seconds)
    log.info("scene %s: %s done in %.2fs", scene_id[:12], path, seconds)
    return StepRef(scene_id, path, key, writer.exec_id, False, seconds,
                   {k_: v for k_, v in attrs.items() if isinstance(v, (int, float, str, bool))})


def _record(store: Store, scene_id: str, path: str, event: str, key: str | None, exec_id: str | None,
            run_id: str, backend: str, seconds: float | None = None, error: str | None = None) -> None:
    """Best effort: an event that cannot be written (store down or full) is logged, never raised, so
    it neither hides the step's own error nor fails a step that completed."""
    try:
        store.tables.write("steps", [{"scene_id": scene_id, "step": path, "event": event, "key": key,
                                      "exec_id": exec_id, "run_id": run_id, "backend": backend,
                                      "at": utcnow(), "seconds": seconds, "error": error}])
    except Exception as exc:
        if store_problem(store.uri, exc) is None and not isinstance(exc, OSError):
            raise
        logger().warning("scene %s: the %s event of %s was not recorded in the steps table: %s",
                         scene_id[:12], event, path, store_problem(store.uri, exc) or exc)


# The steps table is an event log for people and tests: the group's completion marker is the truth
# (a process killed between commit and this write leaves a complete step without its event row).

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
    from navcrafter.models.simulation.backend import SimulationTruth

    record = scene.require_complete(INGEST).attrs.get("simulation_truth")
    if record is None:
        return None
    geo = scene.status(GEOMETRY)
    scale = geo.attrs.get("simulation_world_scale") if geo.complete else None
    return SimulationTruth.from_record(record, world_scale=scale)

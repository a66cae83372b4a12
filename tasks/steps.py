"""How a step runs: its context, its cache key, skipping what is complete, committing what it wrote.

Every step is declared once, by its ``StepSpec`` in ``schemas.layout`` (what it writes and reads, which config
keys it, whether it holds a GPU slot, when it runs, its version). Its body is a plain function over a
``StepContext`` (registered by name in ``tasks/bodies.py``): it reads its inputs from ``ctx.scene``, writes its
outputs with ``ctx.write`` and returns the attributes to commit. This module holds the protocol:

* ``execute(store_uri, scene_id, spec, k, config, run_id, body)``: one step, skipped when its group is already
  complete with the same cache key (``schemas.keys``), run under the scene's lock so two runs never write a scene
  at once; ``execute_attrs`` for a step whose result is its attributes.

``tasks/runner.py`` runs steps by name (``run``, ``run_attrs``), orders a scene run (``scene_steps``) and runs one
in a process without Prefect (``run_scene``).

A step's ``StepRef`` is small (ids and numbers), so orchestration never carries arrays.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from navcrafter.models.reconstruction.pointcloud import Cloud
from navcrafter.models.roles import Backend
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.keys import cache_key, dependencies, stable_hash
from navcrafter.schemas.layout import StepSpec
from navcrafter.schemas.store import SceneStore, StepWriter, Store, StoreFull, store_problem
from navcrafter.schemas.tables import utcnow
from navcrafter.tasks.common import StepError, StepRef, load_backend, load_cloud, logger, open_store
from navcrafter.tasks.memory import StepPeaks


@dataclass
class StepContext:
    """What a step's body gets: the scene, the iteration, the config, its seed, and the writer of its group."""

    scene: SceneStore
    k: int | None
    config: RunConfig
    seed: int  # every random choice of a step is seeded from its key (scene, step, config, upstream): step_seed
    writer: StepWriter
    run_id: str
    prepared: Any = None  # what the step's ``prepare`` returned (ingest), else None

    @property
    def scene_id(self) -> str:
        return self.scene.scene_id

    @cached_property
    def backend(self) -> Backend:
        """The model roles of this run (loaded on first use)."""
        return load_backend(self.scene, self.config)

    def cloud(self, k: int) -> Cloud:
        """The scene cloud after iteration ``k`` (0: the initial geometry)."""
        return load_cloud(self.scene, k)

    def write(self, name: str, array: Any) -> None:
        self.writer.write(name, np.asarray(array))

    def write_all(self, **arrays: Any) -> None:
        for name, array in arrays.items():
            self.write(name, array)

    def write_file(self, name: str, data: bytes) -> None:
        self.writer.write_file(name, data)


Body = Callable[[StepContext], dict[str, Any]]


def step_key(scene: SceneStore, spec: StepSpec, k: int | None, config: RunConfig) -> str:
    """Cache key of a step over a store: its config and the stored keys of the outputs it reads."""
    deps = [scene.require_complete(s, kk).key for s, kk in dependencies(spec, k, config)]
    return cache_key(spec, k, scene.scene_id, config, deps)


def seed_from_key(key: str) -> int:
    return int(key[:15], 16)


def step_seed(scene_id: str, spec: StepSpec, k: int | None, config: RunConfig, key: str) -> int:
    """A step's random seed: from its cache key, or with ``simulation.common_random_numbers`` (simulation backend
    only: the option keys no step of another backend) from the base seed, the scene, the step and the iteration
    alone, so runs that differ in any other setting draw the same random numbers at the same step. The key still
    holds every setting (the option included), so caching is unchanged; only the seed's source is."""
    if config.backend == "simulation" and config.simulation.common_random_numbers:
        return seed_from_key(stable_hash({"common_random_numbers": config.seed, "scene": scene_id,
                                          "step": spec.name, "k": k}, length=32))
    return seed_from_key(key)


# --------------------------------------------------------------------------------------------------
# Running one step
# --------------------------------------------------------------------------------------------------
def execute_attrs(store_uri: str, scene_id: str, spec: StepSpec, config: RunConfig, run_id: str,
                  body: Body) -> dict[str, Any]:
    """``execute`` for a step whose result is its attributes (evaluation, scores): runs or skips it, then returns
    the committed attributes, read back so that a skipped step returns the same."""
    ref = execute(store_uri, scene_id, spec, None, config, run_id, body)
    status = open_store(store_uri).scene(scene_id).status(spec)
    if status.key != ref.key:
        raise RuntimeError(f"scene {scene_id[:12]}: {spec.path} changed while being read; run again")
    return status.attrs


def execute(store_uri: str, scene_id: str, spec: StepSpec, k: int | None, config: RunConfig, run_id: str,
            body: Body, prepare: Callable[[], Any] | None = None) -> StepRef:
    """Run ``body`` unless the step's group is already complete with the same key.

    ``prepare()`` (optional) runs before anything is written; its result reaches the body as ``ctx.prepared``.
    Runs under the scene's lock, so two runs over one store never write a scene at once: the second waits, then
    finds the step complete and skips it. A store that is down or full (``schemas.store.store_problem``) fails
    the step with a ``StepError`` whose cause names the store and the fix (``StoreUnavailable`` / ``StoreFull``).
    """
    try:
        store = open_store(store_uri)
        with store.scene_lock(scene_id):
            return _execute_locked(store, scene_id, spec, k, config, run_id, body, prepare)
    except StepError:
        raise
    except Exception as exc:  # the store failed outside the step's body (opening, key, status)
        problem = store_problem(store_uri, exc)
        if problem is None:
            raise
        raise StepError(scene_id, spec.group_path(k), problem) from exc


def _execute_locked(store: Store, scene_id: str, spec: StepSpec, k: int | None, config: RunConfig, run_id: str,
                    body: Body, prepare: Callable[[], Any] | None) -> StepRef:
    scene = store.scene(scene_id)
    path = spec.group_path(k)
    key = step_key(scene, spec, k, config)
    status = scene.status(spec, k)
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
        writer = scene.begin(spec, k, key, config.backend)
        ctx = StepContext(scene, k, config, step_seed(scene_id, spec, k, config, key), writer, run_id, prepared)
        with StepPeaks() as peaks:
            try:
                attrs = body(ctx) or {}
            finally:  # one step's models at a time (the peak above includes loading them)
                if config.release_models and "backend" in ctx.__dict__:
                    ctx.backend.release()
        seconds = time.perf_counter() - t0
        attrs = {**peaks.attrs(), **attrs}  # the step's own figure (the fit's: its training alone) wins
        writer.commit(seconds, **attrs)
    except Exception as exc:
        problem = None if isinstance(exc, StepError) else store_problem(store.uri, exc)
        if isinstance(problem, StoreFull) and writer is not None and store.local:
            with contextlib.suppress(Exception):  # give the disk back what the failed step wrote
                scene.discard(spec, k, writer.exec_id)
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
    it neither hides the step's own error nor fails a step that completed. The steps table is an event log for
    people and tests: the group's completion marker is the truth (a process killed between commit and this write
    leaves a complete step without its event row)."""
    try:
        store.tables.write("steps", [{"scene_id": scene_id, "step": path, "event": event, "key": key,
                                      "exec_id": exec_id, "run_id": run_id, "backend": backend,
                                      "at": utcnow(), "seconds": seconds, "error": error}])
    except Exception as exc:
        if store_problem(store.uri, exc) is None and not isinstance(exc, OSError):
            raise
        logger().warning("scene %s: the %s event of %s was not recorded in the steps table: %s",
                         scene_id[:12], event, path, store_problem(store.uri, exc) or exc)


# --------------------------------------------------------------------------------------------------
# The order of a scene's steps

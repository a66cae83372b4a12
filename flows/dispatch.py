"""A collection's scenes as flow runs of an ``explore-scene`` deployment (e.g. on a GPU work pool).

``explore_collection(..., scene_deployment="explore-scene/NAME")`` starts each ingested scene with
``run_deployment`` (a child of the collection run, ``timeout=0``) instead of an in-process subflow,
keeps at most ``config.max_parallel_scenes`` of them in flight, and polls their states. What a scene
produced is read back from the store, never from Prefect (its results are not persisted): the scene
run's final manifest row (done or failed, written by ``explore_scene``). A scene run that ended
CRASHED, FAILED or CANCELLED without writing that row is recorded as failed with the Prefect state's
message. Only parameters (store URI, scene id, config, run id, sources) pass through the server.
"""

from __future__ import annotations

import time
from pathlib import Path

from prefect.logging import get_run_logger
from prefect.runtime import flow_run

from navcrafter.flows.tools.report import SceneResult, manifest_rows_for, scene_result, write_manifest
from navcrafter.schemas.config import RunConfig
from navcrafter.tasks.common import open_store

POLL_SECONDS = 2.0  # how often the collection run reads the states of its scene runs
FINAL_STATUSES = ("done", "failed")  # manifest statuses that only a finished scene run writes


class DispatchError(RuntimeError):
    """Scenes cannot be dispatched (no such deployment, no server); the message says how to fix it."""


def store_location(store: str) -> str:
    """Scene runs run elsewhere (another working directory): a local store path must be absolute."""
    return store if "://" in store else str(Path(store).expanduser().resolve())


def scene_parameters(store: str, scene_id: str, config: RunConfig, run_id: str, sources: list[str]) -> dict:
    """The parameters of one scene's flow run (``explore_scene``'s signature, as JSON)."""
    return {"store": store_location(store), "scene_id": scene_id, "config": config.model_dump(mode="json"),
            "run_id": run_id, "sources": sources}


def check_scene_deployment(name: str) -> None:
    """Fail early, with the fix, when ``name`` is not a deployment on the Prefect server."""
    from prefect.client.orchestration import get_client
    from prefect.exceptions import ObjectNotFound
    from prefect.settings import get_current_settings

    if "/" not in name:
        raise DispatchError(f"scene deployment {name!r} must be 'FLOW/NAME', e.g. 'explore-scene/explore-scene'")
    try:
        with get_client(sync_client=True) as client:
            client.read_deployment_by_name(name)
    except ObjectNotFound:
        raise DispatchError(
            f"no deployment {name!r} on the Prefect server at {get_current_settings().api.url}; create it "
            f"with `navcrafter submit ... --work-pool POOL --scene-pool GPU_POOL` (it deploys "
            f"flows/explore.py:explore_scene from this checkout), or `prefect deploy --all --prefect-file "
            f"deploy/prefect.yaml`") from None


class _FinalRows:
    """This run's final manifest rows (done or failed) by scene, read incrementally (only table files
    not read before), so polling costs one listing plus the new files, however large the store."""

    def __init__(self, store: str, run_id: str) -> None:
        self.tables, self.run_id = open_store(store).tables, run_id
        self.seen: set[str] = set()
        self.rows: dict[str, dict] = {}

    def refresh(self) -> None:
        for _ in range(5):
            new = [f for f in self.tables.files("manifest") if f not in self.seen]
            try:
                table = self.tables.read("manifest", files=new)
            except FileNotFoundError:  # merged by a concurrent compaction: its merged file is listed next
                continue
            self.seen.update(new)
            for r in table.to_pylist():
                if r["run_id"] == self.run_id and r["status"] in FINAL_STATUSES:
                    self.rows[r["scene_id"]] = r
            return


def result_from_row(row: dict, sources: list[str]) -> SceneResult:
    return SceneResult(row["scene_id"], sources, row["status"], step=row["step"], error=row["error"],
                       backend=row["backend"] or "", seconds=row["seconds"] or 0.0,
                       timings=dict(row["timings"] or []), metrics=dict(row["metrics"] or []),
                       outputs=row["outputs"])


def result_without_row(store: str, scene_id: str, sources: list[str], config: RunConfig, run_id: str,
                       run_name: str, state) -> SceneResult:
    """A scene run that ended without recording its end (killed, crashed, cancelled): failed, with the
    Prefect state's message and the last step the store shows complete; recorded in the manifest."""
    message = (state.message or "no message") if state is not None else "no state"
    kind = state.type.value if state is not None else "UNKNOWN"
    result = scene_result(open_store(store).scene(scene_id), sources, config, "failed",
                          error=f"scene run {run_name} ended {kind}: {message}")
    write_manifest(store, manifest_rows_for(result, run_id))
    return result


def dispatch_scenes(deployment: str, store: str, items: list[tuple[str, list[str]]], config: RunConfig,
                    run_id: str) -> list[SceneResult]:
    """Run each ``(scene_id, sources)`` as a flow run of ``deployment``, at most
    ``config.max_parallel_scenes`` at once (the next starts as soon as any one ends); wait for all."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.deployments import run_deployment

    logger = get_run_logger()
    tags = sorted({*(flow_run.tags or []), "navcrafter", "scene", f"collection-{run_id[:8]}"})
    pending = list(items)
    in_flight: dict = {}  # flow run id -> (scene id, sources, run name)
    results: dict[str, SceneResult] = {}
    rows = _FinalRows(store, run_id)

    def start(scene_id: str, sources: list[str]) -> None:
        name = f"scene-{scene_id[:12]}"
        try:
            run = run_deployment(deployment, parameters=scene_parameters(store, scene_id, config, run_id, sources),
                                 flow_run_name=name, tags=tags, timeout=0, as_subflow=True)
        except Exception as exc:  # the server refused it: this scene fails, the others go on
            result = SceneResult(scene_id, sources, "failed", step="ingest", backend=config.backend,
                                 error=f"could not start a flow run of {deployment}: {exc}")
            write_manifest(store, manifest_rows_for(result, run_id))
            results[scene_id] = result
            return
        logger.info("scene %s (%s): flow run %s (%s) of %s", scene_id[:12], Path(sources[0]).name, run.name,
                    run.id, deployment)
        in_flight[run.id] = (scene_id, sources, run.name)

    with get_client(sync_client=True) as client:
        while pending or in_flight:
            while pending and len(in_flight) < config.max_parallel_scenes:
                start(*pending.pop(0))
            if not in_flight:
                continue
            time.sleep(POLL_SECONDS)
            runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=list(in_flight))))
            states = {r.id: r.state for r in runs}
            ended = {i: states.get(i) for i in in_flight  # a run deleted meanwhile has ended too
                     if i not in states or (states[i] is not None and states[i].is_final())}
            if ended:
                rows.refresh()
            for fr_id, state in ended.items():
                scene_id, sources, name = in_flight.pop(fr_id)
                row = rows.rows.get(scene_id)
                results[scene_id] = (result_from_row(row, sources) if row is not None else
                                     result_without_row(store, scene_id, sources, config, run_id, name, state))
                logger.info("scene %s: %s (flow run %s ended %s)", scene_id[:12], results[scene_id].status,
                            name, state.type.value if state is not None else "deleted")
    return [results[sid] for sid, _ in items]

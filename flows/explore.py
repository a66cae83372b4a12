"""Prefect flows: thin orchestration of the steps in ``navcrafter.tasks``.

* ``explore_collection(photos, store, config)`` ingests every file of a collection and explores each
  valid image as its own ``explore_scene`` flow run, several at once; a failing image is recorded in
  the manifest and never stops the others.
* ``explore_scene(store, scene_id, config, run_id, sources)``: initial geometry, then N x (plan ->
  synthesize -> lift), then (fit, when built) and export. Each step is a Prefect task whose body
  skips itself when its group in the store is already complete: rerunning after a crash resumes.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from pathlib import PurePath

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.runtime import flow_run, task_run
from prefect.task_runners import ThreadPoolTaskRunner

from navcrafter.models.backends import ONNX_NOT_BUILT
from navcrafter.schemas.config import RunConfig
from navcrafter.tasks import evaluate, export, fit, geometry, ingest, lift, plan, synthesize
from navcrafter.tasks.common import StepError, open_store
from navcrafter.tasks.pipeline import scene_steps
from navcrafter.tasks.report import (
    SceneResult,
    last_step,
    manifest_rows_for,
    plan_artifact_markdown,
    step_timings,
    summary_markdown,
    write_manifest,
    write_summary,
)

TRANSIENT = (OSError, TimeoutError, ConnectionError)


def _transient(task_, task_run_, state) -> bool:
    """Retry only errors that can go away (I/O, network); never bad input or bugs."""
    try:
        state.result()
    except StepError as exc:
        return isinstance(exc.cause, TRANSIENT)
    except TRANSIENT:
        return True
    except Exception:
        return False
    return False


def _short(scene_id: str) -> str:
    return scene_id[:12]


def _step_run_name() -> str:
    p = task_run.parameters
    k = p.get("k")
    return f"{task_run.task_name}{f'-{k}' if k is not None else ''}-{_short(p.get('scene_id', ''))}"


def _source_run_name(prefix: str):
    return lambda: f"{prefix}-{PurePath(task_run.parameters['source']).name}"


def _scene_run_name() -> str:
    return f"scene-{_short(flow_run.parameters['scene_id'])}"


_SOURCE = {"retries": 2, "retry_delay_seconds": [2, 10], "retry_condition_fn": _transient,
           "persist_result": False}
_STEP = {**_SOURCE, "task_run_name": _step_run_name}
identify_task = task(ingest.identify, name="identify", task_run_name=_source_run_name("identify"), **_SOURCE)
ingest_task = task(ingest.ingest, name="ingest", task_run_name=_source_run_name("ingest"), **_SOURCE)
# Steps that run learned models carry this tag, so a Prefect tag concurrency limit bounds how many
# run at once across all flows and workers (one per GPU): `prefect concurrency-limit create
# navcrafter-gpu <number of GPUs>`. Planning, export and evaluation are CPU work and stay unbounded.
GPU_TAG = "navcrafter-gpu"
_GPU = {**_STEP, "tags": [GPU_TAG]}
STEP_TASKS = {  # Prefect tasks by step name (the order of steps is tasks.pipeline.scene_steps)
    "geometry": task(geometry.initial_geometry, name="geometry", **_GPU),
    "plan": task(plan.plan, name="plan", **_STEP),
    "synthesize": task(synthesize.synthesize, name="synthesize", **_GPU),
    "lift": task(lift.lift, name="lift", **_GPU),
    "fit": task(fit.fit, name="fit", **_GPU),
    "export": task(export.export, name="export", **_STEP),
}
evaluate_task = task(evaluate.evaluate_scene, name="evaluate", **_STEP)


def publish_plan_artifact(store: str, scene_id: str, k: int) -> None:
    markdown = plan_artifact_markdown(store, scene_id, k)
    if markdown:
        create_markdown_artifact(key=f"plan-{_short(scene_id)}-{k}", markdown=markdown,
                                 description=f"planner state, scene {_short(scene_id)}, iteration {k}")


def preflight(config: RunConfig) -> list[str]:
    """What the configuration asks for that is not built yet (checked before any work starts)."""
    problems = []
    if config.backend == "onnx":
        problems.append(ONNX_NOT_BUILT)
    if config.fit.enabled:
        problems.append(fit.NOT_BUILT)
    return problems


@dataclass
class CollectionResult:
    run_id: str
    scenes: list[SceneResult]
    summary: str  # store-relative path of the Markdown summary


class SceneFailed(RuntimeError):
    """A scene run failed; carries its full result (failing step, timings, error) to the caller."""

    def __init__(self, result: SceneResult) -> None:
        self.result = result
        super().__init__(result.error)


@flow(name="explore-scene", flow_run_name=_scene_run_name, persist_result=False)
def explore_scene(store: str, scene_id: str, config: RunConfig, run_id: str,
                  sources: list[str] | None = None) -> SceneResult:
    """Explore one ingested scene; records its manifest rows (running, then done or failed)."""
    sources = sources or [scene_id]
    write_manifest(store, manifest_rows_for(SceneResult(scene_id, sources, "running", backend=config.backend),
                                            run_id))
    metrics: dict[str, float] = {}
    failure: Exception | None = None
    try:
        for step in scene_steps(config):
            STEP_TASKS[step.spec.name](store_uri=store, scene_id=scene_id, config=config, run_id=run_id,
                                       **step.kwargs())
            if step.spec.name == "plan":
                publish_plan_artifact(store, scene_id, step.k)
        metrics = evaluate_task(store, scene_id, config, run_id)
    except Exception as exc:  # recorded, then raised so that the flow run shows as failed
        failure = exc
    scene = open_store(store).scene(scene_id)
    timings = step_timings(scene, config)
    result = SceneResult(scene_id, sources, "done" if failure is None else "failed",
                         step=last_step(scene, config), backend=config.backend,
                         seconds=sum(timings.values()), timings=timings, metrics=metrics)
    if failure is None:
        result.outputs = f"scenes/{scene_id}/exports"
    else:
        result.step = getattr(failure, "step", result.step)
        result.error = str(failure)
    write_manifest(store, manifest_rows_for(result, run_id))
    create_markdown_artifact(key=f"scene-{_short(scene_id)}", markdown=summary_markdown(run_id, config, [result]),
                             description=f"navcrafter scene {_short(scene_id)} ({config.backend})")
    if failure is not None:
        raise SceneFailed(result) from failure
    return result


@task(name="scene", task_run_name=lambda: f"scene-{_short(task_run.parameters['scene_id'])}",
      persist_result=False)
def scene_task(store: str, scene_id: str, config: RunConfig, run_id: str, sources: list[str]) -> SceneResult:
    """Runs the scene as its own flow run; a failed scene is returned as data, not raised."""
    try:
        return explore_scene(store, scene_id, config, run_id, sources)
    except SceneFailed as exc:
        return exc.result


@flow(name="explore-collection", persist_result=False,
      task_runner=ThreadPoolTaskRunner(max_workers=2))
def explore_collection(photos: str, store: str, config: RunConfig) -> CollectionResult:
    """Explore every image of a collection into ``store``; one result per image (or per scene, when
    several files hold the same image).

    At most ``config.max_parallel_scenes`` scenes run at once (the thread pool, 2 by default, can be
    resized with ``with_options``; the CLI sizes it to the same number).
    """
    problems = preflight(config)
    if problems:
        raise NotImplementedError(" ".join(problems))
    run_id = str(flow_run.id or uuid.uuid4().hex)
    sources = ingest.list_collection(photos)
    if not sources:
        raise ValueError(f"the collection {photos} holds no files")
    results: list[SceneResult] = []

    def fail(scene_id: str | None, srcs: list[str], res) -> None:
        error = res.error if isinstance(res, ingest.IngestResult) else f"ingest crashed: {res!r}"
        failed = SceneResult(scene_id or "", srcs, "failed", step="ingest", error=error, backend=config.backend)
        write_manifest(store, manifest_rows_for(failed, run_id))
        results.append(failed)

    # hash every file, then ingest each distinct image once (files with equal bytes share a scene)
    by_scene: dict[str, list[str]] = {}
    for source, fut in [(s, identify_task.submit(s, config)) for s in sources]:
        fut.wait()
        res = fut.state.result(raise_on_failure=False)
        if isinstance(res, ingest.IngestResult) and res.ok:
            by_scene.setdefault(res.scene_id, []).append(source)
        else:
            fail(getattr(res, "scene_id", None), [source], res)
    ingests = {sid: ingest_task.submit(store, ingest.primary_source(srcs, sid), config, run_id)
               for sid, srcs in by_scene.items()}
    for sid, fut in ingests.items():
        fut.wait()
        res = fut.state.result(raise_on_failure=False)
        if isinstance(res, ingest.IngestResult) and res.ok:
            write_manifest(store, manifest_rows_for(
                SceneResult(sid, by_scene[sid], "pending", step="ingest", backend=config.backend), run_id))
        else:
            fail(sid, by_scene.pop(sid), res)
    # at most max_parallel_scenes scenes in flight, whatever the task runner's size (deployment runs
    # use the decorator's pool; scene i + n starts when scene i is done)
    items = list(by_scene.items())
    n = config.max_parallel_scenes
    futures = {sid: scene_task.submit(store, sid, config, run_id, srcs) for sid, srcs in items[:n]}
    for i, (sid, _) in enumerate(items):
        fut = futures[sid]
        fut.wait()
        if i + n < len(items):
            nxt, srcs = items[i + n]
            futures[nxt] = scene_task.submit(store, nxt, config, run_id, srcs)
        res = fut.state.result(raise_on_failure=False)
        if not isinstance(res, SceneResult):  # the orchestration itself broke for this scene
            res = SceneResult(sid, by_scene[sid], "failed", error=f"scene run crashed: {res!r}",
                              backend=config.backend)
            write_manifest(store, manifest_rows_for(res, run_id))
        results.append(res)
    order = {s: i for i, s in enumerate(sources)}
    results.sort(key=lambda r: order.get(r.sources[0], 0))
    tables = open_store(store).tables
    for name in ("manifest", "steps"):
        tables.compact(name)
    md = write_summary(store, run_id, config, results)
    create_markdown_artifact(key="run-summary", markdown=md, description="navcrafter run summary")
    return CollectionResult(run_id, results, f"runs/{run_id}/summary.md")

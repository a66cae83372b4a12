"""Prefect flows: thin orchestration of the steps in ``navcrafter.tasks``.

* ``explore_collection(photos, store, config)`` ingests every file of a collection and explores each
  valid image as its own ``explore_scene`` flow run, several at once; a failing image is recorded in
  the manifest and never stops the others. With ``scene_deployment`` the scenes are flow runs of that
  deployment (e.g. on a GPU work pool) instead of in-process subflows (``flows/dispatch.py``).
* ``explore_scene(store, scene_id, config, run_id, sources)``: the scene's steps in the order the step specs
  give (``tasks.runner.scene_steps``: initial geometry, then N x (plan -> synthesize -> lift), then fit and
  refine when enabled, and export), then the evaluation. Each step is a Prefect task derived from its spec
  (``STEP_TASKS``) whose body skips itself when its group in the store is already complete: rerunning after a
  crash resumes.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from pathlib import PurePath

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.concurrency.sync import concurrency
from prefect.runtime import flow_run, task_run
from prefect.task_runners import ThreadPoolTaskRunner

from navcrafter.flows import dashboard, dispatch
from navcrafter.flows.tools.report import (
    SceneResult,
    manifest_rows_for,
    plan_artifact_markdown,
    scene_result,
    summary_markdown,
    write_manifest,
    write_summary,
)
from navcrafter.models.threads import one_blas_thread
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import STEPS, StepSpec
from navcrafter.schemas.store import StoreFull, StoreUnavailable, store_problem
from navcrafter.tasks import ingest, runner
from navcrafter.tasks.backends import onnx_problems
from navcrafter.tasks.common import StepError, logger, open_store
from navcrafter.tasks.runner import scene_steps

TRANSIENT = (OSError, TimeoutError, ConnectionError, StoreUnavailable)


def _transient(task_, task_run_, state) -> bool:
    """Retry only errors that can go away (I/O, network, the store unreachable); never bad input or
    bugs, and never a full disk (``StoreFull``): it does not free itself within the retry delays, and
    each retry would recompute the step only to fill the disk again; the error says to free space."""
    try:
        state.result()
    except Exception as exc:
        cause = exc.cause if isinstance(exc, StepError) else exc
        problem = store_problem("", cause)  # botocore/aiohttp errors are not OSError: classify them
        if problem is not None:
            return not isinstance(problem, StoreFull)
        return isinstance(cause, TRANSIENT)
    return False


def _best_effort(store: str, what: str, fn, *args, notes: list[str] | None = None):
    """Bookkeeping (manifest rows, summaries, compaction, artifacts) with the store down or full: the
    failure is logged (and added to ``notes``) instead of raised, so that it never turns a scene's
    result into a crash nor hides what happened; a rerun writes it again. Other errors are raised."""
    try:
        return fn(*args)
    except Exception as exc:
        problem = store_problem(store, exc)
        if problem is None and not isinstance(exc, OSError):
            raise
        message = f"{what} not written: {problem or exc}"
        logger().warning(message)
        if notes is not None:
            notes.append(message)
        return None


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
# Steps whose spec says ``gpu`` occupy one slot of the Prefect global concurrency limit named by
# `config.gpu_limit` (e.g. `prefect gcl create navcrafter-gpu --limit <number of GPUs>`), which bounds
# how many run at once across all flows and workers. Planning, export and evaluation are CPU work and
# stay unbounded. No limit configured: no API call at all (a Prefect *tag* would cost one per task run,
# whether or not a limit exists: ~0.5 s per step on a busy server, measured).
def in_gpu_slot(spec: StepSpec, config: RunConfig, call):
    """``call()``, inside a slot of ``config.gpu_limit`` when the step holds one (``spec.gpu``)."""
    if spec.gpu and config.gpu_limit is not None:
        with concurrency(config.gpu_limit, occupy=1, strict=True):
            return call()
    return call()


def _step_task(spec: StepSpec):
    """The Prefect task of a step, derived from its spec: runs ``tasks.runner.run`` (or ``run_attrs`` for a step
    whose result is its attributes), inside a GPU slot when the spec says so."""

    def run(store_uri: str, scene_id: str, config: RunConfig, run_id: str, k: int | None = None):
        if spec.stage == "scene":
            return in_gpu_slot(spec, config, lambda: runner.run(store_uri, scene_id, spec.name, config, run_id, k))
        return in_gpu_slot(spec, config, lambda: runner.run_attrs(store_uri, scene_id, spec.name, config, run_id))

    run.__name__ = run.__qualname__ = spec.name
    run.__doc__ = spec.doc
    return task(run, name=spec.name, **_STEP)


STEP_TASKS = {name: _step_task(spec) for name, spec in STEPS.items() if spec.stage in ("scene", "report")}


def publish_plan_artifact(store: str, scene_id: str, k: int) -> None:
    """The planner's dashboard view. Never fails the scene: with the store down the view is skipped, and
    with the Prefect server down the call blocks while Prefect's client retries (about a minute), then
    is skipped, so the steps go on into the store (a rerun or resubmission finds them complete)."""
    markdown = _best_effort(store, f"plan artifact {k}", plan_artifact_markdown, store, scene_id, k)
    if markdown:
        try:
            create_markdown_artifact(key=f"plan-{_short(scene_id)}-{k}", markdown=markdown,
                                     description=f"planner state, scene {_short(scene_id)}, iteration {k}")
        except Exception as exc:  # the Prefect API unreachable past its client's retries
            logger().warning("scene %s: plan artifact %d not published: %s", _short(scene_id), k, exc)


def preflight(config: RunConfig) -> list[str]:
    """What the configuration asks for that cannot work here, checked before any work starts (rules between
    config fields are the config's own validator, ``RunConfig._check``): the onnx model directory, and that a
    named ``gpu_limit`` exists on the Prefect server."""
    problems = []
    if config.backend == "onnx":
        problems.extend(onnx_problems(config))
    problem = gpu_limit_problem(config)
    if problem:
        problems.append(problem)
    return problems


def gpu_limit_problem(config: RunConfig) -> str | None:
    """A named GPU limit must exist on the server (a typo would otherwise fail every model step)."""
    if config.gpu_limit is None:
        return None
    from prefect.client.orchestration import get_client
    from prefect.exceptions import ObjectNotFound

    with get_client(sync_client=True) as client:
        try:
            client.read_global_concurrency_limit_by_name(config.gpu_limit)
        except ObjectNotFound:
            return (f"gpu_limit {config.gpu_limit!r} names no global concurrency limit on the Prefect server; "
                    f"create it with `prefect gcl create {config.gpu_limit} --limit <number of GPUs>` "
                    "or unset gpu_limit")
    return None


@dataclass
class CollectionResult:
    run_id: str
    scenes: list[SceneResult]
    summary: str  # store-relative path of the Markdown summary ("" when it could not be written)
    store_errors: list[str] = field(default_factory=list)  # bookkeeping the store refused (down, full)


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
    _best_effort(store, "manifest", write_manifest, store,
                 manifest_rows_for(SceneResult(scene_id, sources, "running", backend=config.backend), run_id))
    dashboard.tag_scene_run(store, scene_id)
    order = scene_steps(config)
    progress = dashboard.SceneProgress(scene_id, len(order) + 1)  # the steps, then the evaluation
    metrics: dict[str, float] = {}
    failure: Exception | None = None
    try:
        runner.record_run_config(store, scene_id, config, run_id)  # the tools read it (render, view, export)
        for step in order:
            STEP_TASKS[step.spec.name](store, scene_id, config, run_id, **step.kwargs())
            progress.advance()
            if step.spec.name == "plan":
                publish_plan_artifact(store, scene_id, step.k)
        evaluation = STEP_TASKS["evaluate"](store, scene_id, config, run_id)
        metrics = {k: float(v) for k, v in evaluation["metrics"].items()}
        progress.advance()
    except Exception as exc:  # recorded, then raised so that the flow run shows as failed
        failure = exc
    status = "done" if failure is None else "failed"
    result = (_best_effort(store, "timings", lambda: scene_result(open_store(store).scene(scene_id), sources, config,
                                                                  status, metrics=metrics))
              or SceneResult(scene_id, sources, status, backend=config.backend, metrics=metrics))
    if failure is None:
        result.outputs = f"scenes/{scene_id}/exports"
    else:
        result.step = getattr(failure, "step", result.step)
        problem = None if isinstance(failure, StepError) else store_problem(store, failure)
        result.error = str(failure) if problem is None else f"scene {_short(scene_id)}: {problem}"
    _best_effort(store, "manifest", write_manifest, store, manifest_rows_for(result, run_id))
    create_markdown_artifact(key=f"scene-{_short(scene_id)}", markdown=summary_markdown(run_id, config, [result]),
                             description=f"navcrafter scene {_short(scene_id)} ({config.backend})")
    progress.flush()
    dashboard.publish_scene_dashboard(store, scene_id, config, result.label)  # the summary's label, read once
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
def explore_collection(photos: str, store: str, config: RunConfig,
                       scene_deployment: str | None = None) -> CollectionResult:
    """Explore every image of a collection into ``store``; one result per image (or per scene, when
    several files hold the same image). ``photos``: a folder, one image, or an fsspec URL (a prefix
    such as ``s3://bucket/photos/``, or one object).

    At most ``config.max_parallel_scenes`` scenes run at once (the thread pool, 2 by default, can be
    resized with ``with_options``; the CLI sizes it to the same number). With ``scene_deployment``
    ('explore-scene/NAME') each scene is instead a flow run of that deployment (e.g. on a GPU work
    pool), at most ``config.max_parallel_scenes`` in flight (``flows/dispatch.py``).
    """
    with one_blas_thread():  # scenes run in threads: numpy's OpenBLAS pool hung when two entered it
        return _explore_collection(photos, store, config, scene_deployment)


def _explore_collection(photos: str, store: str, config: RunConfig,
                        scene_deployment: str | None = None) -> CollectionResult:
    """The body of ``explore_collection``."""
    problems = preflight(config)
    if problems:
        raise ValueError(" ".join(problems))
    if scene_deployment:
        dispatch.check_scene_deployment(scene_deployment)
    run_id = str(flow_run.id or uuid.uuid4().hex)
    sources = ingest.list_collection(photos)
    if not sources:
        raise ValueError(f"the collection {photos} holds no files")
    results: list[SceneResult] = []

    notes: list[str] = []  # bookkeeping the store refused

    def record(rows) -> None:
        _best_effort(store, "manifest", write_manifest, store, rows, notes=notes)

    def fail(scene_id: str | None, srcs: list[str], res) -> None:
        if isinstance(res, ingest.IngestResult):
            error = res.error
        else:
            problem = res if isinstance(res, StepError) else store_problem(store, res)
            error = f"ingest crashed: {res!r}" if problem is None else str(problem)
        failed = SceneResult(scene_id or "", srcs, "failed", step="ingest", error=error, backend=config.backend)
        record(manifest_rows_for(failed, run_id))
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
            record(manifest_rows_for(
                SceneResult(sid, by_scene[sid], "pending", step="ingest", backend=config.backend), run_id))
        else:
            fail(sid, by_scene.pop(sid), res)
    # at most max_parallel_scenes scenes in flight, whatever the task runner's size (deployment runs
    # use the decorator's pool; scene i + n starts when scene i is done)
    items = list(by_scene.items())
    n = config.max_parallel_scenes
    if scene_deployment:
        results += dispatch.dispatch_scenes(scene_deployment, store, items, config, run_id)
        items = []
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
            record(manifest_rows_for(res, run_id))
        results.append(res)
    order = {s: i for i, s in enumerate(sources)}
    results.sort(key=lambda r: order.get(r.sources[0], 0))
    for name in ("manifest", "steps"):
        _best_effort(store, f"compacted {name} table", lambda t=name: open_store(store).tables.compact(t), notes=notes)
    md = _best_effort(store, "run summary", write_summary, store, run_id, config, results, notes=notes)
    summary = f"runs/{run_id}/summary.md" if md is not None else ""
    md = md or summary_markdown(run_id, config, results)
    create_markdown_artifact(key="run-summary", markdown=md, description="navcrafter run summary")
    return CollectionResult(run_id, results, summary, notes)

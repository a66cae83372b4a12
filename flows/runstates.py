"""Prefect's view of a store's scenes, beside the manifest's (``navcrafter status``).

The manifest says what the store saw last (pending, running, done, failed) and which collection flow
run wrote it (``run_id``); Prefect knows whether those flow runs are alive. ``run_states`` asks a
Prefect API (quickly: a health check and one or two queries, each with a short timeout and no
retries) for each row's collection flow run and its scene's ``explore-scene`` flow run, and flags
what a user must act on:

* **stale**: the manifest says ``running`` (or ``pending``) but the flow run that was to finish the
  scene is CRASHED, FAILED or CANCELLED, or is unknown to the server and the scene has made no progress
  for a while. Nothing will finish it: resubmit the collection (completed steps are kept).
* **possibly dead worker**: Prefect shows the run RUNNING but the scene has made no progress (no step
  event, no manifest update) for ``no_progress_after`` seconds. Prefect does not notice a worker that
  was killed; its runs stay RUNNING.

Scene runs are found as children of the manifest's collection runs and by the tags every
``explore-scene`` run carries (``scene_run_tags``: ``scene:<first 12 of the scene id>`` and
``store:<hash of the store's location>``), so they can also be filtered in the dashboard.
Without a reachable API every state is unknown and nothing is flagged.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import uuid
from dataclasses import dataclass, field
from typing import Any

from navcrafter.flows.tools.report import read_manifest
from navcrafter.schemas.store import Store

SCENE_FLOW = "explore-scene"
BAD_STATES = ("CRASHED", "FAILED", "CANCELLED")
DEFAULT_TIMEOUT = 3.0  # seconds per request to the Prefect API
DEFAULT_NO_PROGRESS_AFTER = 1800.0  # seconds without a step event before a RUNNING scene is suspect
MAX_SCENE_RUNS = 5000  # scene runs read per status call (pages of 200)


def store_tag(store: Store | str) -> str:
    """``store:<12 hex>``: a hash of the store's canonical location (absolute path or URL)."""
    st = store if isinstance(store, Store) else Store(store, create=False)
    location = st.fs.unstrip_protocol(st.root)
    return "store:" + hashlib.sha256(location.encode()).hexdigest()[:12]


def scene_run_tags(store: Store | str, scene_id: str) -> list[str]:
    """Tags of a scene's ``explore-scene`` flow runs (set by the flow itself when missing)."""
    return [f"scene:{scene_id[:12]}", store_tag(store)]


@dataclass(frozen=True)
class FlowRunInfo:
    """What status shows of one flow run."""

    id: str
    name: str
    state: str | None  # state type: RUNNING, COMPLETED, CRASHED, ... (None: no state yet)
    state_name: str | None  # the state's name, e.g. Running, Late, AwaitingRetry
    start_time: dt.datetime | None = None
    parameters: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)


@dataclass(frozen=True)
class SceneRunState:
    """One manifest row with Prefect's view of it."""

    source: str
    scene_id: str | None
    status: str  # the manifest's: pending | running | done | failed
    run_id: str | None  # the collection flow run that wrote the row
    collection_run: FlowRunInfo | None = None
    scene_run: FlowRunInfo | None = None
    last_progress: dt.datetime | None = None  # latest step event or manifest update of the scene
    issue: str | None = None  # None | "stale" | "possibly dead worker"
    advice: str | None = None  # what to do about the issue

    @property
    def run(self) -> FlowRunInfo | None:
        """The flow run that matters for this row: the scene's, else its collection's."""
        return self.scene_run or self.collection_run

    @property
    def prefect_state(self) -> str | None:
        return self.run.state if self.run else None


@dataclass(frozen=True)
class RunStates:
    api_url: str | None
    reachable: bool
    error: str | None  # why the Prefect states are unknown (no API configured, not reachable, ...)
    scenes: list[SceneRunState]

    @property
    def issues(self) -> list[SceneRunState]:
        return [s for s in self.scenes if s.issue]


def configured_api_url() -> str | None:
    """PREFECT_API_URL from the environment or the active Prefect profile (None: not set)."""
    from prefect.settings import get_current_settings

    return get_current_settings().api.url or None


def _info(run) -> FlowRunInfo:
    state = run.state
    return FlowRunInfo(
        id=str(run.id),
        name=run.name,
        state=state.type.value if state else None,
        state_name=state.name if state else None,
        start_time=run.start_time,
        parameters=dict(run.parameters or {}),
    )


def fetch_flow_runs(
    api_url: str, collection_ids: list[str], tag: str, timeout: float = DEFAULT_TIMEOUT
) -> tuple[dict[str, FlowRunInfo], list[FlowRunInfo]]:
    """The collection flow runs with these ids, and the ``explore-scene`` runs that are their children
    or carry ``tag``. Raises ``ConnectionError`` when the API does not answer its health check."""
    import httpx
    from prefect.client.orchestration import SyncPrefectClient
    from prefect.client.schemas.filters import (
        FlowFilter,
        FlowFilterName,
        FlowRunFilter,
        FlowRunFilterId,
        FlowRunFilterParentFlowRunId,
        FlowRunFilterTags,
        Operator,
    )
    from prefect.client.schemas.sorting import FlowRunSort
    from prefect.settings import PREFECT_CLIENT_MAX_RETRIES, get_current_settings, temporary_settings

    api_url = api_url.rstrip("/")
    settings = get_current_settings()
    auth = settings.api.auth_string.get_secret_value() if settings.api.auth_string else None
    key = settings.api.key.get_secret_value() if settings.api.key else None
    headers = {"Authorization": f"Bearer {key}"} if key and not auth else {}
    try:
        health = httpx.get(
            f"{api_url}/health",
            timeout=timeout,
            headers=headers,
            auth=tuple(auth.split(":", 1)) if auth and ":" in auth else None,
        )
        health.raise_for_status()
    except httpx.HTTPError as exc:
        raise ConnectionError(f"{type(exc).__name__}: {exc}") from None
    ids = []
    for rid in collection_ids:
        try:
            ids.append(uuid.UUID(rid))
        except (TypeError, ValueError):
            continue  # not a Prefect flow run id
    collections: dict[str, FlowRunInfo] = {}
    scenes: dict[str, FlowRunInfo] = {}
    with (
        temporary_settings(updates={PREFECT_CLIENT_MAX_RETRIES: 0}),
        SyncPrefectClient(
            api_url, auth_string=auth, api_key=key, httpx_settings={"timeout": httpx.Timeout(timeout)}
        ) as client,
    ):
        for i in range(0, len(ids), 200):
            for run in client.read_flow_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=ids[i : i + 200]))):
                collections[str(run.id)] = _info(run)
        tagged = FlowRunFilterTags(all_=[tag])
        if collections:  # tagged, or children of the collection runs (runs from before the tags)
            parents = FlowRunFilterParentFlowRunId(any_=[uuid.UUID(c) for c in collections])
            scene_filter = FlowRunFilter(operator=Operator.or_, tags=tagged, parent_flow_run_id=parents)
        else:
            scene_filter = FlowRunFilter(tags=tagged)
        for offset in range(0, MAX_SCENE_RUNS, 200):
            page = client.read_flow_runs(
                flow_filter=FlowFilter(name=FlowFilterName(any_=[SCENE_FLOW])),
                flow_run_filter=scene_filter,
                sort=FlowRunSort.START_TIME_DESC,
                limit=200,
                offset=offset,
            )
            for run in page:
                scenes.setdefault(str(run.id), _info(run))
            if len(page) < 200:
                break
    return collections, list(scenes.values())


def _scene_of(run: FlowRunInfo) -> str | None:
    sid = run.parameters.get("scene_id")
    return str(sid) if sid else None


def pick_scene_run(scene_id: str | None, run_id: str | None, runs: list[FlowRunInfo]) -> FlowRunInfo | None:
    """The scene's run started by the row's collection run (its ``run_id`` parameter); the latest one
    when there are several (a retried scene). Runs of other collections are not this row's."""
    if not scene_id or not run_id:
        return None
    mine = [r for r in runs if _scene_of(r) == scene_id and str(r.parameters.get("run_id")) == run_id]
    if not mine:
        return None
    return max(mine, key=lambda r: r.start_time or dt.datetime.min.replace(tzinfo=dt.UTC))


def classify(
    status: str,
    collection_run: FlowRunInfo | None,
    scene_run: FlowRunInfo | None,
    last_progress: dt.datetime | None,
    now: dt.datetime,
    no_progress_after: float = DEFAULT_NO_PROGRESS_AFTER,
) -> tuple[str | None, str | None]:
    """``(issue, advice)`` for a manifest row, given its flow runs as a reachable API reports them
    (``None``: unknown to the server). Only unfinished rows (pending, running) can have an issue."""
    if status not in ("running", "pending"):
        return None, None
    run = scene_run or collection_run
    quiet = last_progress is None or (now - last_progress).total_seconds() > no_progress_after
    idle = (
        "no progress recorded"
        if last_progress is None
        else f"no progress for {(now - last_progress).total_seconds() / 60:.0f} min"
    )
    resubmit = "resubmit the collection to finish it (completed steps are kept)"
    if run is None:  # e.g. a run of another (or a temporary) Prefect server: stale only once quiet
        return (
            ("stale", f"its flow run is unknown to this Prefect server and {idle}: {resubmit}")
            if quiet
            else (None, None)
        )
    if run.state in BAD_STATES or run.state == "COMPLETED":
        return "stale", f"its flow run {run.name} is {run.state}, the scene is not finished: {resubmit}"
    if run.state == "RUNNING" and quiet:
        return (
            "possibly dead worker",
            f"flow run {run.name} is RUNNING but the scene has {idle}; if its worker is gone, cancel it "
            f"(`prefect flow-run cancel {run.id}`) and {resubmit}",
        )
    return None, None


def last_progress_by_scene(store: Store, rows: list[dict]) -> dict[str, dt.datetime]:
    """Latest step event (steps table) or manifest update of each scene."""
    out: dict[str, dt.datetime] = {}
    for r in rows:
        if r.get("scene_id") and r.get("updated_at"):
            out[r["scene_id"]] = max(out.get(r["scene_id"], r["updated_at"]), r["updated_at"])
    wanted = {r["scene_id"] for r in rows if r.get("status") in ("running", "pending") and r.get("scene_id")}
    if wanted:
        steps = store.tables.read("steps").select(["scene_id", "at"]).to_pylist()
        for e in steps:
            sid = e["scene_id"]
            if sid in wanted and (sid not in out or e["at"] > out[sid]):
                out[sid] = e["at"]
    return out


def run_states(
    store: Store | str,
    rows: list[dict] | None = None,
    api_url: str | None = None,
    *,
    timeout: float = DEFAULT_TIMEOUT,
    no_progress_after: float = DEFAULT_NO_PROGRESS_AFTER,
    now: dt.datetime | None = None,
) -> RunStates:
    """Prefect's state of every manifest row's flow runs, and what needs acting on.

    ``rows``: the manifest rows (``flows.tools.report.read_manifest(store).to_pylist()``; read when None).
    ``api_url``: the Prefect API (default: PREFECT_API_URL / the active profile); never starts one.
    Never raises for an unreachable API: the result says ``reachable=False`` and why.
    """

    st = store if isinstance(store, Store) else Store(store, create=False)
    rows = read_manifest(st).to_pylist() if rows is None else rows
    now = now or dt.datetime.now(dt.UTC)
    api_url = api_url or configured_api_url()
    plain = [SceneRunState(r["source"], r.get("scene_id"), r["status"], r.get("run_id")) for r in rows]
    if not api_url:
        return RunStates(None, False, "no Prefect API configured (set PREFECT_API_URL or pass --api-url)", plain)
    if not rows:
        return RunStates(api_url, False, "the manifest is empty", plain)
    try:
        collections, scene_runs = fetch_flow_runs(
            api_url, sorted({r["run_id"] for r in rows if r.get("run_id")}), store_tag(st), timeout
        )
    except Exception as exc:  # unreachable, timed out, refused, not a Prefect API
        return RunStates(api_url, False, f"the Prefect API at {api_url} did not answer ({exc})", plain)
    progress = last_progress_by_scene(st, rows)
    out = []
    for r in rows:
        coll = collections.get(r.get("run_id") or "")
        scene_run = pick_scene_run(r.get("scene_id"), r.get("run_id"), scene_runs)
        last = progress.get(r.get("scene_id") or "")
        issue, advice = classify(r["status"], coll, scene_run, last, now, no_progress_after)
        out.append(
            SceneRunState(
                r["source"], r.get("scene_id"), r["status"], r.get("run_id"), coll, scene_run, last, issue, advice
            )
        )
    return RunStates(api_url, True, None, out)

"""Dashboard artifacts of scene runs and Prefect run states in ``navcrafter status``.

Reuses the session's tiny collection run (``full_run``) and its Prefect test server; the run-state
cases are real flow runs created on that server and put into the states to classify.
"""

from __future__ import annotations

import base64
import datetime as dt
import io
import json
import re
import socket
import time
import uuid
from pathlib import Path

import pytest
from helpers import DEMO, TINY
from PIL import Image
from typer.testing import CliRunner

from navcrafter.flows.cli import app
from navcrafter.flows.runstates import run_states, store_tag
from navcrafter.flows.tools.dashboard import GRID_MAX, THUMB, scene_dashboard_markdown
from navcrafter.flows.tools.report import manifest_rows_for, read_manifest, write_manifest
from navcrafter.models.simulation import LABEL
from navcrafter.schemas.store import Store

pytestmark = pytest.mark.system  # the session's collection run and real flow runs on the Prefect test server
runner = CliRunner()
IMAGE = re.compile(r"!\[([^\]]*)\]\(data:image/png;base64,([A-Za-z0-9+/=]+)\)")


def _closed_port_url() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"http://127.0.0.1:{port}/api"


def _scenes(run):
    return {Path(src).name: r for r in run.scenes for src in r.sources}


def test_dashboard_markdown_of_stored_scenes(full_run):
    store, run = full_run
    by_name = _scenes(run)
    for name in DEMO:
        md = scene_dashboard_markdown(str(store), by_name[name].scene_id, TINY)
        assert len(md) < 200_000 and LABEL in md and "SIMULATION" in md and name in md
        images = IMAGE.findall(md)
        # the input, one top-down plot per iteration, the render grid
        assert len(images) == 2 + TINY.iterations, [alt for alt, _ in images]
        for alt, data in images:
            img = Image.open(io.BytesIO(base64.b64decode(data)))
            img.load()
            assert max(img.size) <= (GRID_MAX if alt == "render grid" else THUMB), (alt, img.size)
        grid = Image.open(io.BytesIO(base64.b64decode(images[-1][1]))).convert("RGB")
        assert grid.getpixel((grid.width - 2, 2)) == (200, 30, 30)  # the SIMULATION band across the top
        assert "| fscore |" in md and "| collisions | 0 |" in md
    failed = by_name["no-groundtruth.png"]  # failed at its first step: the input and nothing else
    md = scene_dashboard_markdown(str(store), failed.scene_id, TINY)
    assert [alt for alt, _ in IMAGE.findall(md)] == ["input image"] and "0 of " in md


def test_scene_runs_publish_progress_and_dashboard(full_run, prefect_api_url):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId, FlowRunFilter, FlowRunFilterTags

    store, run = full_run
    by_name = _scenes(run)
    with get_client(sync_client=True) as client:
        for name in (*DEMO, "no-groundtruth.png"):
            sid = by_name[name].scene_id
            tags = [f"scene:{sid[:12]}", store_tag(str(store))]
            runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(tags=FlowRunFilterTags(all_=tags)))
            assert runs and {r.name for r in runs} == {f"scene-{sid[:12]}"}, name  # findable by its tags
            first = min(runs, key=lambda r: r.start_time)  # the full run's (a rerun may have added one)
            arts = client.read_artifacts(
                artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=[first.id]))
            )
            by_key = {a.key: a for a in arts}
            progress = by_key[f"progress-{sid[:12]}"]
            assert progress.type == "progress"
            dashboard = by_key[f"dashboard-{sid[:12]}"]
            assert dashboard.type == "markdown" and LABEL in dashboard.data
            if name in DEMO:
                assert float(progress.data) == 100.0
                assert len(IMAGE.findall(dashboard.data)) == 2 + TINY.iterations
            else:
                assert float(progress.data) == 0.0  # its first step failed


def _flow_run(client, flow, state, **kw):
    from prefect.states import Running

    fr = client.create_flow_run(flow, state=Running(), **kw)
    if state is not None:
        client.set_flow_run_state(fr.id, state, force=True)
    return fr


def test_run_states_classify_real_flow_runs(prefect_api_url, tmp_path):
    from prefect import flow
    from prefect.client.orchestration import get_client
    from prefect.states import Cancelled, Completed, Crashed

    from navcrafter.flows.explore import explore_scene

    @flow(name="explore-collection")
    def collection_stand_in() -> None:
        pass

    store = tmp_path / "store"
    st = Store(str(store))
    old = dt.datetime.now(dt.UTC) - dt.timedelta(hours=2)
    with get_client(sync_client=True) as client:
        crashed = _flow_run(client, collection_stand_in, Crashed(message="worker lost"))
        running = _flow_run(client, collection_stand_in, None)
        done = _flow_run(client, collection_stand_in, Completed())
        scene_c = "c" * 64
        cancelled_scene = _flow_run(
            client,
            explore_scene,
            Cancelled(),
            name=f"scene-{scene_c[:12]}",
            parameters={"store": str(store), "scene_id": scene_c, "config": {}, "run_id": str(running.id)},
            tags=[f"scene:{scene_c[:12]}", store_tag(st)],
        )
    cases = {  # source -> (status, collection run id, manifest updated at, expected issue)
        "crashed.png": ("running", str(crashed.id), None, "stale"),
        "dead.png": ("running", str(running.id), old, "possibly dead worker"),
        "alive.png": ("running", str(running.id), None, None),
        "cancelled-scene.png": ("running", str(running.id), None, "stale"),
        "lost.png": ("running", str(uuid.uuid4()), old, "stale"),
        "lost-recent.png": ("running", str(uuid.uuid4()), None, None),
        "pending.png": ("pending", str(crashed.id), None, "stale"),
        "done.png": ("done", str(done.id), old, None),
    }
    rows = []
    for i, (source, (status, run_id, at, _)) in enumerate(cases.items()):
        sid = scene_c if source == "cancelled-scene.png" else f"{i:064x}"
        rows += [
            {**r, **({"updated_at": at} if at else {})} for r in manifest_rows_for(_result(sid, source, status), run_id)
        ]
    write_manifest(str(store), rows)
    t0 = time.perf_counter()
    states = run_states(str(store), api_url=prefect_api_url)
    assert time.perf_counter() - t0 < 10
    assert states.reachable and states.error is None
    got = {Path(s.source).name: s for s in states.scenes}
    assert {k: s.issue for k, s in got.items()} == {k: v[3] for k, v in cases.items()}
    assert got["crashed.png"].prefect_state == "CRASHED" and "resubmit the collection" in got["crashed.png"].advice
    assert got["dead.png"].prefect_state == "RUNNING" and "prefect flow-run cancel" in got["dead.png"].advice
    assert got["cancelled-scene.png"].scene_run.id == str(cancelled_scene.id)  # the scene's own run counts
    assert got["cancelled-scene.png"].collection_run.state == "RUNNING"
    assert got["lost.png"].run is None and "unknown to this Prefect server" in got["lost.png"].advice
    assert got["done.png"].prefect_state == "COMPLETED"
    # an API that does not answer: states unknown, nothing flagged, and quickly
    t0 = time.perf_counter()
    unknown = run_states(str(store), api_url=_closed_port_url())
    assert time.perf_counter() - t0 < 5
    assert not unknown.reachable and "did not answer" in unknown.error
    assert all(s.prefect_state is None and s.issue is None for s in unknown.scenes)


def _result(scene_id: str, source: str, status: str):
    from navcrafter.flows.tools.report import SceneResult

    return SceneResult(scene_id, [source], status, backend="simulation")


def test_status_shows_prefect_states(full_run, prefect_api_url):
    store = full_run[0]
    res = runner.invoke(app, ["status", str(store), "--json"])
    assert res.exit_code == 0, res.output
    rows = {Path(r["source"]).name: r for r in map(json.loads, res.output.strip().splitlines())}
    manifest = {Path(r["source"]).name: r for r in read_manifest(Store(str(store))).to_pylist()}
    assert set(rows) == set(manifest)
    for r in rows.values():
        assert r["prefect_api"] == "reachable" and r["issue"] is None
        assert r["prefect_state"] in (("COMPLETED",) if r["status"] == "done" else ("COMPLETED", "FAILED"))
    for name in DEMO:  # found the scene's own flow run
        assert rows[name]["prefect_flow_run_name"] == f"scene-{rows[name]['scene_id'][:12]}"
    assert rows["no-groundtruth.png"]["prefect_state"] == "FAILED"  # its scene run failed
    assert rows["notes.txt"]["prefect_collection_state"] == "COMPLETED"  # no scene: its collection run
    res = runner.invoke(app, ["status", str(store)], env={"COLUMNS": "220"})
    assert res.exit_code == 0 and "prefect" in res.output and "Completed" in res.output, res.output
    assert "Prefect state: unknown" not in res.output


def test_status_without_reachable_api_is_quick(full_run, prefect_api_url):
    from prefect.settings import PREFECT_API_URL, temporary_settings

    store = full_run[0]
    with temporary_settings(updates={PREFECT_API_URL: _closed_port_url()}):  # as if exported in the shell
        t0 = time.perf_counter()
        res = runner.invoke(app, ["status", str(store), "--json"])
        elapsed = time.perf_counter() - t0
    assert res.exit_code == 0, res.output
    rows = [json.loads(line) for line in res.output.strip().splitlines()]
    assert rows and all(r["prefect_api"] == "unknown" and r["prefect_state"] is None for r in rows)
    assert all(r["issue"] is None for r in rows)
    assert elapsed < 5, elapsed  # one refused connection, no retries
    res = runner.invoke(app, ["status", str(store), "--api-url", _closed_port_url()], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "Prefect state: unknown" in res.output and "did not answer" in res.output and "done" in res.output
    header = next(line for line in res.output.splitlines() if "image" in line and "status" in line)
    assert "prefect" not in header  # no Prefect column without an API

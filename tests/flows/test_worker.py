"""Distributed operation with real processes: a Prefect server, process work pools (a CPU one for the
collection runs, a "GPU" one for the scene runs they dispatch), the deployments made from this checkout,
workers, and ``navcrafter submit``; then a worker killed mid-scene.

The server here is its own (own PREFECT_HOME, SQLite), not the session's test server: workers and
flow runs are separate processes and need a server they can reach over HTTP.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import (
    POOL,
    TINY,
    VENV_BIN,
    Worker,
    api_get,
    assert_same_outputs,
    completed_counts,
    kill_tree,
    prefect_env,
    start_prefect_server,
    step_state,
    submit,
    tail,
)

from navcrafter.flows.tools.report import read_manifest
from navcrafter.schemas.store import Store
from navcrafter.tasks.runner import scene_steps

GPU_POOL = "navcrafter-test-gpu"  # process pool standing in for the GPU machines
SCENE_DEPLOYMENT = "explore-scene/test"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    home = tmp_path_factory.mktemp("prefect-home")
    proc, port = start_prefect_server(home, home / "server.log")
    api = f"http://127.0.0.1:{port}/api"
    try:
        for pool in (POOL, GPU_POOL):
            res = subprocess.run([f"{VENV_BIN}/prefect", "work-pool", "create", "--type", "process", pool],
                                 env=prefect_env(home, api), capture_output=True, text=True, timeout=120)
            assert res.returncode == 0, res.stdout + res.stderr
        yield {"api": api, "home": home}
    finally:
        kill_tree(proc, signal.SIGTERM)


@pytest.fixture
def start_worker(server, tmp_path):
    workers: list[Worker] = []

    def start() -> Worker:
        workers.append(Worker(server, tmp_path / f"worker-{len(workers)}.log"))
        return workers[-1]

    yield start
    for w in workers:
        w.kill()


def _state(server, run_id: str) -> str:
    return api_get(f"{server['api']}/flow_runs/{run_id}")["state"]["type"]


def _wait_completed(server, ids: list[str], workers: list[Worker], timeout: float = 240) -> None:
    deadline = time.time() + timeout
    states: dict[str, str] = {}
    while time.time() < deadline:
        states = {i: _state(server, i) for i in ids}
        if all(s == "COMPLETED" for s in states.values()):
            return
        if any(s in ("FAILED", "CRASHED", "CANCELLED") for s in states.values()):
            break
        time.sleep(1)
    logs = "\n".join(tail(w.log) for w in workers)
    raise AssertionError(f"flow runs did not complete: {states}\n{logs}")


@pytest.fixture(scope="module")
def two_photos(tmp_path_factory) -> Path:
    from navcrafter.models.simulation.demo import write_demo_collection

    folder = tmp_path_factory.mktemp("worker-demo") / "photos"
    write_demo_collection(folder, ("room", "tabletop"), width=320, height=240, supersample=1)
    return folder


@pytest.fixture(scope="module")
def uninterrupted(server, two_photos, tmp_path_factory):
    """The two images explored from one submitted run, uninterrupted: the collection run on the CPU
    pool's worker, each scene dispatched as a flow run of explore-scene to the GPU pool's worker."""
    store = tmp_path_factory.mktemp("worker-full") / "store"
    workers = [Worker(server, store.parent / "worker.log"), Worker(server, store.parent / "gpu-worker.log", GPU_POOL)]
    try:
        ids = submit(server, two_photos, store, "--tag", "test", "--scene-pool", GPU_POOL)
        assert len(ids) == 1
        _wait_completed(server, ids, workers)
    finally:
        for w in workers:
            w.kill()
    run = api_get(f"{server['api']}/flow_runs/{ids[0]}")
    return store, run


@pytest.mark.system
def test_submitted_collection_is_explored_by_a_worker(server, uninterrupted, two_photos):
    store, run = uninterrupted
    assert {"navcrafter", "test"} <= set(run["tags"]) and run["work_pool_name"] == POOL
    assert run["parameters"]["store"] == str(store) and run["parameters"]["config"]["iterations"] == TINY.iterations
    assert run["parameters"]["scene_deployment"] == SCENE_DEPLOYMENT
    manifest = {Path(r["source"]).name: r for r in read_manifest(Store(str(store))).to_pylist()}
    assert {k: v["status"] for k, v in manifest.items()} == {"room-0.png": "done", "tabletop-0.png": "done"}
    counts = completed_counts(store)
    assert len(counts) == 2 * (2 + len(scene_steps(TINY))) and set(counts.values()) == {1}  # + input, evaluation
    # the scenes ran as child flow runs of the explore-scene deployment, on the GPU pool
    children = api_get(f"{server['api']}/flow_runs/filter",
                       {"flow_runs": {"parent_flow_run_id": {"any_": [run["id"]]}}})
    assert sorted(c["parameters"]["scene_id"] for c in children) == sorted(Store(str(store)).scene_ids())
    for child in children:
        deployment = api_get(f"{server['api']}/deployments/{child['deployment_id']}")
        flow = api_get(f"{server['api']}/flows/{deployment['flow_id']}")
        assert f"{flow['name']}/{deployment['name']}" == SCENE_DEPLOYMENT
        assert child["work_pool_name"] == GPU_POOL and child["state"]["type"] == "COMPLETED"
        assert child["parameters"]["run_id"] == run["id"] and child["parameters"]["store"] == str(store)
        assert child["name"] == f"scene-{child['parameters']['scene_id'][:12]}" and "test" in child["tags"]
    assert {r["run_id"] for r in manifest.values()} == {run["id"]}


@pytest.mark.system
def test_a_server_that_finds_its_port_taken_starts_on_another(server, tmp_path, monkeypatch):
    """The port race CI met (2026-12-05): free_port's port was bound by another test's server before ours, whose
    health check then answered for the other server. start_prefect_server checks that the answer is its own."""
    import helpers

    taken = int(server["api"].split(":")[-1].split("/")[0])
    home = tmp_path / "second-home"
    home.mkdir()
    with pytest.raises(RuntimeError, match="taken by another server"):
        start_prefect_server(home, tmp_path / "fixed.log", taken, timeout=60)
    ports, free = iter([taken]), helpers.free_port
    monkeypatch.setattr(helpers, "free_port", lambda: next(ports, None) or free())
    proc, port = start_prefect_server(home, tmp_path / "retry.log")
    try:
        assert port != taken
        assert Path(api_get(f"http://127.0.0.1:{port}/api/admin/settings")["home"]) == home.resolve()
        assert Path(api_get(f"{server['api']}/admin/settings")["home"]) == Path(server["home"]).resolve()  # untouched
    finally:
        kill_tree(proc, signal.SIGTERM)


@pytest.mark.system
def test_submit_errors_are_clear(server, two_photos, tmp_path):
    env = prefect_env(server["home"], server["api"])
    base = [sys.executable, "-m", "navcrafter.flows.cli", "submit", str(two_photos), "--store", str(tmp_path / "s"),
            "--preset", "tiny"]
    res = subprocess.run([*base, "--deployment", "explore-collection/nope"], env=env, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2 and "no deployment" in res.stderr and "prefect deploy" in res.stderr, res.stderr
    env.pop("PREFECT_API_URL")
    res = subprocess.run(base, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "prefect server start" in res.stderr, res.stderr
    listing = tmp_path / "photos.txt"
    listing.write_text(f"{two_photos / 'room-0.png'}\nmissing.png\n")
    res = subprocess.run([*base[:4], str(listing), *base[5:]], env={**env, "PREFECT_API_URL": server["api"]},
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "missing.png" in res.stderr, res.stderr
    assert not (tmp_path / "s").exists()


@pytest.mark.system
def test_worker_killed_mid_scene_then_resubmitted(server, start_worker, uninterrupted, two_photos, tmp_path):
    store = tmp_path / "store"
    worker = start_worker()
    [first] = submit(server, two_photos, store)
    deadline = time.time() + 240
    killed_at = None
    while time.time() < deadline:
        state = step_state(store) if (store / "zarr.json").exists() else {}
        done = {(sid, p) for (sid, p), (complete, _) in state.items() if complete}
        if any(p == "iter_1/synthesize" for _, p in done) and sum(p == "exports" for _, p in done) == 0:
            worker.kill()  # the worker and its flow run process: nothing is left to finish the run
            killed_at = state
            break
        if _state(server, first) in ("COMPLETED", "FAILED", "CRASHED"):
            break
        time.sleep(0.05)
    assert killed_at is not None, f"the run ended before it could be killed\n{tail(worker.log)}"
    time.sleep(1)
    after_kill = step_state(store)
    assert not any(p == "exports" and c for (_, p), (c, _) in after_kill.items())  # really killed mid-scene
    assert _state(server, first) in ("RUNNING", "CRASHED")  # nobody finishes it: it is resubmitted

    # a new worker; the collection resubmitted as a list file, one run per image (two runs at once)
    worker = start_worker()
    listing = tmp_path / "photos.txt"
    listing.write_text("# the two demo photos\nroom-0.png\n\ntabletop-0.png\n")
    (tmp_path / "room-0.png").symlink_to(two_photos / "room-0.png")
    (tmp_path / "tabletop-0.png").symlink_to(two_photos / "tabletop-0.png")
    ids = submit(server, listing, store, "--tag", "resubmitted")
    assert len(ids) == 2
    _wait_completed(server, ids, [worker])
    after = step_state(store)
    for path, (complete, exec_id) in after_kill.items():
        if complete:
            assert after[path] == (True, exec_id), path  # completed steps were not recomputed
    assert all(c == 1 for c in completed_counts(store).values())
    manifest = read_manifest(Store(str(store))).to_pylist()
    assert {r["scene_id"]: r["status"] for r in manifest} == dict.fromkeys(Store(str(store)).scene_ids(), "done")
    assert_same_outputs(uninterrupted[0], store)  # identical to the uninterrupted run


def test_collection_items_and_list_files(tmp_path, monkeypatch):
    from navcrafter.flows.submit import SubmitError, absolute, collection_items, ui_url

    photos = tmp_path / "photos"
    (photos / "sub").mkdir(parents=True)
    for name in ("a.png", "sub/b.png", ".groundtruth"):
        (photos / name).write_bytes(b"x")
    assert collection_items(photos, per_image=False) == [str(photos.resolve())]
    assert collection_items(photos, per_image=True) == [str(photos / "a.png"), str(photos / "sub" / "b.png")]
    listing = tmp_path / "list.txt"
    listing.write_text("# comment\n\nphotos/a.png\n  s3://bucket/c.png  \n" + str(photos / "sub/b.png") + "\n")
    assert collection_items(listing, per_image=False) == [str(photos / "a.png"), "s3://bucket/c.png",
                                                         str(photos / "sub" / "b.png")]
    listing.write_text("# nothing\n")
    with pytest.raises(SubmitError, match="names no images"):
        collection_items(listing, per_image=False)
    with pytest.raises(SubmitError, match="does not exist"):
        collection_items(tmp_path / "nope", per_image=False)
    assert absolute("s3://b/store") == "s3://b/store" and absolute("rel") == str(Path("rel").resolve())
    from prefect.settings import PREFECT_API_URL, PREFECT_UI_URL, temporary_settings

    with temporary_settings({PREFECT_API_URL: "http://h:4200/api"}):
        assert ui_url() == "http://h:4200"
    with temporary_settings({PREFECT_API_URL: "http://h:4200/api", PREFECT_UI_URL: "https://ui.example/"}):
        assert ui_url() == "https://ui.example"


def test_dispatched_scene_results_come_from_the_manifest_or_the_run_state(tmp_path):
    """What the collection run makes of its scene runs: the scene's final manifest row of this run, else
    (killed, crashed, cancelled before writing it) a failure carrying the Prefect state's message."""
    from prefect.states import Crashed

    from navcrafter.flows.dispatch import _FinalRows, result_from_row, result_without_row
    from navcrafter.flows.tools.report import SceneResult, manifest_rows_for, write_manifest

    store, a, b = str(tmp_path / "store"), "a" * 64, "b" * 64
    done = SceneResult(b, ["/p/b.png"], "done", step="export", backend="simulation", seconds=3.0,
                       timings={"iter_0/geometry": 1.0}, metrics={"n_points": 5.0}, outputs=f"scenes/{b}/exports")
    write_manifest(store, manifest_rows_for(SceneResult(a, ["/p/a.png"], "done", backend="simulation"), "earlier"))
    write_manifest(store, manifest_rows_for(SceneResult(a, ["/p/a.png"], "running", backend="simulation"), "run"))
    write_manifest(store, manifest_rows_for(done, "run"))
    rows = _FinalRows(store, "run")
    rows.refresh()
    assert set(rows.rows) == {b}  # another run's final row does not count, nor a "running" one
    assert result_from_row(rows.rows[b], ["/p/b.png"]) == done
    state = Crashed(message="Flow run infrastructure exited with non-zero status code -9.")
    failed = result_without_row(store, a, ["/p/a.png"], TINY, "run", f"scene-{a[:12]}", state)
    assert failed.status == "failed" and failed.step is None
    assert failed.error == f"scene run scene-{a[:12]} ended CRASHED: {state.message}"
    rows.refresh()  # only the new file is read; the failure just recorded is this run's final row
    assert result_from_row(rows.rows[a], ["/p/a.png"]) == failed
    latest = {r["scene_id"]: r["status"] for r in read_manifest(Store(store)).to_pylist()}
    assert latest == {a: "failed", b: "done"}

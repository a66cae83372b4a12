"""The store: layout validation, the step protocol (skip / stale / incomplete), tables, faults."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import numpy as np
import pyarrow.parquet as pq
import pytest

from navcrafter.schemas.layout import GEOMETRY, INGEST, LIFT, PLAN, STEPS, SYNTHESIZE
from navcrafter.schemas.store import FAULT_ENV, Store, StoreError
from navcrafter.schemas.tables import Tables, to_table, utcnow
from navcrafter.tasks import runner
from navcrafter.tasks.ingest import ingest


def test_step_roundtrip_with_schema_chunks(tmp_path):
    scene = Store(tmp_path / "s").scene("abc")
    w = scene.begin(SYNTHESIZE, 1, key="k1", backend="simulation")
    frames = np.random.default_rng(0).integers(0, 255, (5, 16, 24, 3), dtype=np.uint8)
    w.write("frames", frames)
    assert not scene.status(SYNTHESIZE, 1).complete
    w.commit(0.5)
    st = scene.status(SYNTHESIZE, 1)
    assert st.complete and st.key == "k1" and st.attrs["backend"] == "simulation"
    np.testing.assert_array_equal(scene.read(SYNTHESIZE, 1, "frames"), frames)
    arr = scene._open("iter_1/synthesize")["frames"]
    assert arr.chunks == (1, 16, 24, 3)  # one frame per chunk, as schemas.layout says
    # a fresh Store object (another process) sees the same
    again = Store(tmp_path / "s").scene("abc")
    assert again.status(SYNTHESIZE, 1).complete


def test_writer_validates_against_layout(tmp_path):
    scene = Store(tmp_path / "s").scene("abc")
    w = scene.begin(LIFT, 2, key="k", backend="simulation")
    with pytest.raises(TypeError, match="dtype"):
        w.write("depth", np.zeros((2, 8, 8), np.float64))
    w.write("depth", np.zeros((2, 8, 8), np.float32))
    with pytest.raises(ValueError, match="dimension S"):
        w.write("confidence", np.zeros((3, 8, 8), np.float32))
    with pytest.raises(ValueError, match="shape"):
        w.write("c2w", np.zeros((2, 3, 4)))
    with pytest.raises(KeyError, match="no array"):
        w.write("bogus", np.zeros(3))
    with pytest.raises(StoreError, match="arrays not written"):
        w.commit(0.1)
    with pytest.raises(ValueError):
        PLAN.group_path(None)
    assert {s.path for s in STEPS.values()} >= {"input", "iter_0/geometry", "exports"}


def test_empty_cloud_arrays_are_allowed(tmp_path):
    scene = Store(tmp_path / "s").scene("abc")
    w = scene.begin(GEOMETRY, None, key="k", backend="simulation")
    w.write("cloud_points", np.zeros((0, 3), np.float32))
    assert scene._open("iter_0/geometry")["cloud_points"].shape == (0, 3)


def test_begin_wipes_previous_content(tmp_path):
    scene = Store(tmp_path / "s").scene("abc")
    w = scene.begin(SYNTHESIZE, 1, key="old", backend="simulation")
    w.write("frames", np.ones((3, 4, 4, 3), np.uint8))
    w.commit(1.0)
    w = scene.begin(SYNTHESIZE, 1, key="new", backend="simulation")
    st = scene.status(SYNTHESIZE, 1)
    assert st.exists and not st.complete and st.key == "new"
    assert "frames" not in scene._open("iter_1/synthesize")
    with pytest.raises(StoreError, match="has not completed"):
        scene.read(SYNTHESIZE, 1, "frames")


def test_store_version_and_missing(tmp_path):
    with pytest.raises(StoreError, match="no navcrafter store"):
        Store(tmp_path / "missing", create=False)
    s = Store(tmp_path / "s")
    s.group.attrs.update({"navcrafter_schema_version": 999})
    with pytest.raises(StoreError, match="schema"):
        Store(tmp_path / "s")


def test_step_protocol_skip_stale_and_incomplete(tmp_path, demo_photos, tiny):
    uri = str(tmp_path / "s")
    res = ingest(uri, str(demo_photos / "room-0.png"), tiny, "run1")
    assert res.ok and res.step is not None and not res.step.skipped
    first = runner.run(uri, res.scene_id, "geometry", tiny, "run1")
    assert not first.skipped
    second = runner.run(uri, res.scene_id, "geometry", tiny, "run2")
    assert second.skipped and second.exec_id == first.exec_id
    # a config change that the step reads makes it stale
    changed = tiny.model_copy(update={"lift": tiny.lift.model_copy(update={"voxel_size": 0.05})})
    third = runner.run(uri, res.scene_id, "geometry", changed, "run3")
    assert not third.skipped and third.key != first.key
    # a config change the step does not read does not
    other = tiny.model_copy(update={"plan": tiny.plan.model_copy(update={"orbit_step_deg": 5.0})})
    assert runner.run(uri, res.scene_id, "geometry", other, "run4").skipped is False  # key(changed) != key(other)
    assert runner.run(uri, res.scene_id, "geometry", other, "run5").skipped
    # an incomplete group (a crash mid-step) is rewritten
    scene = Store(uri).scene(res.scene_id)
    scene.begin(GEOMETRY, None, key=scene.status(GEOMETRY).key, backend="simulation")
    redo = runner.run(uri, res.scene_id, "geometry", other, "run6")
    assert not redo.skipped and scene.status(GEOMETRY).complete
    events = Store(uri).tables.read("steps").to_pylist()
    geo = [(e["run_id"], e["event"]) for e in events if e["step"] == "iter_0/geometry"]
    assert geo == [("run1", "completed"), ("run2", "skipped"), ("run3", "completed"), ("run4", "completed"),
                   ("run5", "skipped"), ("run6", "completed")]


def test_downstream_needs_upstream(tmp_path, tiny):
    with pytest.raises(Exception, match="has not completed"):
        runner.run(str(tmp_path / "s"), "nothing-here", "geometry", tiny, "r")


@pytest.mark.system  # a subprocess killed by the injected fault
def test_fault_injection_kills_before_commit(tmp_path, demo_photos, tiny):
    uri = str(tmp_path / "s")
    res = ingest(uri, str(demo_photos / "tabletop-0.png"), tiny, "r")
    code = ("import sys; from navcrafter.schemas.config import RunConfig; "
            "from navcrafter.tasks import runner; "
            f"runner.run({uri!r}, {res.scene_id!r}, 'geometry', RunConfig.load(preset='tiny'), 'r')")
    env = {**os.environ, FAULT_ENV: "iter_0/geometry"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=300)
    assert proc.returncode == -9, proc.stderr.decode()[-2000:]
    st = Store(uri).scene(res.scene_id).status(GEOMETRY)
    assert st.exists and not st.complete  # arrays were written, the marker was not
    assert runner.run(uri, res.scene_id, "geometry", tiny, "r2").skipped is False
    assert Store(uri).scene(res.scene_id).status(GEOMETRY).complete
    assert Store(uri).scene(res.scene_id).status(INGEST).complete


def test_tables_roundtrip_latest_and_compact(tmp_path):
    s = Store(tmp_path / "s")
    t: Tables = s.tables
    with pytest.raises(KeyError, match="no column"):
        to_table("manifest", [{"source": "a", "status": "x", "updated_at": utcnow(), "bogus": 1}])
    t0 = utcnow()
    t.write("manifest", [{"source": "a.png", "status": "running", "updated_at": t0, "timings": {"x": 1.0}}])
    t.write("manifest", [{"source": "b.png", "status": "failed", "updated_at": t0, "error": "bad"}])
    t.write("manifest", [{"source": "a.png", "status": "done", "updated_at": utcnow(), "n_points": 5}])
    (tmp_path / "s" / "tables" / "manifest" / ".tmp-leftover").write_bytes(b"garbage from a crash")
    latest = t.latest("manifest", key=("source",), order="updated_at").to_pylist()
    assert [(r["source"], r["status"]) for r in latest] == [("a.png", "done"), ("b.png", "failed")]
    assert t.compact("manifest") == 3 and len(t.files("manifest")) == 1
    assert t.latest("manifest", key=("source",), order="updated_at").to_pylist() == latest
    # poses round-trip bit-exactly through Parquet as fixed-shape tensors
    poses = np.random.default_rng(0).normal(size=(3, 4, 4))
    rows = [{"scene_id": "s", "iteration": 1, "frame": i, "c2w": poses[i]} for i in range(3)]
    path = t.write("trajectories", rows, part="scene-s")
    back = pq.read_table(path).column("c2w").combine_chunks().to_numpy_ndarray()
    np.testing.assert_array_equal(back, poses)


def test_concurrent_table_writers_lose_nothing(tmp_path):
    t = Store(tmp_path / "s").tables

    def writer(i):
        for j in range(10):
            t.write("metrics", [{"scene_id": f"s{i}", "name": f"m{j}", "value": float(j), "created_at": utcnow()}])

    threads = [threading.Thread(target=writer, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert t.read("metrics").num_rows == 40


def test_compaction_races_with_writers_and_readers(tmp_path):
    t = Store(tmp_path / "s").tables
    stop = threading.Event()
    errors = []

    def writer(i):
        for j in range(15):
            t.write("steps", [{"scene_id": f"s{i}", "step": f"x{j}", "event": "completed", "at": utcnow()}])

    def compactor():
        while not stop.is_set():
            try:
                t.compact("steps")
            except Exception as exc:  # noqa: BLE001 - any error fails the test below
                errors.append(exc)

    def reader():
        while not stop.is_set():
            try:
                rows = t.read("steps").to_pylist()
                keys = [(r["scene_id"], r["step"]) for r in rows]
                assert len(keys) == len(set(keys)), "a row was read twice"
            except Exception as exc:  # noqa: BLE001
                errors.append(exc)

    side = [threading.Thread(target=f) for f in (compactor, compactor, reader)]
    writers = [threading.Thread(target=writer, args=(i,)) for i in range(3)]
    for th in side + writers:
        th.start()
    for th in writers:
        th.join()
    stop.set()
    for th in side:
        th.join()
    assert not errors, errors[:3]
    rows = t.read("steps").to_pylist()
    assert sorted((r["scene_id"], r["step"]) for r in rows) == sorted((f"s{i}", f"x{j}") for i in range(3)
                                                                      for j in range(15))


def test_a_store_another_process_creates_meanwhile_is_opened_not_a_crash(tmp_path, monkeypatch):
    """Two runs starting on a new store at once: both see no root and create it; zarr raises ContainsGroupError in the
    one that comes second, which then opens the other's (before: `ingest crashed: ContainsGroupError`, once in a
    fresh-clone run of the concurrent-runs flow test)."""
    import zarr
    from zarr.errors import ContainsGroupError

    uri = str(tmp_path / "store")
    real_open = zarr.open_group
    raced = []

    def open_group(*args, mode=None, **kwargs):
        if mode == "a" and not raced:  # the other process writes the root between our check and our create
            raced.append(real_open(*args, mode=mode, **kwargs))
            raise ContainsGroupError("A group exists in store at path ''.")
        return real_open(*args, mode=mode, **kwargs)

    monkeypatch.setattr(zarr, "open_group", open_group)
    store = Store(uri)
    assert raced and store.group.attrs["navcrafter_schema_version"] == raced[0].attrs["navcrafter_schema_version"]

"""The store on S3: Zarr groups, Parquet tables and a whole pipeline run on an ``s3://`` URL, against a
real S3-compatible server process (moto's server mode) started by these tests."""

from __future__ import annotations

import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
from helpers import BUCKET, DEMO, TINY, assert_same_outputs, s3_url

pytest.importorskip("s3fs")
pytest.importorskip("moto.server")

from navcrafter.schemas.layout import EVALUATE, EXPORT, LIFT, SYNTHESIZE  # noqa: E402
from navcrafter.schemas.store import Store, StoreError  # noqa: E402
from navcrafter.schemas.tables import utcnow  # noqa: E402

pytestmark = [
    pytest.mark.system,  # moto's S3 server (conftest.s3_endpoint), and whole flows on the Prefect test server
    pytest.mark.filterwarnings("ignore:Object at .* is not recognized:UserWarning"),
]


def test_step_roundtrip_on_s3(s3_endpoint):
    uri = s3_url("roundtrip")
    with pytest.raises(StoreError, match="no navcrafter store"):
        Store(uri, create=False)
    store = Store(uri)
    assert not store.local and store.storage_options["endpoint_url"] == s3_endpoint
    scene = store.scene("abc")
    w = scene.begin(LIFT, 1, key="k1", backend="simulation")
    rng = np.random.default_rng(0)
    arrays = {"view_index": np.array([0, 3], np.int32),
              "c2w": np.tile(np.eye(4), (2, 1, 1)),
              "K": np.tile(np.eye(3), (2, 1, 1)),
              "depth": rng.random((2, 8, 12), dtype=np.float32),
              "confidence": rng.random((2, 8, 12), dtype=np.float32),
              "cloud_points": rng.random((50, 3), dtype=np.float32),
              "cloud_colors": rng.integers(0, 255, (50, 3), dtype=np.uint8),
              "cloud_confidence": rng.random(50, dtype=np.float32)}
    assert set(arrays) == {a.name for a in LIFT.arrays}
    for name, data in arrays.items():
        w.write(name, data)
    rel = w.write_file("notes.bin", b"\x00payload")
    st = scene.status(LIFT, 1)
    assert st.exists and not st.complete  # nothing trusted before the commit
    with pytest.raises(StoreError, match="has not completed"):
        scene.read_all(LIFT, 1)
    w.commit(0.25, scale=1.0, n_new_points=50, n_points=50)

    again = Store(uri, create=False)  # a fresh Store (another process) sees the same
    assert again.scene_ids() == ["abc"]
    st = again.scene("abc").status(LIFT, 1)
    assert st.complete and st.key == "k1" and st.attrs["files"]["notes.bin"]["bytes"] == 8
    got = again.scene("abc").read_all(LIFT, 1)
    assert set(got) == set(w.written)
    for name in got:
        np.testing.assert_array_equal(got[name], arrays[name])
    assert again.read_bytes(rel) == b"\x00payload"
    assert again.fs.exists(again.path(rel))

    # a step begun again is rewritten from scratch: incomplete, old arrays and files gone
    w2 = scene.begin(LIFT, 1, key="k2", backend="simulation")
    st = again.scene("abc").status(LIFT, 1)
    assert st.exists and not st.complete and st.key == "k2"
    assert not again.fs.exists(again.path(rel))
    assert w2.exec_id != w.exec_id


def test_commit_refuses_a_group_another_run_took_over(s3_endpoint):
    """No lock on S3: if a second run restarts a step while the first still writes it, the first
    must not mark the group complete (it would certify the second run's partial arrays)."""
    scene = Store(s3_url("takeover")).scene("abc")
    frames = np.zeros((2, 4, 6, 3), np.uint8)
    first = scene.begin(SYNTHESIZE, 1, key="k", backend="simulation")
    first.write("frames", frames)
    second = scene.begin(SYNTHESIZE, 1, key="k", backend="simulation")
    with pytest.raises(StoreError, match="rewritten by another run"):
        first.commit(0.1)
    assert not scene.status(SYNTHESIZE, 1).complete
    second.write("frames", frames + 1)
    second.commit(0.1)
    st = scene.status(SYNTHESIZE, 1)
    assert st.complete and st.attrs["exec_id"] == second.exec_id
    np.testing.assert_array_equal(scene.read(SYNTHESIZE, 1, "frames"), frames + 1)


@pytest.mark.parametrize("var", ["FSSPEC_S3_ENDPOINT_URL", "explicit"])
def test_endpoint_configuration(s3_endpoint, monkeypatch, var):
    monkeypatch.delenv("AWS_ENDPOINT_URL")
    uri = s3_url("endpoint")
    if var == "explicit":
        store = Store(uri, storage_options={"endpoint_url": s3_endpoint, "key": "testing", "secret": "testing"})
    else:
        monkeypatch.setenv(var, s3_endpoint)
        store = Store(uri)
    assert store.fs.exists(store.path("zarr.json"))
    assert store.storage_options["endpoint_url"] == s3_endpoint


def test_tables_on_s3(s3_endpoint):
    store = Store(s3_url("tables"))
    t = store.tables
    assert t.read("metrics").num_rows == 0 and t.files("metrics") == []
    t0 = utcnow()
    t.write("metrics", [{"scene_id": "a", "name": "n_points", "value": 1.0, "created_at": t0},
                        {"scene_id": "b", "name": "n_points", "value": 2.0, "created_at": t0}])
    path = t.write("metrics", [{"scene_id": "a", "name": "n_points", "value": 3.0, "created_at": utcnow()}])
    t.write("metrics", [{"scene_id": "b", "name": "n_points", "value": 4.0, "created_at": utcnow()}], part="fixed")
    t.write("metrics", [{"scene_id": "b", "name": "n_points", "value": 5.0, "created_at": utcnow()}], part="fixed")
    fresh = Store(store.uri).tables  # another process
    assert len(fresh.files("metrics")) == 3  # the same part written twice is replaced, not added
    assert fresh.read("metrics").num_rows == 4
    latest = fresh.latest("metrics", ["scene_id", "name"], "created_at").to_pylist()
    assert [(r["scene_id"], r["value"]) for r in latest] == [("a", 3.0), ("b", 5.0)]
    with store.fs.open(path, "rb") as fh:
        assert pq.read_table(fh).column("value").to_pylist() == [3.0]
    assert t.compact("metrics") == 0  # no lock on object stores: compaction is skipped
    assert fresh.read("metrics").num_rows == 4


def test_explore_collection_on_s3_matches_local(s3_endpoint, prefect_api_url, demo_photos, full_run, tmp_path):
    """One image (the table-top; test_faults runs the room over S3 through a flaky proxy)."""
    from navcrafter.flows.explore import explore_collection
    from navcrafter.flows.tools.report import read_manifest
    from navcrafter.models.reconstruction.pointcloud import read_ply
    from navcrafter.tasks.runner import scene_steps

    photos = tmp_path / "photos"
    photos.mkdir()
    shutil.copy(demo_photos / "tabletop-0.png", photos / "tabletop-0.png")
    shutil.copytree(demo_photos / ".groundtruth", photos / ".groundtruth")
    uri = f"s3://{BUCKET}/store"
    run = explore_collection(str(photos), uri, TINY)
    assert [src.rsplit("/", 1)[-1] for r in run.scenes for src in r.sources] == ["tabletop-0.png"]
    assert all(r.status == "done" for r in run.scenes), [r.error for r in run.scenes]

    s3, local = Store(uri, create=False), Store(str(full_run[0]), create=False)
    assert len(s3.scene_ids()) == 1 and set(s3.scene_ids()) <= set(local.scene_ids())
    manifest = {r["scene_id"]: r for r in read_manifest(s3).to_pylist()}
    local_metrics = {r.scene_id: r.metrics for r in full_run[1].scenes}
    for r in run.scenes:
        assert manifest[r.scene_id]["status"] == "done"
        assert {**r.metrics, "plan_seconds": 0} == {**local_metrics[r.scene_id], "plan_seconds": 0}
    for sid in s3.scene_ids():
        a, b = s3.scene(sid), local.scene(sid)
        for spec, k in [(s.spec, s.k) for s in scene_steps(TINY)]:
            assert a.status(spec, k).complete and a.status(spec, k).key == b.status(spec, k).key
            if spec is EXPORT:
                for name in ("cloud.ply", "trajectory.json", "trajectory.parquet", "video.mp4"):
                    rel = a.file_rel(EXPORT, None, name)
                    assert s3.read_bytes(rel) == local.read_bytes(rel), (sid[:8], name)
                continue
            xa, xb = a.read_all(spec, k), b.read_all(spec, k)
            assert xa.keys() == xb.keys()
            for name in xa:
                np.testing.assert_array_equal(xa[name], xb[name], err_msg=f"{sid[:8]} {spec.group_path(k)}/{name}")
        cloud, comments = read_ply(s3.read_bytes(a.file_rel(EXPORT, None, "cloud.ply")))
        assert len(cloud) > 2000 and any("SIMULATION" in c for c in comments)
        assert a.status(EVALUATE).complete
    # the same flow again over the S3 store recomputes nothing
    again = explore_collection(str(photos), uri, TINY)
    events = [e for e in s3.tables.read("steps").to_pylist() if e["run_id"] == again.run_id]
    assert events and {e["event"] for e in events} == {"skipped"}


def test_photos_under_an_s3_prefix(s3_endpoint, prefect_api_url, demo_photos, full_run, tmp_path, monkeypatch):
    """A collection under an s3:// prefix (demo photos with their ground-truth sidecars, uploaded as
    objects) explored by the CLI into a local store: the same arrays and files as from the local photos.
    One image, to stay fast; listing, per-image submission and the errors are checked on three."""
    from typer.testing import CliRunner

    from navcrafter.flows.cli import app
    from navcrafter.flows.submit import collection_items
    from navcrafter.flows.tools.report import read_manifest
    from navcrafter.tasks.ingest import CollectionError, list_collection, source_fs

    fs, _ = source_fs(f"s3://{BUCKET}")
    everything = s3_url("photos")
    fs.put(str(demo_photos), everything.removeprefix("s3://"), recursive=True)  # photos + .groundtruth/
    assert list_collection(f"{everything}/") == [f"{everything}/{name}" for name in DEMO]  # sidecars hidden
    assert collection_items(everything, per_image=True) == [f"{everything}/{name}" for name in DEMO]
    assert collection_items(everything, per_image=False) == [everything]
    one = s3_url("one")
    for rel in ("tabletop-0.png", ".groundtruth/tabletop-0/scene.json"):
        fs.put_file(str(demo_photos / rel), f"{one.removeprefix('s3://')}/{rel}")

    store = tmp_path / "store"
    runner = CliRunner()
    res = runner.invoke(app, ["explore", f"{one}/", "--store", str(store), "--preset", "tiny"])
    assert res.exit_code == 0, res.output
    [row] = read_manifest(Store(str(store))).to_pylist()
    assert row["source"] == f"{one}/tabletop-0.png" and row["status"] == "done", row
    assert_same_outputs(full_run[0], store)

    # clear errors, naming the URL and the fix; nothing is written
    errors = {f"s3://{BUCKET}/nothing-here/": "no objects under",
              "s3://no-such-bucket/photos/": "bucket does not exist"}
    for url, message in errors.items():
        with pytest.raises(CollectionError, match=message):
            list_collection(url)
        res = runner.invoke(app, ["explore", url, "--store", str(tmp_path / "s")])
        assert res.exit_code == 2 and message in res.output and url in res.output, res.output
    monkeypatch.delenv("AWS_ACCESS_KEY_ID")
    monkeypatch.delenv("AWS_SECRET_ACCESS_KEY")
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    fs.clear_instance_cache()
    with pytest.raises(CollectionError, match="no credentials.*AWS_ACCESS_KEY_ID"):
        list_collection(everything)
    assert not (tmp_path / "s").exists()

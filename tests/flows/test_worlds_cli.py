"""``navcrafter demo-data --world``: a scan (built here, scan_fixtures) as the ground-truth world of the demo,
explored and evaluated unchanged."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scan_fixtures as sf
from typer.testing import CliRunner

from navcrafter.flows.cli import app
from navcrafter.models.camera.cameras import look_at

runner = CliRunner()
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # scan_fixtures.gt_to_yup as a matrix


def _file_c2w(eye, target) -> list:
    """An OpenCV c2w in the OBJ's (y up, uncentred) coordinates, from room coordinates (z up)."""
    M = look_at(np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64), up=np.array([0, 0, 1.0]))
    out = np.eye(4)
    out[:3, :3] = Z_UP_TO_Y_UP @ M[:3, :3]
    out[:3, 3] = Z_UP_TO_Y_UP @ M[:3, 3]
    return out.tolist()


def test_start_cameras_from_a_file_and_bad_scans(tmp_path):
    obj = sf.write_obj_room(tmp_path / "scan")
    cams = tmp_path / "cams.json"
    cams.write_text(json.dumps({"c2w": [_file_c2w((1.0, 2.0, 1.5), (4.0, 2.0, 1.2))]}))
    out = tmp_path / "photos"
    res = runner.invoke(app, ["demo-data", str(out), "--world", str(obj), "--start", str(cams), "--width", "96",
                              "--height", "72"])
    assert res.exit_code == 0, res.output
    record = json.loads((out / ".groundtruth" / "scan-room-v0" / "scene.json").read_text())
    c2w = np.asarray(record["photo"]["c2w"])
    np.testing.assert_allclose(c2w[:3, 3], [1.0 - sf.W / 2, 2.0 - sf.D / 2, 1.5], atol=0.02)  # centred room
    assert c2w[0, 2] > 0.9  # looking along +x
    assert record["scene"]["kind"] == "scan" and "SIMULATION" in record["note"]
    assert record["world"]["colour"] == "texture" and (out / "scan-room-v0.png").is_file()
    inside = tmp_path / "inside.json"
    inside.write_text(json.dumps({"c2w": [_file_c2w((4.0, 3.0, 0.4), (1.0, 1.0, 0.4))]}))  # in the crate
    res = runner.invoke(app, ["demo-data", str(tmp_path / "p2"), "--world", str(obj), "--start", str(inside)])
    assert res.exit_code == 2 and "start camera" in res.output and "inside.json" in res.output
    res = runner.invoke(app, ["demo-data", str(tmp_path / "p3"), "--world", str(tmp_path / "nope.obj")])
    assert res.exit_code == 2 and "nope.obj" in res.output and "does not exist" in res.output
    res = runner.invoke(app, ["demo-data", str(tmp_path / "p4"), "--world", str(obj), "--up", "sideways"])
    assert res.exit_code == 2 and "--up" in res.output


@pytest.mark.system
def test_scan_world_demo_explore_and_evaluate(prefect_api_url, tmp_path):
    from navcrafter.schemas.store import Store

    obj = sf.write_obj_room(tmp_path / "scan")
    photos, store = tmp_path / "photos", tmp_path / "store"
    res = runner.invoke(app, ["demo-data", str(photos), "--world", str(obj), "--views", "1", "--width", "160",
                              "--height", "120"])
    assert res.exit_code == 0, res.output
    assert [p.name for p in photos.iterdir() if p.is_file()] == ["scan-room-v0.png"]
    res = runner.invoke(app, ["explore", str(photos), "--store", str(store), "--preset", "tiny", "--parallel", "1"])
    assert res.exit_code == 0, res.output[-3000:]
    metrics = {m["name"]: m["value"] for m in Store(str(store)).tables.read("metrics").to_pylist()}
    assert 0 < metrics["coverage"] <= 1 and 0 <= metrics["noise_ratio"] < 1 and "collisions" in metrics
    # the lifted cloud lies on the scan (metres; a wrong scale or frame would put it metres off): the simulation's
    # draw alone moves it: 0.05-0.21 m in eight draws of this scene and two start-view rules (collide15)
    assert metrics["cloud_median_dist_m"] < 0.3
    from navcrafter.models.simulation import LABEL
    from navcrafter.models.simulation.worlds import LABEL as SCAN_LABEL

    said = " ".join(res.output.split())
    assert " ".join(SCAN_LABEL.split()) in said and LABEL not in said  # explore announces the scans' label
    summaries = list((store / "runs").glob("*/summary.md"))
    assert summaries and all(SCAN_LABEL in p.read_text() for p in summaries)  # the run summary names the scan
    exports = list(store.rglob("trajectory.json"))
    assert exports and all(json.loads(p.read_text())["label"] == SCAN_LABEL for p in exports)
    res = runner.invoke(app, ["evaluate", str(store)])
    assert res.exit_code == 0, res.output[-3000:]
    assert "PSNR" in res.output
    reports = list((store / "evaluations").glob("*/report.md"))
    assert reports and all(SCAN_LABEL in p.read_text() for p in reports)


def _ingested(tmp_path, kind: str | None, backend: str = "simulation"):
    """A scene whose ingest step carries a demo photo's truth record of ``kind`` (None: an ordinary photo)."""
    from navcrafter.schemas.layout import INGEST
    from navcrafter.schemas.store import Store

    scene = Store(str(tmp_path / f"store-{kind}-{backend}")).scene("a" * 64)
    w = scene.begin(INGEST, None, "key", backend)
    img = np.zeros((8, 8, 3), dtype=np.uint8)
    w.write("image", img)
    w.write("work_image", img)
    attrs = {"source": "photo.png", "sha256": "a" * 64, "original_size": [8, 8], "original_mode": "RGB",
             "exif_orientation": 1, "crop_box": [0, 0, 8, 8], "normalised_size": [8, 8], "work_size": [8, 8]}
    if kind is not None:
        attrs["simulation_truth"] = {"scene": {"kind": kind, "name": "room", "seed": 0}}
    w.commit(0.0, **attrs)
    return scene


def test_a_scan_worlds_outputs_carry_the_scan_label(tmp_path):
    """The run summary, the export's label reader, the dashboard and the evaluation report name the scan when the
    scene is a scanned world (``simulation_label``: the one source), the generated scenes' label otherwise."""
    from helpers import TINY

    from navcrafter.flows.tools.dashboard import scene_dashboard_markdown
    from navcrafter.flows.tools.report import SceneResult, scene_result, summary_markdown
    from navcrafter.models.simulation import LABEL, simulation_label
    from navcrafter.models.simulation.worlds import LABEL as SCAN_LABEL
    from navcrafter.tasks.readers import scene_label, scene_run_label
    from navcrafter.tasks.score import evaluation_markdown

    assert SCAN_LABEL != LABEL and "scan" in SCAN_LABEL
    assert simulation_label({"kind": "scan"}) == SCAN_LABEL and simulation_label({"kind": "room"}) == LABEL
    assert simulation_label(None) == LABEL
    sim = TINY.model_copy(update={"backend": "simulation"})
    scan, room, photo = _ingested(tmp_path, "scan"), _ingested(tmp_path, "room"), _ingested(tmp_path, None)
    assert scene_run_label(scan, sim) == SCAN_LABEL and scene_label(scan) == SCAN_LABEL
    assert scene_run_label(room, sim) == LABEL and scene_label(room) == LABEL and scene_run_label(photo, sim) == LABEL
    assert scene_run_label(_ingested(tmp_path, "scan", "onnx"), TINY.model_copy(update={"backend": "onnx"})) != \
        SCAN_LABEL
    r_scan = scene_result(scan, ["scan-room-v0.png"], sim, "done")
    assert r_scan.label == SCAN_LABEL
    md = summary_markdown("r1", sim, [r_scan])
    assert SCAN_LABEL in md and "procedurally generated" not in md
    both = summary_markdown("r2", sim, [r_scan, scene_result(room, ["room.png"], sim, "done")])
    assert SCAN_LABEL in both and LABEL in both
    assert LABEL in summary_markdown("r3", sim, [SceneResult("b" * 64, ["room.png"], "done")])
    dash = scene_dashboard_markdown(str(tmp_path / "store-scan-simulation"), "a" * 64, sim)
    assert SCAN_LABEL in dash and "scanned world" in dash and "generated" not in dash
    report = evaluation_markdown("e1", [], {}, "simulation", [SCAN_LABEL])
    assert SCAN_LABEL in report and LABEL not in report
    assert LABEL in evaluation_markdown("e2", [], {}, "simulation")

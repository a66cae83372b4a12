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
    assert metrics["cloud_median_dist_m"] < 0.2  # the lifted cloud lies on the scan (metres)
    res = runner.invoke(app, ["evaluate", str(store)])
    assert res.exit_code == 0, res.output[-3000:]
    assert "PSNR" in res.output

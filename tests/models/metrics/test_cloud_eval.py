"""``navcrafter evaluate-cloud`` (models.metrics.cloud.cloud_metrics, flows.tools.interchange.evaluate_cloud_files,
flows/cli/cloud.py): precision / recall / F-score / Coverage / Noise ratio of a cloud against a reference cloud,
before and after ICP; a mesh reference sampled; unreadable and empty files named in the error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from navcrafter.flows.cli import app
from navcrafter.models.metrics.cloud import cloud_metrics

runner = CliRunner()
T = 0.02


def box_surface(n: int, rng, faces=range(6)) -> np.ndarray:
    """``n`` points uniform on the given faces of the unit cube [0, 1]^3 (face f: axis f // 2 at f % 2)."""
    faces = list(faces)
    face = rng.choice(faces, n)
    pts = rng.random((n, 3))
    pts[np.arange(n), face // 2] = face % 2
    return pts


def outliers(n: int, rng) -> np.ndarray:
    """Points at least 0.1 outside the cube (more than 5 thresholds from every face)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return 0.5 + d * rng.uniform(0.87 + 0.1, 1.5, (n, 1))  # the cube's circumradius is 0.866


@pytest.fixture(scope="module")
def clouds():
    """GT: 60k points on the box. Pred: 50k points on 5 faces (the top z=1 missing) with 3 mm noise, shifted by
    5 mm, plus 5k outliers."""
    rng = np.random.default_rng(0)
    gt = box_surface(60_000, rng)
    surface = box_surface(50_000, rng, faces=range(5)) + rng.normal(0, 0.003, (50_000, 3)) + [0.003, -0.004, 0.0]
    pred = np.concatenate([surface, outliers(5_000, rng)])
    return gt, pred


def write_ply(path: Path, points: np.ndarray) -> Path:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(points)
    assert o3d.io.write_point_cloud(str(path), pcd)
    return path


def test_known_precision_and_recall(clouds):
    gt, pred = clouds
    m = cloud_metrics(pred, gt, T)
    # precision: the surface points (noise and shift well inside 2 cm) out of all
    assert m["precision"] == pytest.approx(50_000 / 55_000, abs=0.005)
    # recall: five faces, plus the 2 cm band of the missing face along its four edges (1 - 0.96^2 of it)
    assert m["recall"] == pytest.approx((5 + 1 - 0.96 ** 2) / 6, abs=0.01)
    assert m["coverage"] == m["recall"] and m["noise_ratio"] == pytest.approx(1 - m["precision"])
    p, r = m["precision"], m["recall"]
    assert m["fscore"] == pytest.approx(2 * p * r / (p + r))
    assert m["median_dist_to_reference"] < T and m["median_dist_from_reference"] < T
    # the same numbers as coverage_metrics (the scene metrics' definitions) with nearest-point distances
    from navcrafter.models.metrics.cloud import coverage_metrics, nearest_distances

    ref = coverage_metrics(pred, gt, nearest_distances(pred, gt), T)
    assert all(m[k] == ref[k] for k in ref)
    # a perfect copy scores 1; nothing at all scores 0
    assert cloud_metrics(gt, gt, T)["fscore"] == 1.0
    empty = cloud_metrics(np.zeros((0, 3)), gt, T)
    assert empty["precision"] == empty["recall"] == empty["fscore"] == 0.0


def test_alignment_improves_a_shifted_copy(clouds, tmp_path):
    from navcrafter.flows.tools.interchange import evaluate_cloud_files
    from navcrafter.models.camera.cameras import axis_angle_to_matrix

    gt, _ = clouds
    rng = np.random.default_rng(1)
    R = axis_angle_to_matrix(np.array([1.0, 2.0, 0.5]), np.deg2rad(1.0))
    shift = np.array([0.03, -0.02, 0.025])
    copy = (box_surface(40_000, rng) - 0.5) @ R.T + 0.5 + shift
    a, b = write_ply(tmp_path / "pred.ply", copy), write_ply(tmp_path / "gt.ply", gt)
    doc = evaluate_cloud_files(a, b, T, align=True)
    before, after = doc["unaligned"], doc["aligned"]
    assert before["fscore"] < 0.6 and after["fscore"] > 0.97 and after["fscore"] > before["fscore"] + 0.3
    X = np.asarray(after["transform"])
    assert X.shape == (4, 4) and np.allclose(X[3], [0, 0, 0, 1])
    # the transform undoes the shift: the copy's centre goes back to the box's
    moved_centre = (copy.mean(0) @ X[:3, :3].T) + X[:3, 3]
    assert np.linalg.norm(moved_centre - 0.5) < 0.005
    assert after["icp"]["max_correspondence_distance"] == pytest.approx(5 * T) and after["icp"]["fitness"] > 0.9
    assert doc["n_pred"] == 40_000 and doc["n_gt"] == len(gt) and not doc["gt_sampled_from_mesh"]
    # without --align, no aligned section
    assert "aligned" not in evaluate_cloud_files(a, b, T)


def test_cli_table_json_and_a_mesh_reference(clouds, tmp_path):
    import open3d as o3d

    _, pred = clouds
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)  # the unit cube [0, 1]^3
    assert o3d.io.write_triangle_mesh(str(tmp_path / "box.ply"), mesh)
    p = write_ply(tmp_path / "pred.ply", pred)
    out = tmp_path / "res" / "metrics.json"
    res = runner.invoke(app, ["evaluate-cloud", str(p), str(tmp_path / "box.ply"), "--threshold", "0.02",
                              "--mesh-points", "60000", "--align", "--out", str(out)])
    assert res.exit_code == 0, res.output
    for word in ("Precision", "Recall", "F-score", "Coverage", "Noise ratio", "ICP-aligned", "GT is a mesh"):
        assert word in res.output
    doc = json.loads(out.read_text())
    assert doc["gt_sampled_from_mesh"] and doc["n_gt"] == 60_000 and doc["threshold"] == 0.02
    m = doc["unaligned"]
    assert m["precision"] == pytest.approx(50_000 / 55_000, abs=0.005)
    assert m["recall"] == pytest.approx((5 + 1 - 0.96 ** 2) / 6, abs=0.015)
    assert set(doc["aligned"]) >= {"precision", "recall", "fscore", "coverage", "noise_ratio", "transform", "icp"}


def test_bad_files_are_named(tmp_path, clouds):
    gt, _ = clouds
    good = write_ply(tmp_path / "gt.ply", gt[:1000])
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01 this is not a point cloud" * 10)
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n")
    for bad, words in ((tmp_path / "missing.ply", "no such file"), (garbage, "no points"), (empty, "no points")):
        for args in ([str(bad), str(good)], [str(good), str(bad)]):
            res = runner.invoke(app, ["evaluate-cloud", *args])
            assert res.exit_code == 2, res.output
            assert bad.name in res.output and words in res.output
    res = runner.invoke(app, ["evaluate-cloud", str(good), str(good), "--threshold", "0"])
    assert res.exit_code == 2 and "--threshold must be positive" in res.output

from __future__ import annotations

import numpy as np
import pytest

from navcrafter.models.reconstruction.pointcloud import Cloud, ply_bytes, read_ply, voxel_fuse


def test_voxel_fuse_averages_per_voxel():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [0.5, 0.5, 0.5], [-0.01, 0, 0]])
    cols = np.array([[0, 0, 0], [100, 100, 100], [10, 20, 30], [7, 7, 7]])
    conf = np.array([1.0, 1.0, 0.4, 0.9])
    out = voxel_fuse(Cloud(pts, cols, conf), 0.1)
    assert len(out) == 3  # the negative x point falls into its own voxel
    i = int(np.argmin(np.abs(out.points[:, 0] - 0.02)))
    np.testing.assert_allclose(out.points[i], [0.02, 0.01, 0.01], atol=1e-6)
    np.testing.assert_array_equal(out.colors[i], [50, 50, 50])
    assert sorted(np.round(out.confidence.astype(float), 3).tolist()) == [0.4, 0.9, 1.0]
    with pytest.raises(ValueError):
        voxel_fuse(Cloud(pts, cols, conf), 0.0)


def test_voxel_fuse_is_deterministic_and_order_independent():
    rng = np.random.default_rng(0)
    c = Cloud(rng.uniform(-2, 2, (5000, 3)), rng.integers(0, 255, (5000, 3)), rng.uniform(0.5, 1, 5000))
    a = voxel_fuse(c, 0.2)
    perm = rng.permutation(5000)
    b = voxel_fuse(Cloud(c.points[perm], c.colors[perm], c.confidence[perm]), 0.2)
    np.testing.assert_array_equal(a.colors, b.colors)
    np.testing.assert_allclose(a.points, b.points, atol=1e-6)
    assert len(voxel_fuse(Cloud.empty(), 0.1)) == 0


def test_ply_roundtrip_and_comments():
    rng = np.random.default_rng(1)
    c = Cloud(rng.normal(size=(100, 3)), rng.integers(0, 255, (100, 3)), rng.uniform(size=100))
    data = ply_bytes(c, ["backend simulation"])
    back, comments = read_ply(data)
    np.testing.assert_array_equal(back.points, c.points)
    np.testing.assert_array_equal(back.colors, c.colors)
    assert comments == ["backend simulation"]
    import open3d as o3d  # a standard reader opens it too

    path = "/tmp/_navcrafter_test.ply"
    with open(path, "wb") as fh:
        fh.write(data)
    pcd = o3d.io.read_point_cloud(path)
    np.testing.assert_allclose(np.asarray(pcd.points), c.points, atol=1e-6)
    with pytest.raises(ValueError):
        read_ply(b"not a ply")
    with pytest.raises(ValueError):
        Cloud(np.zeros((2, 3)), np.zeros((3, 3)), np.zeros(2))

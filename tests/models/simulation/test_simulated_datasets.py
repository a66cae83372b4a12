"""The simulation data engine: datasets the readers read back with the exact cameras, depth beside the frames,
collision-free and diverse trajectories."""

from __future__ import annotations

import json

import numpy as np
import pytest

from navcrafter.models.camera.cameras import Intrinsics, rotation_angle_deg
from navcrafter.models.simulation.datasets import (
    CLEARANCE,
    MANIFEST,
    TRAJECTORIES,
    depth_path,
    sequence_trajectory,
    write_dataset,
)
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.scenes import KINDS, generate_scene
from navcrafter.schemas.datasets import open_dataset


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


@pytest.mark.parametrize("kind", ["re10k", "dl3dv"])
def test_round_trip_exact_cameras_frames_and_depth(tmp_path, kind):
    H, W = 24, 32
    names = write_dataset(tmp_path, kind, sequences=4, frames=6, resolution=(H, W), seed=5)
    assert names == sorted(names) and len(set(names)) == 4
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert "SIMULATION" in manifest["note"]
    records = {r["name"]: r for r in manifest["sequences"]}
    assert {r["trajectory"] for r in records.values()} == set(TRAJECTORIES)
    assert {r["scene"]["kind"] for r in records.values()} == set(KINDS)
    options = {"split": None} if kind == "re10k" else {}
    reader = open_dataset(kind, tmp_path, resolution=None, num_frames=5, start="first", strict=True, **options)
    samples = list(reader)
    assert sorted(s.sequence for s in samples) == names
    for s in samples:
        rec = records[s.sequence]
        c2w, K = np.asarray(rec["c2w"]), np.asarray(rec["K"])
        assert _rel_err(s.c2w, c2w) < 1e-6
        assert _rel_err(s.K, np.broadcast_to(K, s.K.shape)) < 1e-6
        assert s.images.shape == (6, H, W, 3)
        # the frames are the renders of the true scene from those cameras; the depth beside them too
        scene = generate_scene(rec["scene"]["kind"], rec["scene"]["seed"])
        intr = Intrinsics.from_matrix(K, W, H)
        for i in (0, 5):
            r = render(scene, c2w[i], intr)
            np.testing.assert_array_equal(s.images[i], r.rgb)
            depth = np.load(depth_path(s.paths[i]))
            assert depth.dtype == np.float32 and depth.shape == (H, W)
            np.testing.assert_array_equal(depth, r.depth)


def test_both_formats_and_splits_hold_the_same_cameras(tmp_path):
    write_dataset(tmp_path / "re", "re10k", sequences=2, frames=5, resolution=16, seed=2, split="train",
                  depth=False)
    write_dataset(tmp_path / "dl", "dl3dv", sequences=2, frames=5, resolution=16, seed=2, depth=False)
    a = {s.sequence: s for s in open_dataset("re10k", tmp_path / "re", split="train", resolution=None,
                                             num_frames=4, start="first")}
    b = {s.sequence: s for s in open_dataset("dl3dv", tmp_path / "dl", resolution=None, num_frames=4,
                                             start="first")}
    assert a.keys() == b.keys()
    for name in a:
        assert _rel_err(a[name].c2w, b[name].c2w) < 1e-6
        np.testing.assert_array_equal(a[name].images, b[name].images)
        assert not depth_path(a[name].paths[0]).exists()  # depth=False writes none


def test_sequences_are_seeded_one_by_one(tmp_path):
    write_dataset(tmp_path / "a", "re10k", sequences=2, frames=4, resolution=8, seed=9, depth=False)
    write_dataset(tmp_path / "b", "re10k", sequences=3, frames=4, resolution=8, seed=9, depth=False)
    write_dataset(tmp_path / "c", "re10k", sequences=2, frames=4, resolution=8, seed=10, depth=False)
    for name in ("sim-00000-room-orbit", "sim-00001-street-dolly"):
        assert (tmp_path / "a" / f"{name}.txt").read_text() == (tmp_path / "b" / f"{name}.txt").read_text()
        assert (tmp_path / "a" / f"{name}.txt").read_text() != (tmp_path / "c" / f"{name}.txt").read_text()


@pytest.mark.parametrize("scene_kind", KINDS)
def test_trajectories_collision_free_and_of_their_kind(scene_kind):
    scene = generate_scene(scene_kind, 4)
    for kind in TRAJECTORIES:
        for seed in range(2):
            c2w = sequence_trajectory(scene, kind, 9, np.random.default_rng([seed, 1]))
            np.testing.assert_allclose(c2w[0], scene.camera_c2w, atol=1e-9)  # starts at the input photo
            pos = c2w[:, :3, 3]
            assert scene.distance(pos).min() >= CLEARANCE
            travel = np.linalg.norm(pos - pos[0], axis=1).max()
            turn = rotation_angle_deg(c2w[0, :3, :3], c2w[-1, :3, :3])
            where = f"{scene_kind}/{kind}/{seed}"
            if kind == "pan":
                assert travel == 0 and turn > 5, where
            elif kind == "dolly":
                assert travel > 0.05 and turn < 1e-6, where
                step = pos[-1] - pos[0]
                assert abs(step @ c2w[0, :3, 2]) / np.linalg.norm(step) > 0.9, where  # along the optical axis
            elif kind == "orbit":
                assert travel > 0.05 and turn > 5, where
                # every optical axis passes through one point (the orbit centre): least-squares meeting point
                axes = c2w[:, :3, 2]
                proj = np.eye(3) - axes[:, :, None] * axes[:, None, :]
                centre = np.linalg.solve(proj.sum(0), np.einsum("nij,nj->i", proj, pos))
                d = centre - pos
                off = np.linalg.norm(d - (d * axes).sum(1, keepdims=True) * axes, axis=1)
                assert off.max() < 1e-6 and ((d * axes).sum(1) > 0).all(), where
            else:
                assert travel > 0.05 and turn > 1, where


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="kind must be"):
        write_dataset(tmp_path, "tnt", sequences=1, frames=3, resolution=8, seed=0)
    with pytest.raises(ValueError, match="trajectories"):
        write_dataset(tmp_path, "re10k", sequences=1, frames=3, resolution=8, seed=0, trajectories=("spiral",))
    with pytest.raises(ValueError, match="frames >= 2"):
        write_dataset(tmp_path, "re10k", sequences=1, frames=1, resolution=8, seed=0)
    with pytest.raises(ValueError, match="split"):
        write_dataset(tmp_path, "dl3dv", sequences=1, frames=3, resolution=8, seed=0, split="train")

"""A user's camera path in place of the planner: presets and camera files (`plan.trajectory`,
`explore --trajectory`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from navcrafter.models.camera.cameras import invert_pose, look_at
from navcrafter.models.camera.trajectories import GL_CV_FLIP, read_camera_file
from navcrafter.models.planning.user import parse_spec, resample, user_path
from navcrafter.schemas.config import RunConfig

runner = CliRunner()


def _path(n: int = 6) -> np.ndarray:
    """A camera moving right and turning left, in some world frame far from the origin."""
    out = []
    for i in range(n):
        eye = np.array([10.0 + 0.2 * i, -3.0, 5.0])
        out.append(look_at(eye, eye + np.array([np.sin(-0.1 * i), 0.0, np.cos(-0.1 * i)]), up=(0.0, -1.0, 0.0)))
    return np.array(out)


def test_specs_are_checked_before_any_work(tmp_path):
    assert parse_spec("arc:-45").preset == "arc" and parse_spec("arc:-45").size == -45.0
    assert parse_spec("dolly").size is None
    for bad, message in (("zoom", "one focal length"), ("arc:left", "must be a number"),
                         (str(tmp_path / "none.txt"), "neither a preset")):
        with pytest.raises(ValueError, match=message):
            parse_spec(bad)
    (tmp_path / "broken.json").write_text(json.dumps({"c2w": [[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, 0],
                                                              [0, 0, 0, 1]]]}))
    with pytest.raises(ValueError, match=r"broken.json: c2w\[0\].*not a rotation"):
        parse_spec(str(tmp_path / "broken.json"))
    with pytest.raises(Exception, match="plan.trajectory"):  # the config refuses it too, naming the field
        RunConfig.load(overrides={"plan.trajectory": ["zoom"]})
    (tmp_path / "ok.npy").write_bytes(b"")
    np.save(tmp_path / "ok.npy", _path())
    cfg = RunConfig.load(overrides={"plan.trajectory": ["orbit:30", str(tmp_path / "ok.npy")]})
    assert cfg.plan.trajectory == ["orbit:30", str((tmp_path / "ok.npy").resolve())]


def test_matrix_files_in_both_conventions(tmp_path):
    c2w = _path()
    np.save(tmp_path / "cv.npy", c2w)
    (tmp_path / "gl.json").write_text(json.dumps({"c2w": (c2w @ GL_CV_FLIP).tolist(), "convention": "opengl"}))
    (tmp_path / "list.json").write_text(json.dumps(c2w[:, :3].tolist()))  # 3x4 rows
    for name in ("cv.npy", "gl.json", "list.json"):
        np.testing.assert_allclose(read_camera_file(tmp_path / name).c2w, c2w, atol=1e-12)
    # the caller states the axes of a bare array
    np.save(tmp_path / "gl.npy", c2w @ GL_CV_FLIP)
    np.testing.assert_allclose(read_camera_file(tmp_path / "gl.npy", "opengl").c2w, c2w, atol=1e-12)
    np.save(tmp_path / "flat.npy", c2w.reshape(-1, 16))
    with pytest.raises(ValueError, match=r"flat.npy: expected N camera-to-world matrices"):
        read_camera_file(tmp_path / "flat.npy")


def test_a_file_is_taken_relative_to_its_first_camera_and_scaled_to_the_scene(tmp_path):
    c2w = _path(6)
    np.save(tmp_path / "path.npy", c2w)
    spec = parse_spec(str(tmp_path / "path.npy"))
    current = look_at(np.array([0.5, 0.0, -0.2]), np.array([0.0, 0.0, 2.0]), up=(0.0, -1.0, 0.0))
    centre = np.array([0.0, 0.0, 2.0])
    d = float(np.linalg.norm(centre - current[:3, 3]))
    out = user_path(spec, current, centre, 11, extent=0.5)
    traj = out.trajectory
    assert traj.shape == (11, 4, 4) and np.allclose(traj[0], current)
    rel = np.einsum("ij,njk->nik", invert_pose(current), traj)
    far = np.linalg.norm(rel[:, :3, 3], axis=1).max()
    assert far == pytest.approx(0.5 * d)  # the farthest camera at trajectory_extent x the distance to o
    rel_file = np.einsum("ij,njk->nik", invert_pose(c2w[0]), c2w)
    np.testing.assert_allclose(rel[-1, :3, :3], rel_file[-1, :3, :3], atol=1e-9)  # rotations kept
    np.testing.assert_allclose(rel[-1, :3, 3] / far, rel_file[-1, :3, 3] / np.linalg.norm(rel_file[-1, :3, 3]),
                               atol=1e-9)  # the direction of travel kept
    assert out.source["file_poses"] == 6 and len(out.source["sha256"]) == 64
    same = user_path(spec, current, centre, 11, extent=0.0).trajectory  # the file's own units
    rel0 = np.einsum("ij,njk->nik", invert_pose(current), same)
    assert np.linalg.norm(rel0[-1, :3, 3]) == pytest.approx(np.linalg.norm(rel_file[-1, :3, 3]))
    # resampling: evenly over the file's frames, the ends exact
    r = resample(c2w, 11)
    np.testing.assert_allclose(r[[0, -1]], c2w[[0, -1]], atol=1e-12)
    np.testing.assert_allclose(r[2], c2w[1], atol=1e-9)


def test_presets_start_at_the_current_camera_and_aim_at_the_centre():
    current = np.eye(4)
    centre = np.array([0.0, 0.0, 3.0])
    traj = user_path(parse_spec("arc:40"), current, centre, 9, extent=0.5).trajectory
    assert np.allclose(traj[0], current)
    for pose in traj:  # an arc keeps its distance to the centre and looks at it
        to_centre = centre - pose[:3, 3]
        assert np.linalg.norm(to_centre) == pytest.approx(3.0)
        assert np.dot(pose[:3, 2], to_centre / np.linalg.norm(to_centre)) == pytest.approx(1.0, abs=1e-9)


def test_explore_follows_the_given_trajectory_and_flags_collisions(demo_photos, tmp_path):
    from navcrafter.schemas.layout import PLAN
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.ingest import ingest
    from navcrafter.tasks.runner import run_scene

    # iteration 1 a short dolly towards the centre (space the photo saw free), iteration 2 a truck 3x the
    # distance to the centre sideways: through the room's wall
    cfg = RunConfig.load(preset="tiny", overrides={"plan.trajectory": ["dolly:0.3", "truck:3"]})
    store = str(tmp_path / "store")
    sid = ingest(store, str(demo_photos / "room-0.png"), cfg, "t").scene_id
    run_scene(store, sid, cfg, "t")
    scene = Store(store).scene(sid)
    a1, a2 = scene.status(PLAN, 1).attrs, scene.status(PLAN, 2).attrs
    assert a1["strategy"] == a2["strategy"] == "trajectory"
    assert a1["trajectory"] == "dolly:0.3" and a1["source"]["preset"] == "dolly"
    assert a1["collision_free"] and not a1["warning"]
    assert not a2["collision_free"] and a2["colliding_frames"] > 0 and "truck:3" in a2["warning"]
    assert "kept as given" in a2["warning"]
    t2 = scene.read(PLAN, 2, "trajectory")
    assert np.array_equal(t2, scene.read(PLAN, 2, "initial_trajectory"))
    # exported as before: the path of iteration 2 is in trajectory.json
    from navcrafter.schemas.layout import EXPORT

    doc = json.loads(Store(store).read_bytes(scene.file_rel(EXPORT, None, "trajectory.json")))
    exported = np.array([f["c2w"] for f in doc["frames"] if f["iteration"] == 2])
    assert len(exported) == len(t2)
    # repair: the collision optimisation moves the colliding path (same end poses) or says it could not
    fixed = RunConfig.load(preset="tiny", overrides={"plan.trajectory": ["dolly:0.3", "truck:3"],
                                                      "plan.trajectory_repair": True})
    from navcrafter.tasks import runner

    runner.run(store, sid, "plan", fixed, "t2", k=2)
    b2 = scene.status(PLAN, 2).attrs
    assert "repaired" in b2["warning"] or "found no safe path" in b2["warning"]
    if b2["optimised"]:
        t = scene.read(PLAN, 2, "trajectory")
        assert np.allclose(t[[0, -1]], t2[[0, -1]]) and not np.allclose(t, t2)

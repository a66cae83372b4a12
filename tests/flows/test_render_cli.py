"""``navcrafter render`` (flows/cli/render.py over flows/tools/render.py, whose own tests are
tests/flows/tools/test_render.py): PLYs of any 3DGS tool and a scene's fitted Gaussians, rendered along
presets and camera files to PNG frames and an MP4; bad input ends with a message and exit code 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from render_fixtures import blob_model, write_scene
from typer.testing import CliRunner

from navcrafter.flows.cli import app
from navcrafter.models.gaussians.ply import load_gaussian_ply, load_ply, save_ply

pytestmark = pytest.mark.usefixtures("one_torch_thread")
runner = CliRunner()
SIZE = ["--width", "32", "--height", "32"]


def inria_ply(path: Path, n=150, *, quat_scale=7.0, rows=None, count=None, props=None, fmt="binary_little_endian"
              ) -> Path:
    """A PLY as the INRIA 3DGS code writes it (with normals), SH degree 0, unnormalised quaternions."""
    names = props or ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                      "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rng = np.random.default_rng(1)
    arr = np.zeros(n, dtype=[(k, "<f4") for k in names])
    for k in names:
        arr[k] = rng.normal(size=n)
    for k in ("x", "y", "z"):
        if k in names:
            arr[k] = rng.uniform(-1, 1, n) + (3 if k == "z" else 0)
    for k in ("scale_0", "scale_1", "scale_2"):
        if k in names:
            arr[k] = -2.5
    if "opacity" in names:
        arr["opacity"] = 3.0
    for k in ("rot_0", "rot_1", "rot_2", "rot_3"):
        if k in names:
            arr[k] *= quat_scale
    if rows is not None:
        rows(arr)
    header = ["ply", f"format {fmt} 1.0", f"element vertex {n if count is None else count}",
              *(f"property float {k}" for k in names), "end_header"]
    path.write_bytes(("\n".join(header) + "\n").encode() + arr.tobytes())
    return path


def frames_of(out: Path) -> list[Path]:
    return sorted((out / "frames").glob("*.png"))


def ok(res) -> None:
    assert res.exit_code == 0, (res.output, res.exception)


def test_our_ply_with_sh_degree_3_renders_frames_and_an_mp4(tmp_path):
    model = blob_model(degree=3)
    ply = save_ply(tmp_path / "ours.ply", model, comments="navcrafter test")
    out = tmp_path / "out"
    res = runner.invoke(app, ["render", str(ply), "--out", str(out), "--frames", "3", *SIZE])
    ok(res)
    pngs = frames_of(out)
    assert [p.name for p in pngs] == ["00000.png", "00001.png", "00002.png"]
    imgs = [np.asarray(Image.open(p)) for p in pngs]
    assert all(im.shape == (32, 32, 3) for im in imgs)
    assert all(im.mean() > 5 for im in imgs)  # the framed Gaussians are in view
    assert (out / "render.mp4").stat().st_size > 200
    cams = json.loads((out / "cameras.json").read_text())
    assert len(cams["frames"]) == 3 and "label" not in cams and cams["width"] == 32
    # a rerun with fewer frames leaves no stale frame behind; the preset turns the camera
    res = runner.invoke(app, ["render", str(ply), "--out", str(out), "--frames", "2", "--trajectory", "pan",
                              "--degrees", "20", *SIZE, "--background", "255,255,255"])
    ok(res)
    assert len(frames_of(out)) == 2
    c2w = np.array([f["c2w"] for f in json.loads((out / "cameras.json").read_text())["frames"]])
    assert np.rad2deg(np.arccos(c2w[0, :3, 2] @ c2w[1, :3, 2])) == pytest.approx(20)
    assert np.asarray(Image.open(frames_of(out)[0]))[0, 0].tolist() == [255, 255, 255]  # background


def test_inria_ply_with_unnormalised_quaternions_and_degree_0(tmp_path):
    ply = inria_ply(tmp_path / "point_cloud.ply")
    model = load_gaussian_ply(ply)
    assert model.sh_degree == 0 and len(model) == 150
    np.testing.assert_allclose(torch.linalg.vector_norm(model.quats, dim=1).numpy(), 1.0, rtol=1e-6)
    raw = load_ply(ply)  # the plain load keeps what is stored
    assert torch.linalg.vector_norm(raw.quats, dim=1).mean() > 3
    out = tmp_path / "out"
    res = runner.invoke(app, ["render", str(ply), "--out", str(out), "--frames", "4", "--trajectory", "orbit",
                              "--width", "32"])
    ok(res)
    assert len(frames_of(out)) == 4 and (out / "render.mp4").stat().st_size > 200
    assert np.asarray(Image.open(frames_of(out)[3])).shape == (32, 32, 3)  # width alone: square like the default
    assert np.asarray(Image.open(frames_of(out)[3])).mean() > 5


def test_simulation_ply_is_labelled(tmp_path):
    ply = save_ply(tmp_path / "sim.ply", blob_model(degree=1),
                   comments=["SIMULATION MODE: rendered from procedurally generated ground truth"])
    out = tmp_path / "out"
    ok(runner.invoke(app, ["render", str(ply), "--out", str(out), "--frames", "2", "--width", "64", "--height",
                           "64", "--background", "0,0,0"]))
    assert json.loads((out / "cameras.json").read_text())["label"] == "SIMULATION"
    corner = np.asarray(Image.open(frames_of(out)[0]))[:6, :40]
    assert ((corner[..., 0] > 200) & (corner[..., 2] < 60)).any()  # the yellow band


def _bad_files(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    text = tmp_path / "notes.ply"
    text.write_text("hello\n")
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")

    def nan_rows(arr):
        arr["x"][[3, 7]] = np.nan
        arr["scale_1"][9] = np.inf

    def zero_quat(arr):
        for k in ("rot_0", "rot_1", "rot_2", "rot_3"):
            arr[k][4] = 0.0

    truncated = inria_ply(tmp_path / "trunc.ply", count=151)
    return {
        "not a ply": (text, "not a PLY file"),
        "ascii": (ascii_ply, "only binary_little_endian PLY is supported, got format 'ascii'"),
        "missing": (inria_ply(tmp_path / "cloud.ply", props=["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]),
                    "missing properties ['opacity', 'scale_0', 'scale_1', 'scale_2', 'rot_0', 'rot_1', 'rot_2', "
                    "'rot_3']"),
        "f_rest count": (inria_ply(tmp_path / "rest.ply", props=["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2",
                                                                 *(f"f_rest_{i}" for i in range(12)), "opacity",
                                                                 "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
                                                                 "rot_2", "rot_3"]),
                         "12 f_rest_* properties; a 3DGS PLY has 0, 9, 24 or 45"),
        "truncated": (truncated, "truncated PLY: the header declares 151 Gaussians"),
        "nan": (inria_ply(tmp_path / "nan.ply", rows=nan_rows),
                "3 of 150 Gaussians have NaN/inf values (rows [3, 7, 9]"),
        "zero quaternion": (inria_ply(tmp_path / "q.ply", rows=zero_quat),
                            "1 of 150 Gaussians have a zero quaternion"),
        "empty": (inria_ply(tmp_path / "empty.ply", n=0), "holds zero Gaussians"),
        "absent": (tmp_path / "absent.ply", "does not exist"),
    }


def test_bad_plys_end_with_a_message_and_the_usage_code(tmp_path):
    for what, (path, message) in _bad_files(tmp_path).items():
        res = runner.invoke(app, ["render", str(path), "--out", str(tmp_path / "out"), "--frames", "1", *SIZE])
        assert res.exit_code == 2, (what, res.output)
        assert message in res.output.replace("\n", ""), (what, res.output)
        assert str(path.name) in res.output, what  # the message names the file
        assert "Traceback" not in res.output and isinstance(res.exception, SystemExit), what
    assert not (tmp_path / "out" / "frames").exists()  # refused before any work


def test_option_mistakes_are_usage_errors(tmp_path):
    ply = save_ply(tmp_path / "a.ply", blob_model(n=20, degree=0))
    base = ["render", str(ply), "--out", str(tmp_path / "o"), "--frames", "1"]
    for extra, message in ((["--trajectory", "circle"], "neither a preset (orbit, arc,"),
                           (["--width", "33"], "--width 33 is odd"),
                           (["--background", "red"], "--background expects three comma-separated numbers"),
                           (["--trajectory", "dolly", "--degrees", "5"], "sized by amount, not degrees"),
                           (["--fov", "200"], "--fov must be in (0, 180)"),
                           (["--store", str(tmp_path)], "not both")):
        res = runner.invoke(app, [*base, *extra])
        assert res.exit_code == 2 and message in res.output, (extra, res.output)
    res = runner.invoke(app, ["render", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "give a PLY file" in res.output
    res = runner.invoke(app, ["render", str(ply)])
    assert res.exit_code == 2 and "--out" in res.output


def test_a_camera_file_renders_at_its_poses_and_size(tmp_path):
    from navcrafter.models.camera.cameras import look_at

    ply = save_ply(tmp_path / "a.ply", blob_model(degree=0))
    c2w = np.stack([look_at(np.array([x, 0.0, -1.0]), np.array([0.0, 0.0, 3.0])) for x in (-0.5, 0.5)])
    gl = c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
    doc = {"w": 40, "h": 30, "fl_x": 30.0, "frames": [{"file_path": f"{i}.png", "transform_matrix": gl[i].tolist()}
                                                        for i in range(2)]}
    cams = tmp_path / "transforms.json"
    cams.write_text(json.dumps(doc))
    out = tmp_path / "out"
    ok(runner.invoke(app, ["render", str(ply), "--out", str(out), "--trajectory", str(cams)]))
    pngs = frames_of(out)
    assert len(pngs) == 2 and np.asarray(Image.open(pngs[0])).shape == (30, 40, 3)
    got = json.loads((out / "cameras.json").read_text())["frames"]
    np.testing.assert_allclose(np.array([f["c2w"] for f in got]), c2w, atol=1e-9)  # absolute, OpenCV
    np.testing.assert_allclose(got[0]["K"], [[30, 0, 20], [0, 30, 15], [0, 0, 1]])
    assert np.asarray(Image.open(pngs[0])).mean() > 5
    ok(runner.invoke(app, ["render", str(ply), "--out", str(out), "--trajectory", str(cams), "--relative"]))
    rel = np.array([f["c2w"] for f in json.loads((out / "cameras.json").read_text())["frames"]])
    np.testing.assert_allclose(rel[0, :3, :3], np.eye(3), atol=1e-9)  # the first camera is the framed start view
    assert rel[0, 2, 3] < 3 - 1  # outside the box, in front of it
    np.testing.assert_allclose(np.linalg.inv(rel[0]) @ rel[1], np.linalg.inv(c2w[0]) @ c2w[1], atol=1e-9)
    mats = tmp_path / "c2w.npy"  # plain matrices: OpenCV axes unless --convention opengl
    np.save(mats, gl)
    ok(runner.invoke(app, ["render", str(ply), "--out", str(out), "--trajectory", str(mats), "--convention",
                           "opengl"] + SIZE))
    got = np.array([f["c2w"] for f in json.loads((out / "cameras.json").read_text())["frames"]])
    np.testing.assert_allclose(got, c2w, atol=1e-9)
    ok(runner.invoke(app, ["render", str(ply), "--out", str(out), "--trajectory", str(mats)] + SIZE))
    got = np.array([f["c2w"] for f in json.loads((out / "cameras.json").read_text())["frames"]])
    np.testing.assert_allclose(got, gl, atol=1e-9)  # read as OpenCV: the axes flipped, not converted
    res = runner.invoke(app, ["render", str(ply), "--out", str(out), "--trajectory", str(mats), "--convention", "gl"])
    assert res.exit_code == 2 and "convention 'gl' must be one of" in res.output, res.output
    doc["frames"][1]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    cams.write_text(json.dumps(doc))
    res = runner.invoke(app, ["render", str(ply), "--out", str(out), "--trajectory", str(cams)])
    assert res.exit_code == 2 and "frames[1]: transform_matrix must be a finite 4x4" in res.output, res.output


# --------------------------------------------------------------------------------------------------
# A scene of a store (written through the store API: cheaper than running explore with the fit)
# --------------------------------------------------------------------------------------------------
def test_scene_render_through_the_cli(tmp_path):
    store = tmp_path / "store"
    write_scene(store, "ab" * 32, blob_model(n=80, degree=1))
    out = tmp_path / "out"
    ok(runner.invoke(app, ["render", "--store", str(store), "--out", str(out), "--frames", "2",
                           "--trajectory", "dolly"]))
    pngs = frames_of(out)
    assert len(pngs) == 2 and np.asarray(Image.open(pngs[0])).shape == (24, 32, 3)  # the scene's resolution
    cams = json.loads((out / "cameras.json").read_text())
    np.testing.assert_allclose(cams["frames"][0]["c2w"], np.eye(4))  # starts at the input camera
    np.testing.assert_allclose(cams["frames"][1]["c2w"][2][3], 1.5)  # dolly in, halfway to the centre
    assert cams["label"] == "SIMULATION"
    res = runner.invoke(app, ["render", "--store", str(tmp_path / "nope"), "--out", str(out)])
    assert res.exit_code == 2 and "no navcrafter store" in res.output
    res = runner.invoke(app, ["render", "--store", str(store), "--out", str(out), "--fov", "50"])
    assert res.exit_code == 2 and "--fov applies to a bare PLY" in res.output

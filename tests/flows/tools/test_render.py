"""flows/tools/render.py (``navcrafter render``'s tool; the command's tests are tests/flows/test_render_cli.py): the
sources, the cameras of a render and the frames it writes, called directly."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image
from render_fixtures import blob_model, write_scene

from navcrafter.flows.tools.render import (
    Cameras,
    RenderError,
    Source,
    render_cameras,
    render_frames,
    render_size,
    scene_source,
)
from navcrafter.models.camera.cameras import Intrinsics

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_scene_source_reads_the_fit_the_input_camera_and_the_centre(tmp_path):
    model = blob_model(n=50, degree=1)
    store = tmp_path / "store"
    write_scene(store, "ab" * 32, model)
    src = scene_source(str(store), "abab")  # a prefix will do
    assert all(torch.equal(a, b) for a, b in zip(src.model.tensors().values(), model.tensors().values()))
    np.testing.assert_allclose(src.c2w, np.eye(4))
    assert (src.intrinsics.width, src.intrinsics.height, src.intrinsics.fx) == (32, 24, 20.0)
    np.testing.assert_allclose(src.target, [0, 0, 3])
    assert src.band == "SIMULATION" and src.name.startswith("scene abababababab")
    assert scene_source(str(store), None).name == src.name  # the only scene
    assert scene_source(str(store), "x.png").name == src.name  # its photo's file name
    write_scene(store, "cd" * 32, None, backend="onnx")
    with pytest.raises(ValueError, match=f"scene {'cd' * 32} has no fitted Gaussians; run explore with "
                                         "fit.enabled=true"):
        scene_source(str(store), "cd")
    with pytest.raises(ValueError, match="holds 2 scenes; choose one with --scene"):
        scene_source(str(store), None)
    with pytest.raises(ValueError, match="--scene 'ef' names no scene of"):
        scene_source(str(store), "ef")


def test_render_size_keeps_the_aspect_and_refuses_odd_sizes():
    assert render_size((32, 24), None, None) == (32, 24)
    assert render_size((32, 24), 64, None) == (64, 48)
    assert render_size((32, 24), None, 12) == (16, 12)
    with pytest.raises(ValueError, match="--width 33 is odd"):
        render_size((32, 24), 33, None)


def scene_like(model) -> Source:
    return Source(model, "blob", np.eye(4), Intrinsics.from_fov(60.0, 32, 24), np.array([0.0, 0.0, 3.0]), None)


def test_preset_cameras_start_at_the_source_camera_at_its_size():
    cams = render_cameras(scene_like(blob_model(n=20, degree=0)), "dolly", None, 3, height=12)
    assert (cams.width, cams.height) == (16, 12) and cams.c2w.shape == (3, 4, 4) and cams.K.shape == (3, 3, 3)
    np.testing.assert_allclose(cams.c2w[0], np.eye(4))
    np.testing.assert_allclose(cams.c2w[-1][:3, 3], [0, 0, 1.5])  # dolly in, halfway to the target
    np.testing.assert_allclose(cams.K[0], Intrinsics.from_fov(60.0, 16, 12).K)
    bare = Source(blob_model(n=20, degree=0), "ply", None, None, None, None)  # framed from its Gaussians
    cams = render_cameras(bare, "orbit", None, 4, fov=90.0)
    assert (cams.width, cams.height) == (512, 512) and len(cams.c2w) == 4
    np.testing.assert_allclose(cams.K[0], Intrinsics.from_fov(90.0, 512, 512).K)


def test_render_frames_writes_pngs_mp4_cameras_and_replaces_an_earlier_render(tmp_path):
    out = tmp_path / "out"
    (out / "frames").mkdir(parents=True)
    (out / "frames" / "00007.png").write_bytes(b"stale")  # a longer earlier render's frame
    (out / "frames" / "notes.txt").write_text("kept")
    src = scene_like(blob_model(n=30, degree=0))
    src.band = "SIMULATION"
    cams = render_cameras(src, "orbit", None, 2)
    seen = []
    paths = render_frames(src, cams, (0.0, 0.0, 0.0), out, 4, "cpu", "auto", "orbit", on_frame=seen.append)
    assert seen == [0, 1] and [p.name for p in paths] == ["00000.png", "00001.png"]
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["00000.png", "00001.png", "notes.txt"]
    assert np.asarray(Image.open(paths[0])).shape == (24, 32, 3)
    assert (out / "render.mp4").stat().st_size > 0
    doc = json.loads((out / "cameras.json").read_text())
    assert doc["label"] == "SIMULATION" and len(doc["frames"]) == 2
    np.testing.assert_allclose(doc["frames"][1]["c2w"], cams.c2w[1])
    (tmp_path / "file").write_text("")
    with pytest.raises(RenderError, match="cannot create"):
        render_frames(src, Cameras(cams.c2w, cams.K, 32, 24), (0.0, 0.0, 0.0), tmp_path / "file", 4, "cpu", "auto",
                      "orbit")

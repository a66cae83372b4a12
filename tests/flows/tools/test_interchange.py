"""``navcrafter export`` (flows/tools/interchange.py, flows/cli/export.py): a finished scene as a nerfstudio dataset
and a COLMAP text model (read back with pycolmap), at the fit's cameras or the estimated path; and the export
step's ``gaussians.ply`` as splat viewers read it (plyfile, the INRIA 3DGS layout)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from navcrafter.flows.cli import app

pytestmark = [pytest.mark.usefixtures("one_torch_thread"),
              pytest.mark.slow]  # every test uses `explored`: three tiny scenes explored (~1 min on 2 idle cores)
runner = CliRunner()


@pytest.fixture(scope="module")
def explored(demo_photos, tmp_path_factory):
    """A store with a tiny explored scene with the fit (5 iterations), one without it, and one only ingested."""
    from navcrafter.schemas.config import RunConfig
    from navcrafter.tasks.ingest import ingest
    from navcrafter.tasks.runner import run_scene

    store = str(tmp_path_factory.mktemp("interchange") / "store")
    fit_cfg = RunConfig.load(preset="tiny", overrides={"fit.enabled": True, "fit.iterations": 5})
    plain_cfg = RunConfig.load(preset="tiny")
    fitted = ingest(store, str(demo_photos / "tabletop-0.png"), fit_cfg, "t").scene_id
    run_scene(store, fitted, fit_cfg, "t")
    plain = ingest(store, str(demo_photos / "room-0.png"), plain_cfg, "t").scene_id
    run_scene(store, plain, plain_cfg, "t")
    unfinished = ingest(store, str(demo_photos / "street-0.png"), plain_cfg, "t").scene_id
    return {"store": store, "fitted": fitted, "plain": plain, "unfinished": unfinished, "fit_cfg": fit_cfg,
            "plain_cfg": plain_cfg}


def _scene(explored, which):
    from navcrafter.schemas.store import Store

    return Store(explored["store"]).scene(explored[which])


def _check_images(scene, out: Path, refs, width, height):
    from navcrafter.schemas.layout import SYNTHESIZE

    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == [f"frame_{f:05d}.png" for f in range(len(refs))]
    for f, (k, i) in enumerate(refs):
        with Image.open(out / "images" / names[f]) as im:
            assert im.size == (width, height)
            assert np.array_equal(np.asarray(im.convert("RGB")), scene.read(SYNTHESIZE, k, "frames")[i])


def test_nerfstudio_export_at_the_fit_cameras(explored, tmp_path):
    import open3d as o3d

    from navcrafter.flows.tools.interchange import export_nerfstudio
    from navcrafter.models.simulation import LABEL
    from navcrafter.schemas.layout import FIT
    from navcrafter.tasks.common import load_cloud
    from navcrafter.tasks.readers import camera_path

    scene, cfg = _scene(explored, "fitted"), explored["fit_cfg"]
    out = tmp_path / "ns"
    doc = export_nerfstudio(explored["store"], explored["fitted"][:10], out)
    fit = scene.read_all(FIT)
    path = camera_path(scene, cfg, cameras="estimated")
    distinct = path.distinct()
    # the fit's frames: every frame but the first of clip 2 (a repeat of clip 1's last)
    refs = [tuple(r) for r in fit["frame_ref"].tolist()]
    assert refs == distinct.refs and len(refs) == len(path) - (cfg.iterations - 1)
    assert (2, 0) not in refs and (1, 0) in refs
    W, H = cfg.synthesis.width, cfg.synthesis.height
    _check_images(scene, out, refs, W, H)

    tf = json.loads((out / "transforms.json").read_text())
    assert tf["camera_model"] == "OPENCV" and (tf["w"], tf["h"]) == (W, H)
    assert all(tf[k] == 0.0 for k in ("k1", "k2", "p1", "p2"))
    # the fit's K (at its resolution) scaled to the frames: the path's full-resolution intrinsics
    K = distinct.K[0]
    assert np.allclose([tf["fl_x"], tf["fl_y"], tf["cx"], tf["cy"]], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
                       rtol=0, atol=1e-9)
    assert [f["file_path"] for f in tf["frames"]] == [f"images/frame_{f:05d}.png" for f in range(len(refs))]
    gl = np.array([f["transform_matrix"] for f in tf["frames"]])
    c2w = fit["c2w"]
    assert np.allclose(gl[:, :3, 3], c2w[:, :3, 3], atol=1e-12)  # same camera centres
    assert np.allclose(gl[:, :3, 0], c2w[:, :3, 0], atol=1e-12)  # x right in both
    assert np.allclose(gl[:, :3, 1:3], -c2w[:, :3, 1:3], atol=1e-12)  # OpenGL: y up, z back
    # initial points: the fused cloud, as nerfstudio reads them (Open3D)
    assert tf["ply_file_path"] == "sparse_pc.ply"
    pcd = o3d.io.read_point_cloud(str(out / tf["ply_file_path"]))
    cloud = load_cloud(scene, cfg.iterations)
    assert np.allclose(np.asarray(pcd.points), cloud.points, atol=1e-6)
    assert np.array_equal(np.round(np.asarray(pcd.colors) * 255).astype(np.uint8), cloud.colors)
    assert b"SIMULATION" in (out / "sparse_pc.ply").read_bytes()[:2000]

    meta = json.loads((out / "navcrafter_export.json").read_text())
    assert meta == doc and meta["format"] == "nerfstudio" and meta["scene_id"] == explored["fitted"]
    assert meta["backend"] == "simulation" and meta["label"] == LABEL and meta["cameras"] == "fit"
    assert "OpenCV" in meta["world"] and meta["world_units_per_metre"] > 0 and "per metre" in meta["units"]
    assert [(f["iteration"], f["frame"]) for f in meta["frames"]] == refs
    assert [f["holdout"] for f in meta["frames"]] == fit["holdout"].tolist()
    with Image.open(out / "images" / "frame_00000.png") as im:  # labelled in the PNG, not in the pixels
        assert im.text.get("navcrafter") == LABEL


def test_colmap_export_reads_back_with_pycolmap(explored, tmp_path):
    import pycolmap

    from navcrafter.schemas.layout import FIT
    from navcrafter.tasks.common import load_cloud

    scene, cfg = _scene(explored, "fitted"), explored["fit_cfg"]
    out = tmp_path / "colmap"
    res = runner.invoke(app, ["export", explored["store"], explored["fitted"], "--format", "colmap",
                              "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "fit cameras" in res.output and "SIMULATION" in res.output
    fit = scene.read_all(FIT)
    c2w = fit["c2w"]
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert len(rec.images) == len(c2w) and len(rec.cameras) == 1
    cam = rec.cameras[1]
    W, H = cfg.synthesis.width, cfg.synthesis.height
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (W, H)
    w, h = scene.status(FIT).attrs["resolution"]
    K = fit["K"][0]
    assert np.allclose(cam.params, [K[0, 0] * W / w, K[1, 1] * H / h, K[0, 2] * W / w, K[1, 2] * H / h],
                       rtol=0, atol=1e-9)
    for image_id, img in rec.images.items():
        f = image_id - 1
        assert img.name == f"frame_{f:05d}.png" and img.camera_id == 1
        world_from_cam = img.cam_from_world().inverse()
        assert np.allclose(img.projection_center(), c2w[f, :3, 3], rtol=0, atol=1e-9)
        assert np.allclose(world_from_cam.rotation.matrix(), c2w[f, :3, :3], rtol=0, atol=1e-9)
        assert len(img.points2D) == 0
    cloud = load_cloud(scene, cfg.iterations)
    assert len(rec.points3D) == len(cloud)
    xyz = np.array([rec.points3D[j + 1].xyz for j in range(len(cloud))])
    rgb = np.array([rec.points3D[j + 1].color for j in range(len(cloud))])
    assert np.array_equal(xyz, cloud.points.astype(np.float64)) and np.array_equal(rgb, cloud.colors)
    assert all(rec.points3D[j + 1].track.length() == 0 and rec.points3D[j + 1].error == 0 for j in (0, len(cloud) - 1))
    _check_images(scene, out, [tuple(r) for r in fit["frame_ref"].tolist()], W, H)
    meta = json.loads((out / "navcrafter_export.json").read_text())
    assert meta["format"] == "colmap" and meta["cameras"] == "fit" and meta["n_points"] == len(cloud)


def test_export_without_the_fit_uses_the_estimated_path(explored, tmp_path):
    import pycolmap

    from navcrafter.flows.tools.interchange import export_colmap, export_nerfstudio
    from navcrafter.schemas.layout import FIT
    from navcrafter.tasks.readers import camera_path

    scene, cfg = _scene(explored, "plain"), explored["plain_cfg"]
    assert not scene.status(FIT).exists
    path = camera_path(scene, cfg, cameras="estimated").distinct()
    doc = export_colmap(explored["store"], explored["plain"], tmp_path / "c")
    assert doc["cameras"] == "estimated" and "holdout" not in doc["frames"][0]
    assert [(f["iteration"], f["frame"]) for f in doc["frames"]] == path.refs
    rec = pycolmap.Reconstruction(str(tmp_path / "c" / "sparse" / "0"))
    for image_id, img in rec.images.items():
        assert np.allclose(img.projection_center(), path.c2w[image_id - 1, :3, 3], rtol=0, atol=1e-9)
        assert np.allclose(img.cam_from_world().inverse().rotation.matrix(), path.c2w[image_id - 1, :3, :3],
                           rtol=0, atol=1e-9)
    # the config given from Python (iterations, size) reads the same frames as the one derived from the store
    ns = export_nerfstudio(explored["store"], explored["plain"], tmp_path / "n", config=cfg)
    assert ns["frames"] == doc["frames"] and ns["cameras"] == "estimated"
    tf = json.loads((tmp_path / "n" / "transforms.json").read_text())
    assert np.allclose(np.array([f["transform_matrix"] for f in tf["frames"]]),
                       path.c2w @ np.diag([1.0, -1.0, -1.0, 1.0]), atol=1e-12)


def test_export_errors_say_what_to_do(explored, tmp_path):
    store = explored["store"]
    res = runner.invoke(app, ["export", store, "ffff0000", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "ffff0000" in res.output and f"navcrafter status {store}" in res.output
    sid = explored["unfinished"]
    res = runner.invoke(app, ["export", store, sid, "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and sid[:12] in res.output and "finished exploring" in res.output
    assert "navcrafter explore" in res.output
    res = runner.invoke(app, ["export", store, explored["plain"], "--format", "blender", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "nerfstudio, colmap" in res.output
    res = runner.invoke(app, ["export", str(tmp_path / "nostore"), "abc", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "no navcrafter store" in res.output
    assert not (tmp_path / "x").exists()


def test_gaussians_ply_reads_as_the_inria_layout_with_plyfile(explored):
    plyfile = pytest.importorskip("plyfile")
    import torch

    from navcrafter.models.simulation import LABEL
    from navcrafter.schemas.layout import EXPORT, FIT
    from navcrafter.tasks.readers import load_gaussians

    scene = _scene(explored, "fitted")
    path = scene.store.path(scene.status(EXPORT).attrs["files"]["gaussians.ply"]["path"])
    ply = plyfile.PlyData.read(path)
    model = load_gaussians(scene)
    G, degree = len(model), model.sh_degree
    assert G == scene.status(FIT).attrs["n_gaussians"] and degree == 1
    assert [e.name for e in ply.elements] == ["vertex"] and ply.elements[0].count == G
    assert not ply.text and ply.byte_order == "<" and LABEL in ply.comments
    n_rest = 3 * ((degree + 1) ** 2 - 1)
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(n_rest)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    v = ply["vertex"]
    assert [p.name for p in v.properties] == names
    assert all(p.val_dtype == "f4" for p in v.properties) and v.data.dtype == np.dtype([(n, "<f4") for n in names])

    def cols(*keys):
        return np.stack([v[k] for k in keys], axis=1)

    m = {k: t.numpy() for k, t in model.tensors().items()}
    assert np.array_equal(cols("x", "y", "z"), m["means"]) and not cols("nx", "ny", "nz").any()
    assert np.array_equal(cols("f_dc_0", "f_dc_1", "f_dc_2"), m["sh_dc"])
    # f_rest: INRIA's channel-major order (all of red's higher coefficients, then green's, then blue's)
    rest = cols(*names[9:9 + n_rest]).reshape(G, 3, -1)
    assert np.array_equal(rest, np.transpose(m["sh_rest"], (0, 2, 1)))
    # opacity as a logit, scales as logs, the rotation as the model holds it: (w, x, y, z), not normalised
    assert np.array_equal(v["opacity"], m["opacity_logits"])
    alpha = 1 / (1 + np.exp(-v["opacity"].astype(np.float64)))
    assert np.allclose(alpha, torch.sigmoid(model.opacity_logits.double()).numpy())
    assert np.array_equal(cols("scale_0", "scale_1", "scale_2"), m["log_scales"])
    assert np.allclose(np.exp(cols("scale_0", "scale_1", "scale_2").astype(np.float64)),
                       model.log_scales.double().exp().numpy())
    q = cols("rot_0", "rot_1", "rot_2", "rot_3")
    assert np.array_equal(q, m["quats"]) and (np.linalg.norm(q, axis=1) > 0).all()


def test_scene_run_config_is_the_stored_one(explored, caplog):
    """A run stores its resolved config with the scene; the tools read it back (not defaults); a rerun with another
    config keeps the earlier one's hash in the history; a scene without the file falls back with a warning."""
    from navcrafter.flows.tools.interchange import scene_config
    from navcrafter.schemas.config import RUN_CONFIG_FILE, RunConfig
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.readers import scene_run_config, stored_run_config
    from navcrafter.tasks.runner import record_run_config

    store = Store(explored["store"], create=False)
    fitted = store.scene(explored["fitted"])
    assert scene_run_config(fitted) == explored["fit_cfg"] and scene_config(fitted) == explored["fit_cfg"]
    assert scene_run_config(fitted) != RunConfig()  # not rebuilt from defaults (tiny preset, fit on)
    other = RunConfig.load(preset="tiny", overrides={"seed": 7})
    record_run_config(explored["store"], explored["plain"], other, "t2")
    doc = stored_run_config(store.scene(explored["plain"]))
    assert doc.config == other and doc.run_id == "t2"
    assert [h["config_hash"] for h in doc.history] == [explored["plain_cfg"].config_hash()]
    record_run_config(explored["store"], explored["plain"], explored["plain_cfg"], "t3")  # as the other tests expect
    unfinished = store.scene(explored["unfinished"])  # only ingested: as a scene of a store written before
    assert stored_run_config(unfinished) is None
    assert Path(store.path(f"scenes/{explored['fitted']}/{RUN_CONFIG_FILE}")).is_file()
    with caplog.at_level("WARNING"):
        legacy = scene_run_config(unfinished)
    assert legacy.iterations == RunConfig().iterations and "written before runs stored their config" in caplog.text

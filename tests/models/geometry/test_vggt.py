"""VGGT geometry network: ONNX export vs torch, manifest, official checkpoint layout, processing, backend.

One tiny export is shared by the module (exports take most of this file's time).
"""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch

from navcrafter.models.geometry import processing as proc
from navcrafter.models.geometry.vggt import (
    OUTPUT_NAMES,
    VGGT,
    VGGTConfig,
    VGGTWeightsError,
    load_vggt_weights,
    official_layout,
    read_key_list,
    save_official_safetensors,
    vggt_state_dict_from_official,
    vggt_state_dict_official,
)
from navcrafter.models.runtime import onnxio

TINY = VGGTConfig.tiny()
TINY2 = dataclasses.replace(TINY, depth=2, dpt_layers=(0, 0, 1, 1))  # eager tests: two aggregator rounds
SEED = 0  # the seed of the session's shared tiny export (conftest.tiny_models)


def _random_model(config: VGGTConfig, seed: int) -> VGGT:
    torch.manual_seed(seed)
    return VGGT(config).eval()


@pytest.fixture(scope="module")
def exported(tiny_models):
    return tiny_models / "geometry"  # export_geometry(out, VGGTConfig.tiny(), seed=0), shared by the session


@pytest.fixture(scope="module")
def runner(exported):
    manifest = onnxio.load_manifest(exported, "geometry")
    return onnxio.GraphRunner(exported, manifest, ["CPUExecutionProvider"])


# --------------------------------------------------------------------------------------------------
# ONNX export
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("S,H,W", [(2, 56, 42), (3, 28, 70)])
def test_onnx_matches_torch(runner, S, H, W):
    model = _random_model(TINY, SEED)  # export_geometry builds its random model the same way
    images = torch.rand(1, S, 3, H, W, generator=torch.Generator().manual_seed(S))
    with torch.no_grad():
        ref = model(images)
    got = runner.run("geometry", {"images": images.numpy()})
    assert list(got) == list(OUTPUT_NAMES)
    shapes = {"pose_enc": (1, S, 9), "depth": (1, S, H, W, 1), "depth_conf": (1, S, H, W),
              "world_points": (1, S, H, W, 3), "world_points_conf": (1, S, H, W)}
    for name in OUTPUT_NAMES:
        assert got[name].shape == shapes[name] == tuple(ref[name].shape), name
        assert np.abs(got[name] - ref[name].numpy()).max() <= 1e-4, name
    assert (got["depth"] > 0).all() and (got["depth_conf"] >= 1).all()


def test_manifest(exported):
    manifest = onnxio.load_manifest(exported, "geometry")
    assert manifest["architecture"] == "vggt"
    assert manifest["weights"] == {"source": "random", "seed": SEED}
    assert VGGTConfig.from_dict(manifest["config"]) == TINY
    assert manifest["config"]["img_size"] == 56 and manifest["config"]["patch_size"] == 14
    graph = manifest["graphs"]["geometry"]
    assert graph["inputs"] == ["images"] and graph["outputs"] == list(OUTPUT_NAMES)
    dims = graph["dynamic"]["images"]
    assert dims[0] == "" and dims[2] == "" and all(dims[i] for i in (1, 3, 4))  # S, H, W dynamic


def test_corrupted_export_is_rejected(exported, tmp_path):
    from navcrafter.models.geometry.onnx_geometry import OnnxGeometry

    copy = tmp_path / "geometry"
    shutil.copytree(exported, copy)
    data = copy / "geometry.onnx.data"
    raw = bytearray(data.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    data.write_bytes(bytes(raw))
    with pytest.raises(onnxio.ModelDirError, match="checksum of geometry.onnx.data"):
        onnxio.load_manifest(copy, "geometry")
    with pytest.raises(onnxio.ModelDirError, match="checksum"):
        OnnxGeometry(copy)
    (copy / "manifest.json").unlink()
    with pytest.raises(onnxio.ModelDirError, match="no manifest.json"):
        OnnxGeometry(copy)


# --------------------------------------------------------------------------------------------------
# Geometry backend
# --------------------------------------------------------------------------------------------------
def test_onnx_geometry_predict(exported):
    from navcrafter.models.geometry.onnx_geometry import OnnxGeometry
    from navcrafter.models.roles import Geometry

    geo = OnnxGeometry(exported, providers=["CPUExecutionProvider"])
    assert isinstance(geo, Geometry) and geo.backend == "onnx" and geo.random_weights
    frames = np.random.default_rng(0).integers(0, 256, size=(3, 40, 50, 3), dtype=np.uint8)
    pred = geo.predict(frames, seed=0)
    assert pred.c2w.shape == (3, 4, 4) and pred.c2w.dtype == np.float64
    assert np.array_equal(pred.c2w[0], np.eye(4))
    R = pred.c2w[:, :3, :3]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-9)
    assert np.allclose(pred.c2w[:, 3], [0, 0, 0, 1])
    assert pred.K.shape == (3, 3, 3) and pred.K.dtype == np.float64
    assert np.allclose(pred.K[:, :2, 2], [25.0, 20.0])  # centred principal point in input pixels
    assert (pred.K[:, 0, 0] > 0).all() and (pred.K[:, 1, 1] > 0).all()
    assert pred.depth.shape == (3, 40, 50) and pred.depth.dtype == np.float32
    assert pred.confidence.shape == (3, 40, 50) and pred.confidence.dtype == np.float32
    assert np.isfinite(pred.depth).all() and (pred.depth >= 0).all()
    assert (pred.confidence >= 0).all() and (pred.confidence <= 1).all()
    assert (pred.confidence[pred.depth == 0] == 0).all()
    assert all(isinstance(v, float) for v in pred.extras.values())
    assert pred.extras["model_width"] == 56 and pred.extras["model_height"] == 42
    # hints are ignored, the result is deterministic
    again = geo.predict(frames, seed=5, hint_c2w=np.tile(np.eye(4), (3, 1, 1)))
    assert np.array_equal(again.depth, pred.depth) and np.array_equal(again.c2w, pred.c2w)
    # one frame (the initial-geometry step) and a portrait frame (crop mode: rows outside get no depth)
    single = geo.predict(frames[:1], seed=0)
    assert single.c2w.shape == (1, 4, 4) and np.array_equal(single.c2w[0], np.eye(4))
    assert single.depth.shape == (1, 40, 50)
    tall = geo.predict(np.ascontiguousarray(frames[:2].transpose(0, 2, 1, 3)), seed=0)  # 50 x 40 -> 56 x 70 -> crop
    assert tall.depth.shape == (2, 50, 40) and (tall.depth[:, :3] == 0).all() and (tall.depth[:, 10:40] > 0).all()


# --------------------------------------------------------------------------------------------------
# Checkpoint layout and loading
# --------------------------------------------------------------------------------------------------
def test_full_size_layout_matches_official_key_list():
    with torch.device("meta"):
        model = VGGT(VGGTConfig.vggt_1b())
    used, ignored = read_key_list()
    assert list(official_layout(model).items()) == list(used.items())  # names, shapes and order
    assert len(used) == 1403 and len(ignored) == 394
    assert all(k.startswith("track_head.") for k in ignored)
    assert sum(int(np.prod(s)) for s in used.values()) == 1_190_596_120


def test_official_layout_round_trip():
    model = _random_model(TINY2, 1)
    official = vggt_state_dict_official(model)
    ours = vggt_state_dict_from_official(official)
    assert ours.keys() == model.state_dict().keys()
    back = vggt_state_dict_official(ours)
    assert list(back) == list(official)
    assert all(torch.equal(back[k], official[k]) for k in official)
    # the fused DINOv2 qkv is [q; k; v] along the output features
    qkv = official["aggregator.patch_embed.blocks.0.attn.qkv.weight"]
    q = model.state_dict()["aggregator.patch_embed.layer.0.attention.q_proj.weight"]
    assert torch.equal(qkv[: q.shape[0]], q)


def test_load_weights_safetensors_and_pt(tmp_path):
    from safetensors.torch import save_file

    src = _random_model(TINY2, 1)
    images = torch.rand(1, 2, 3, 28, 42, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref = src(images)
    sd = {k: v.contiguous() for k, v in vggt_state_dict_official(src).items()}
    sd["track_head.fnet.conv.weight"] = torch.zeros(2, 2)  # present in the official file, not built here
    st = tmp_path / "vggt.safetensors"
    save_file(sd, str(st))
    pt = tmp_path / "vggt.pt"
    torch.save(sd, pt)
    for path in (st, pt):
        dst = _random_model(TINY2, 2)
        report = load_vggt_weights(dst, path)
        assert report["ignored"] == ["track_head.fnet.conv.weight"]
        assert report["loaded"] == len(sd) - 1 and len(report["sha256"]) == 64
        with torch.no_grad():
            out = dst(images)
        assert all(torch.equal(out[k], ref[k]) for k in OUTPUT_NAMES)
    assert save_official_safetensors(src, tmp_path / "b.safetensors").is_file()


def test_load_weights_errors(tmp_path):
    from safetensors.torch import save_file

    sd = {k: v.contiguous() for k, v in vggt_state_dict_official(_random_model(TINY2, 1)).items()}
    bad = dict(sd)
    bad["camera_head.embed_pose.weight"] = torch.zeros(3, 9)
    path = tmp_path / "wrong.safetensors"
    save_file(bad, str(path))
    with pytest.raises(VGGTWeightsError, match=r"wrong\.safetensors.*shape mismatch \[camera_head\.embed_pose\.weight"):
        load_vggt_weights(_random_model(TINY2, 2), path)
    bad = dict(sd)
    del bad["depth_head.norm.bias"]
    bad["extra_head.weight"] = torch.zeros(1)
    path = tmp_path / "keys.safetensors"
    save_file(bad, str(path))
    with pytest.raises(VGGTWeightsError) as err:
        load_vggt_weights(_random_model(TINY2, 2), path)
    assert "missing keys [depth_head.norm.bias]" in str(err.value)
    assert "unexpected keys [extra_head.weight]" in str(err.value)
    # a tiny checkpoint into the full-size layout: many mismatches, listed briefly
    with torch.device("meta"):
        big = VGGT(VGGTConfig.vggt_1b())
    with pytest.raises(VGGTWeightsError, match=r"\.\.\. \(\+\d+ more\)"):
        load_vggt_weights(big, tmp_path / "keys.safetensors")
    pickled = tmp_path / "pickled.pt"
    torch.save({"model": object()}, pickled)
    with pytest.raises(VGGTWeightsError, match="weights_only"):
        load_vggt_weights(_random_model(TINY2, 2), pickled)


# --------------------------------------------------------------------------------------------------
# Building blocks against their definitions
# --------------------------------------------------------------------------------------------------
def test_position_table_resampling_is_identity_at_training_size():
    model = _random_model(TINY, 0)
    emb = model.aggregator.patch_embed.embeddings
    table = emb.position_embeddings
    got = emb.interpolate_pos_encoding(torch.zeros(1, table.shape[1], table.shape[2]), 56, 56)
    assert torch.equal(got, table)


def test_tiny_config_validation():
    with pytest.raises(ValueError, match="dpt_layers"):
        dataclasses.replace(TINY2, dpt_layers=(0, 0, 1, 2))
    cfg = VGGTConfig.from_dict({**dataclasses.asdict(TINY2), "dpt_layers": [0, 0, 1, 1], "unknown": 1})
    assert cfg == TINY2


# --------------------------------------------------------------------------------------------------
# Processing
# --------------------------------------------------------------------------------------------------
def _random_cameras(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = proc.quat_xyzw_to_matrix(q)
    t = rng.normal(size=(n, 3))
    extr = np.concatenate([R, t[:, :, None]], axis=-1)
    K = np.zeros((n, 3, 3))
    K[:, 0, 0] = rng.uniform(200, 600, n)
    K[:, 1, 1] = rng.uniform(200, 600, n)
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = 259.0, 196.0, 1.0
    return extr, K, q


def test_pose_encoding_round_trip():
    rng = np.random.default_rng(0)
    extr, K, q = _random_cameras(rng, 64)
    # include rotations near 180 degrees (the w ~ 0 branch of the matrix -> quaternion conversion)
    extr[0, :, :3] = np.diag([1.0, -1.0, -1.0])
    extr[1, :, :3] = np.diag([-1.0, -1.0, 1.0])
    enc = proc.extri_intri_to_pose_encoding(extr, K, (392, 518))
    assert enc.shape == (64, 9) and (enc[:, 6] >= 0).all()
    assert np.allclose(np.linalg.norm(enc[:, 3:7], axis=1), 1.0)
    extr2, K2 = proc.pose_encoding_to_extri_intri(enc, (392, 518))
    assert np.allclose(extr2, extr, atol=1e-12) and np.allclose(K2, K, atol=1e-9)
    enc2 = proc.extri_intri_to_pose_encoding(extr2, K2, (392, 518))
    assert np.allclose(enc2, enc, atol=1e-12)
    # quaternions are (x, y, z, w) with w >= 0: q and -q encode the same rotation
    qs = np.where(q[:, 3:4] < 0, -q, q)[2:]
    assert np.allclose(enc[2:, 3:7], qs, atol=1e-12)
    # non-unit quaternions (as the network outputs) still give rotations
    R = proc.quat_xyzw_to_matrix(3.0 * q)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)


def test_c2w_conversions():
    rng = np.random.default_rng(1)
    extr, _, _ = _random_cameras(rng, 5)
    c2w = proc.extrinsics_to_c2w(extr)
    assert np.allclose(proc.c2w_to_extrinsics(c2w), extr)
    X = rng.normal(size=3)
    # a world point's camera coordinates: extr @ [X, 1] == R^T (X - t) of the c2w pose
    cam = extr[:, :, :3] @ X + extr[:, :, 3]
    cam2 = np.einsum("nji,nj->ni", c2w[:, :3, :3], X - c2w[:, :3, 3])
    assert np.allclose(cam, cam2)
    rel = proc.relative_to_first(c2w)
    assert np.array_equal(rel[0], np.eye(4))
    assert np.allclose(c2w[0] @ rel, c2w)


def test_input_transform_official_rules():
    tr = proc.vggt_input_transform(640, 480)  # landscape, crop mode: width 518, height 389 -> 392
    assert (tr.width, tr.height) == (518, 392) and tr.offset_y == 0
    tr = proc.vggt_input_transform(480, 640)  # portrait: resized to 518 x 686 (round(690.7 / 14) * 14)
    assert (tr.resized_width, tr.resized_height) == (518, 686)
    assert (tr.width, tr.height) == (518, 518) and tr.offset_y == -84  # central rows kept
    tr = proc.vggt_input_transform(480, 640, mode="pad")
    assert (tr.resized_width, tr.resized_height) == (392, 518)
    assert (tr.width, tr.height, tr.offset_x, tr.offset_y) == (518, 518, 63, 0)
    # intrinsics: a point projects to corresponding pixels in the source and the model image
    K_model = np.array([[400.0, 0, 259], [0, 410, 259], [0, 0, 1]])
    K_src = tr.intrinsics_to_source(K_model)
    p = np.array([0.3, -0.2, 2.0])
    uv_m = (K_model @ p)[:2] / p[2]
    uv_s = (K_src @ p)[:2] / p[2]
    assert np.allclose(uv_m, [tr.scale_x * uv_s[0] + tr.offset_x, tr.scale_y * uv_s[1] + tr.offset_y])


def test_preprocess_frames():
    frames = np.zeros((2, 30, 40, 3), dtype=np.uint8)
    frames[:, :, :, 0] = 255
    images, tr = proc.preprocess_frames(frames, img_size=56, patch_size=14)
    assert images.shape == (2, 3, 42, 56) and images.dtype == np.float32
    assert np.allclose(images[:, 0], 1.0) and np.allclose(images[:, 1:], 0.0)
    images, tr = proc.preprocess_frames(frames, img_size=56, patch_size=14, mode="pad")
    assert images.shape == (2, 3, 56, 56) and tr.offset_x == 0 and tr.offset_y == 7
    assert np.allclose(images[:, :, :7], 1.0) and np.allclose(images[:, 1:, 7:49], 0.0)
    images, tr = proc.preprocess_frames(frames[:, :, :10], img_size=56, patch_size=14, mode="pad")
    assert tr.resized_width == 14 and tr.offset_x == 21
    assert np.allclose(images[:, :, :, :21], 1.0)  # white padding
    with pytest.raises(ValueError, match="uint8"):
        proc.preprocess_frames(frames.astype(np.float32))


def test_confidence_and_invalid_depth():
    conf = np.array([1.0, 2.0, 4.0, 0.5, np.inf, np.nan])
    assert np.allclose(proc.confidence_to_unit(conf), [0.0, 0.5, 0.75, 0.0, 0.0, 0.0])
    depth = np.array([[1.0, -1.0], [np.nan, 0.0]])
    d, c = proc.clean_depth(depth, np.full((2, 2), 0.9))
    assert d.tolist() == [[1.0, 0.0], [0.0, 0.0]] and c.tolist() == [[pytest.approx(0.9), 0.0], [0.0, 0.0]]


def test_resample_to_source():
    tr = proc.vggt_input_transform(28, 28, img_size=14, patch_size=14)  # model grid half the size
    depth = np.arange(1, 1 + 14 * 14, dtype=np.float32).reshape(1, 14, 14)
    depth[0, 0, 0] = 0.0  # one invalid model pixel
    conf = np.full_like(depth, 0.5)
    conf[depth == 0] = 0
    d, c = proc.resample_to_source(depth, conf, tr)
    assert d.shape == (1, 28, 28)
    assert d[0, 27, 27] == depth[0, 13, 13] and c[0, 27, 27] == pytest.approx(0.5)
    assert np.isclose(d[0, 11, 10], 1 + 14 * 5.25 + 4.75)  # bilinear is exact on a linear ramp
    assert d[0, 0, 0] == 0 and c[0, 0, 0] == 0  # only the invalid model pixel contributes
    assert np.isclose(d[0, 1, 1], (3 * 2 + 3 * 15 + 1 * 16) / 7)  # the invalid neighbour is left out
    # crop mode: rows cut away from a portrait frame have no depth
    tr = proc.vggt_input_transform(14, 28, img_size=14, patch_size=14)
    d, c = proc.resample_to_source(np.ones((1, 14, 14), np.float32), np.ones((1, 14, 14), np.float32), tr)
    assert (d[0, :7] == 0).all() and (d[0, 7:21] == 1).all() and (d[0, 21:] == 0).all()

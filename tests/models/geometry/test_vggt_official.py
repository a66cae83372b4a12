"""VGGT against the official implementation (facebookresearch/vggt at 44b3afb): aggregator tokens, camera head
(pose encoding of every refinement iteration), depth and point heads with their confidences, the pose-encoding
conversions and the image preprocessing (crop and pad modes).

The fixture (``fixtures/official/vggt/``, see its README) holds a tiny official ``VGGT`` state dict (loaded here
through our converter ``load_vggt_weights``), the inputs, and the official outputs.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import official_close

from navcrafter.models.geometry.processing import (
    extri_intri_to_pose_encoding,
    pose_encoding_to_extri_intri,
    preprocess_frames,
)
from navcrafter.models.geometry.vggt import VGGT, VGGTConfig, load_vggt_weights

FIXTURE = Path(__file__).with_name("fixtures") / "official" / "vggt"
TOL = 1e-4

pytestmark = [pytest.mark.official_parity, pytest.mark.usefixtures("one_torch_thread")]


@pytest.fixture(scope="module")
def official():
    from safetensors.numpy import load_file

    meta = json.loads((FIXTURE / "meta.json").read_text())
    c = meta["config"]
    config = VGGTConfig(img_size=c["img_size"], patch_size=c["patch_size"], embed_dim=c["embed_dim"], depth=c["depth"],
                        num_heads=c["num_heads"], num_register_tokens=c["num_register_tokens"],
                        encoder_depth=c["encoder_depth"], encoder_heads=c["encoder_heads"],
                        camera_trunk_depth=c["camera_trunk_depth"], camera_heads=c["camera_heads"],
                        camera_iterations=c["camera_iterations"], dpt_features=c["dpt_features"],
                        dpt_out_channels=tuple(c["dpt_out_channels"]), dpt_layers=tuple(c["dpt_layers"]))
    torch.manual_seed(123)  # any init: every weight comes from the official state dict
    model = VGGT(config).eval()
    report = load_vggt_weights(model, FIXTURE / "state.safetensors")
    assert report["ignored"] == []
    return meta, model, {k: torch.from_numpy(v) for k, v in load_file(str(FIXTURE / "cases.safetensors")).items()}


def test_fixture_names_its_source(official):
    meta, _, _ = official
    assert meta["official_repo"] == "facebookresearch/vggt" and meta["commit"] == "44b3afb"


def test_aggregator_tokens_match(official):
    meta, model, cases = official
    with torch.no_grad():
        tokens = model.aggregator(cases["images"], tuple(range(model.config.depth)))
    assert model.aggregator.patch_start_idx == meta["patch_start_idx"]
    for i in range(model.config.depth):
        assert official_close(tokens[i], cases[f"aggregator.{i}"]) <= TOL, i


def test_heads_match(official):
    _, model, cases = official
    with torch.no_grad():
        pred = model(cases["images"])
    for name in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        assert official_close(pred[name], cases[f"pred.{name}"]) <= TOL, name
    # the confidences are 1 + exp(x): compared on log(c - 1) too, where small values are not hidden by 1
    for name in ("depth_conf", "world_points_conf"):
        assert official_close(torch.log(pred[name] - 1), torch.log(cases[f"pred.{name}"] - 1)) <= TOL, name


def test_pose_encoding_conversions_match(official):
    _, _, cases = official
    hw = (392, 518)
    enc = extri_intri_to_pose_encoding(cases["pose.extrinsics"].numpy(), cases["pose.intrinsics"].numpy(), hw)
    assert official_close(enc, cases["pose.encoding"]) <= 1e-6
    ext, K = pose_encoding_to_extri_intri(cases["pose.encoding"].numpy(), hw)
    assert official_close(ext, cases["pose.extrinsics_back"]) <= 1e-6
    assert official_close(K, cases["pose.intrinsics_back"]) <= 1e-6


@pytest.mark.parametrize("name", ["crop_wide", "crop_tall", "pad_tall"])
def test_preprocessing_matches_load_and_preprocess_images(official, name):
    meta, _, _ = official
    pre = np.load(FIXTURE / "preprocess.npz")
    x, _ = preprocess_frames(pre[f"{name}.image"][None], mode=name.split("_")[0])
    u8 = np.round(x[0] * 255).astype(np.uint8)
    assert np.array_equal(u8.astype(np.float32) / 255, x[0])  # the official values are exactly k / 255
    if name == "crop_tall":
        digest = meta["preprocess_digests"][name]
        assert list(u8.shape) == digest["shape"]
        assert np.array_equal(np.concatenate([u8[:, :4], u8[:, -4:]], axis=1), pre[f"{name}.out_u8_rows"])
        assert hashlib.sha256(u8.tobytes()).hexdigest() == digest["sha256"]
    else:
        assert np.array_equal(u8, pre[f"{name}.out_u8"])

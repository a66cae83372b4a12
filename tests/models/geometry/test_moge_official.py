"""MoGe-2 against the official implementation (microsoft/MoGe at 0744441), end to end at the input resolution.

The fixture (``fixtures/official/moge2/``, see its README) holds a tiny official ``MoGeModel`` state dict, two
uint8 images and what the official ``forward(image, num_tokens)`` and ``infer(image, num_tokens, use_fp16=False)``
returned for them. Here the state dict goes through our converter (``load_moge2_weights``) and our pipeline
(``preprocess_image`` -> ``MoGe2`` -> ``head_maps_to_size`` -> ``postprocess``, i.e. ``infer_torch``) runs on the
same images: the resize to the token grid, the network, the one resize of the head maps and the focal / shift
recovery all have to agree to 1e-4 (relative to the map's magnitude where it exceeds 1).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import official_close

from navcrafter.models.geometry.moge import (
    MoGe2,
    MoGe2Config,
    head_maps_to_size,
    infer_torch,
    load_moge2_weights,
    preprocess_image,
)

FIXTURE = Path(__file__).with_name("fixtures") / "official" / "moge2"
TOL = 1e-4

pytestmark = [pytest.mark.official_parity, pytest.mark.usefixtures("one_torch_thread")]


@pytest.fixture(scope="module")
def official():
    from safetensors.numpy import load_file

    meta = json.loads((FIXTURE / "meta.json").read_text())
    torch.manual_seed(123)  # any init: every weight comes from the official state dict
    model = load_moge2_weights(MoGe2(MoGe2Config.from_official(meta["model_config"])), FIXTURE / "state.safetensors")
    return meta, model.eval(), load_file(str(FIXTURE / "cases.safetensors"))


def test_fixture_names_its_source(official):
    meta, model, _ = official
    assert meta["official_repo"] == "microsoft/MoGe" and meta["commit"] == "0744441"
    assert model.config.remap_output == "exp" and model.config.normal_head


@pytest.mark.parametrize("case", [0, 1])
def test_network_and_head_resize_match_official_forward(official, case):
    meta, model, cases = official
    spec = meta["cases"][case]
    image = cases[f"case{case}.image"]
    x = preprocess_image(image, spec["num_tokens"], model.config.patch_size)
    with torch.no_grad():
        out = model(torch.from_numpy(x), torch.tensor([spec["width"] / spec["height"]]))
    out = {k: v.numpy() for k, v in zip(model.output_names, out)}
    points, mask, normal = head_maps_to_size(out["points_raw"][0], out["mask_logits"][0], out["normal_raw"][0],
                                             size=(spec["height"], spec["width"]), remap_output="exp")
    want = {k.split(".")[-1]: v for k, v in cases.items() if k.startswith(f"case{case}.forward.")}
    assert official_close(points, want["points"]) <= TOL
    assert official_close(normal, want["normal"]) <= TOL
    assert official_close(mask, want["mask"]) <= TOL
    assert official_close(out["metric_scale"][0], want["metric_scale"]) <= TOL


@pytest.mark.parametrize("known_fov", [False, True])
@pytest.mark.parametrize("case", [0, 1])
def test_pipeline_matches_official_infer(official, case, known_fov):
    """``infer(image, num_tokens)`` (focal and shift recovered) and ``infer(..., fov_x=60)`` (shift only)."""
    meta, model, cases = official
    spec = meta["cases"][case]
    result = infer_torch(model, cases[f"case{case}.image"], num_tokens=spec["num_tokens"],
                         fov_x=meta["fov_x"] if known_fov else None)
    want = {k.split(".")[-1]: v for k, v in cases.items() if k.startswith(f"case{case}.infer.")}
    valid = want["mask"].astype(bool)
    if known_fov:
        want.update({k.split(".")[-1]: v for k, v in cases.items() if k.startswith(f"case{case}.infer_fov.")})
    assert 0.2 < valid.mean() < 0.8  # the random heads give a mixed mask: both branches are compared
    assert np.array_equal(result.valid, valid)
    assert official_close(result.intrinsics, want["intrinsics"]) <= TOL
    assert official_close(result.depth[valid], want["depth"][valid]) <= TOL
    assert np.isinf(result.depth[~valid]).all() and np.isinf(want["depth"][~valid]).all()
    assert official_close(result.points[valid], want["points"][valid]) <= TOL
    assert np.isinf(result.points[~valid]).all() and np.isinf(want["points"][~valid]).all()
    assert official_close(result.normal, want["normal"]) <= TOL

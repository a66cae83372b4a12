"""The Fun-Camera DiT with its camera adapter against VideoX-Fun's own ``WanTransformer3DModel``
(aigc-apps/VideoX-Fun at 804a425, ``add_control_adapter=True``, model_type i2v), at a tiny size in float32.

The fixture (``fixtures/official/funcamera/``, see its README) is an official transformer folder (``config.json`` +
``diffusion_pytorch_model.safetensors`` written from the official module's ``state_dict()``), loaded here through
our converter ``load_fun_camera``; the inputs are raw Plücker rays (packed by our ``fun_camera_pack`` here, by the
official pipeline's code there), noisy and start-image latents, text and CLIP features and a timestep.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import official_close

from navcrafter.models.synthesis.funcamera import fun_camera_pack, load_fun_camera

FIXTURE = Path(__file__).with_name("fixtures") / "official" / "funcamera"
TOL = 1e-4

pytestmark = [pytest.mark.official_parity, pytest.mark.usefixtures("one_torch_thread")]


@pytest.fixture(scope="module")
def official():
    from safetensors.torch import load_file

    meta = json.loads((FIXTURE / "meta.json").read_text())
    model = load_fun_camera(FIXTURE).eval()
    cases = {k: v.float() for k, v in load_file(str(FIXTURE / "cases.safetensors")).items()}
    return meta, model, cases


def test_fixture_names_its_source(official):
    meta, model, _ = official
    assert meta["official_repo"] == "aigc-apps/VideoX-Fun" and meta["commit"] == "804a425"
    assert model.config.dim == 24 and model.config.image_dim == 4 and model.config.rope_max_seq_len == 1024


def test_adapter_on_the_pipeline_packing_matches(official):
    _, model, cases = official
    with torch.no_grad():
        got = model.control_adapter(fun_camera_pack(cases["plucker"]))
    assert official_close(got, cases["adapter"]) <= TOL


@pytest.mark.parametrize("camera", [True, False])
def test_dit_forward_matches_wan_transformer3d(official, camera):
    _, model, c = official
    with torch.no_grad():
        pred = model(torch.cat([c["x"], c["y"]], dim=1), c["t"], c["context"], c["clip_fea"],
                     c["plucker"] if camera else None)
    want = c["noise_pred" if camera else "noise_pred_no_camera"]
    assert official_close(pred, want) <= TOL
    assert np.abs(c["noise_pred"] - c["noise_pred_no_camera"]).max() > 0.1  # the rays do reach the output

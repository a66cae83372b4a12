"""Difix against the official implementation (nv-tlabs/Difix3D at c76edc5, run with its pinned diffusers 0.25.1 and
peft 0.9.0): the VAE encoder with its skip activations, the decoder with the skip convolutions and the decoder LoRA,
and the whole one-step denoise, with reference mixing (``mv_unet``, nvidia/difix_ref) and without (nvidia/difix).

The fixture (``fixtures/official/difix/``, see its README) is a diffusers-layout directory (``unet/`` and ``vae/``
safetensors from the official modules' ``state_dict()``: diffusers names, ``decoder.skip_conv_*`` and peft's unmerged
LoRA layout), loaded through our ``load_difix_weights``; the official outputs come from ``Difix.forward`` itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers import official_close

from navcrafter.models.refiner.difix import DifixConfig, DifixRefinerModel, load_difix_weights

FIXTURE = Path(__file__).with_name("fixtures") / "official" / "difix"
TOL = 1e-4

pytestmark = [pytest.mark.official_parity, pytest.mark.usefixtures("one_torch_thread")]


def _model(meta: dict, reference_mixing: bool) -> DifixRefinerModel:
    vae, unet = meta["vae"], meta["unet"]
    config = DifixConfig(unet_block_out_channels=tuple(unet["block_out_channels"]),
                         unet_layers_per_block=unet["layers_per_block"],
                         unet_attention_heads=tuple(unet["attention_head_dim"]),
                         cross_attention_dim=unet["cross_attention_dim"], unet_norm_num_groups=unet["norm_num_groups"],
                         vae_block_out_channels=tuple(vae["block_out_channels"]),
                         vae_layers_per_block=vae["layers_per_block"], vae_norm_num_groups=vae["norm_num_groups"],
                         lora_rank=meta["lora_rank"], timestep=meta["timestep"], reference_mixing=reference_mixing)
    torch.manual_seed(123)  # any init: every weight comes from the official state dicts
    model = DifixRefinerModel(config).eval()
    load_difix_weights(model, FIXTURE)
    return model


@pytest.fixture(scope="module")
def official():
    from safetensors.torch import load_file

    meta = json.loads((FIXTURE / "meta.json").read_text())
    return meta, load_file(str(FIXTURE / "cases.safetensors"))


def test_fixture_names_its_source(official):
    meta, _ = official
    assert meta["official_repo"] == "nv-tlabs/Difix3D" and meta["commit"] == "c76edc5"
    assert len(meta["lora_targets"]) > 10  # peft adapted the decoder (LoRA active, not zeroed)


def test_vae_encoder_and_decoder_with_skips_match(official):
    meta, c = official
    model = _model(meta, reference_mixing=True)
    x = c["views"].reshape(2, 3, 32, 32)
    with torch.no_grad():
        mean, std, skips = model.encode(x)
        mean_ref, logvar_ref = c["encoder.moments"].chunk(2, dim=1)
        assert official_close(mean, mean_ref) <= TOL
        assert official_close(std, torch.exp(0.5 * logvar_ref.clamp(-30.0, 20.0))) <= TOL
        assert len(skips) == 4
        for i, s in enumerate(skips):
            assert official_close(s, c[f"encoder.skip{i}"]) <= TOL, i
        decoded = model.decode(mean_ref, [c[f"encoder.skip{i}"] for i in range(4)])
        assert official_close(decoded, c["decoder.out"]) <= TOL


@pytest.mark.parametrize("reference_mixing", [True, False])
def test_one_step_refinement_matches_difix_forward(official, reference_mixing):
    meta, c = official
    model = _model(meta, reference_mixing)
    name = "ref" if reference_mixing else "plain"
    views = c["views"]
    with torch.no_grad():
        out = model(views[:, 0], views[:, 1] if reference_mixing else None, c["prompt_embeds"],
                    latent_noise=c[f"{name}.latent_noise"])
    assert official_close(out, c[f"{name}.out"]) <= TOL
    assert 0.05 < c[f"{name}.out"].abs().mean() < 0.95  # not saturated by the final clamp


def test_reference_mixing_changes_the_output(official):
    _, c = official
    assert (c["ref.out"] - c["plain.out"]).abs().max() > 1e-2  # the two official paths differ: both are tested

"""Camera-controlled Wan2.1 DiT: zero-init identity, control paths, weights I/O, ONNX export."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from navcrafter.models.synthesis import camcontrol as cc


def _base_only(model: cc.CameraControlledWan):
    """An independent copy of the base with diffusers' own attention processor restored."""
    from diffusers.models.transformers.transformer_wan import WanAttnProcessor

    base = copy.deepcopy(model.base)
    for block in base.blocks:
        block.attn1.set_processor(WanAttnProcessor())
    return base.eval()


def _base_out(base, inp) -> torch.Tensor:
    with torch.no_grad():
        return base(inp["hidden_states"], inp["timestep"], inp["encoder_hidden_states"],
                    inp["encoder_hidden_states_image"], return_dict=False)[0]


def _out(model, inp, **kw) -> torch.Tensor:
    with torch.no_grad():
        return model(**{**inp, **kw})


@pytest.fixture(scope="module")
def tiny() -> cc.CameraControlledWan:
    return cc.tiny_camera_wan(seed=0)


@pytest.fixture(scope="module")
def trained(tiny) -> cc.CameraControlledWan:
    """The tiny model with every control weight randomised (as if trained)."""
    return cc.randomize_camera_control(copy.deepcopy(tiny), seed=1)


@pytest.fixture(scope="module")
def exported(tmp_path_factory, export_cache):
    """ONE export of the full camera-controlled DiT (batch 2, 2 latent frames, 4x4 latents), every control path
    active. One DiT block instead of the tiny preset's two: each block costs ~20 s of export time on these
    CPUs, and all blocks run the same code (the torch tests above cover two). Kept between sessions while the
    code stays the same (conftest.export_cache)."""
    import time

    from navcrafter.models.runtime.onnxio import GraphInfo

    config, seeds, shape = {**cc.TINY_I2V_CONFIG, "num_layers": 1}, (0, 1), (2, 2, 4, 4)
    model = cc.randomize_camera_control(cc.build_camera_wan(config, cc.tiny_camera_config(), seed=seeds[0]),
                                        seed=seeds[1])
    folder = tmp_path_factory.mktemp("dit")

    def export(out):
        t0 = time.perf_counter()
        info = cc.export_dit(model, out / "dit.onnx", shape)
        print(f"export_dit: {time.perf_counter() - t0:.1f} s")
        return info.__dict__

    args = {"config": config, "camera": cc.tiny_camera_config(), "seeds": seeds, "shape": shape}
    info = GraphInfo(**export_cache(folder, "camcontrol-dit", args, export))
    return model, folder / "dit.onnx", info


def test_zero_init_equals_base(tiny):
    base = _base_only(tiny)
    inp = cc.example_inputs(tiny, (2, 3, 6, 8), seed=3)
    assert inp["plucker"].abs().sum() > 0 and inp["cond"].abs().sum() > 0
    ref = _base_out(base, inp)
    assert torch.equal(_out(tiny, inp), ref)
    assert torch.equal(_out(tiny, inp, plucker=None, cond=None), ref)
    # training mode (random reference frames) is still the identity while untrained
    tiny.train()
    try:
        assert torch.equal(_out(tiny, inp, reference_latents=torch.randn(2, 16, 3, 6, 8)), ref)
    finally:
        tiny.eval()


def test_randomised_control_depends_on_plucker_cond_and_scale(tiny, trained):
    base = _base_only(tiny)
    inp = cc.example_inputs(trained, (1, 2, 4, 4), seed=4)
    out = _out(trained, inp)
    assert out.shape == (1, 16, 2, 4, 4)
    assert not torch.allclose(out, _base_out(base, inp), atol=1e-4)
    assert not torch.allclose(out, _out(trained, inp, plucker=inp["plucker"].flip(2)), atol=1e-5)
    assert not torch.allclose(out, _out(trained, inp, cond=torch.zeros_like(inp["cond"])), atol=1e-5)
    assert not torch.allclose(out, _out(trained, inp, lora_scale=torch.tensor(0.0)), atol=1e-5)


def test_lora_scale_zero_equals_base(tiny):
    model = copy.deepcopy(tiny)
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for name, p in model.control.named_parameters():
            if ".lora_" in name:
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)
    base = _base_only(tiny)
    inp = cc.example_inputs(model, (2, 2, 4, 4), seed=5)
    assert torch.equal(_out(model, inp, lora_scale=torch.tensor(0.0)), _base_out(base, inp))
    assert not torch.allclose(_out(model, inp, lora_scale=torch.tensor(0.7)), _base_out(base, inp), atol=1e-5)


def test_reference_frames_seeded_and_include_first():
    a = [cc.select_reference_frames(9, 3, torch.Generator().manual_seed(7)).tolist() for _ in range(2)]
    assert a[0] == a[1] and a[0][0] == 0 and len(set(a[0])) == 3 and a[0] == sorted(a[0])
    draws = {tuple(cc.select_reference_frames(9, 3, torch.Generator().manual_seed(s)).tolist()) for s in range(20)}
    assert len(draws) > 1 and all(d[0] == 0 for d in draws)
    assert cc.select_reference_frames(2, 5).tolist() == [0, 1]
    assert cc.select_reference_frames(4, 0).numel() == 0


def test_training_mode_reference_selection(trained):
    model = copy.deepcopy(trained).train()
    model.seed_reference_frames(11)
    first = [model.reference_indices(6) for _ in range(5)]
    model.seed_reference_frames(11)
    assert first == [model.reference_indices(6) for _ in range(5)]
    assert all(f[0] == 0 and len(f) == model.config.num_reference_frames for f in first)
    model.eval()
    assert model.reference_indices(6) == [0]
    # the reference branch reads the clean latents of exactly the chosen frames
    inp = cc.example_inputs(model, (1, 3, 4, 4), seed=6)
    clean = torch.randn(1, 16, 3, 4, 4)
    out = _out(model, inp, reference_frames=[0, 2], reference_latents=clean)
    changed = clean.clone()
    changed[:, :, 1] += 1.0  # not a reference frame
    assert torch.equal(out, _out(model, inp, reference_frames=[0, 2], reference_latents=changed))
    changed[:, :, 2] += 1.0  # a reference frame
    assert not torch.allclose(out, _out(model, inp, reference_frames=[0, 2], reference_latents=changed), atol=1e-6)


def test_training_needs_clean_reference_latents_and_trains_the_lora_at_full_strength(trained):
    model = copy.deepcopy(trained).train()
    inp = cc.example_inputs(model, (1, 3, 4, 4), seed=6)
    with pytest.raises(ValueError, match="training mode needs reference_latents"):
        _out(model, inp)
    clean = torch.randn(1, 16, 3, 4, 4)
    default = {**inp, "lora_scale": None}
    assert torch.equal(_out(model, default, reference_frames=[0], reference_latents=clean),
                       _out(model, inp, reference_frames=[0], reference_latents=clean, lora_scale=1.0))
    assert not torch.allclose(_out(model, default, reference_frames=[0], reference_latents=clean),
                              _out(model, inp, reference_frames=[0], reference_latents=clean, lora_scale=0.7))
    model.eval()
    assert model.config.lora_scale == 0.7
    assert torch.equal(_out(model, default), _out(model, inp, lora_scale=0.7))


def test_input_shape_errors(tiny):
    inp = cc.example_inputs(tiny, (1, 2, 4, 4))
    with pytest.raises(ValueError, match="plucker must be"):
        _out(tiny, inp, plucker=inp["plucker"][:, :, :4])
    with pytest.raises(ValueError, match="cond must be"):
        _out(tiny, inp, cond=inp["cond"][:, :16])


def test_config_roundtrip_and_masks():
    cfg = cc.CameraControlConfig(lora_rank=8, plucker_convention="paper", inference_reference_frames=[0])
    assert cc.CameraControlConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match="unknown"):
        cc.CameraControlConfig.from_dict({"lora_rnk": 3})
    with pytest.raises(ValueError, match="plucker_convention"):
        cc.CameraControlConfig(plucker_convention="other")
    assert cc.latent_frames(81) == 21 and cc.video_frames(21) == 81
    # Wan I2V mask layout: latent frame 0 = video frame 0 (x4), latent frame k = video frames 4k-3..4k
    vis = torch.zeros(1, 9, 16, 16)
    vis[:, 0] = 1.0
    vis[:, 6, :8, :8] = 1.0
    packed = cc.pack_visibility_mask(vis)
    assert packed.shape == (1, 4, 3, 2, 2)
    assert torch.all(packed[:, :, 0] == 1) and packed[0, 1, 2, 0, 0] == 1 and packed.sum() == 4 * 4 + 1
    cond = cc.make_render_condition(torch.zeros(1, 16, 3, 2, 2), vis)
    assert cond.shape == (1, 20, 3, 2, 2)
    rays = np.random.default_rng(0).normal(size=(5, 32, 32, 6)).astype(np.float32)
    assert cc.plucker_to_tensor(rays).shape == (1, 6, 5, 32, 32)


def test_save_load_roundtrip(tiny, trained, tmp_path):
    cc.save_camera_control(trained, tmp_path / "ctrl")
    assert sorted(p.name for p in (tmp_path / "ctrl").iterdir()) == [cc.CONTROL_CONFIG, cc.CONTROL_WEIGHTS]
    inp = cc.example_inputs(trained, (1, 2, 4, 4), seed=8)
    fresh = copy.deepcopy(tiny)
    cc.load_camera_control(fresh, tmp_path / "ctrl")
    assert torch.equal(_out(fresh, inp), _out(trained, inp))
    # from_pretrained: diffusers base directory + control directory
    _base_only(tiny).save_pretrained(tmp_path / "wan" / "transformer")
    loaded = cc.CameraControlledWan.from_pretrained(tmp_path / "wan", tmp_path / "ctrl").eval()
    assert torch.equal(_out(loaded, inp), _out(trained, inp))
    zero = cc.CameraControlledWan.from_pretrained(tmp_path / "wan").eval()
    assert torch.equal(_out(zero, inp), _base_out(_base_only(tiny), inp))


def test_load_mismatch_fails_clearly(tiny, trained, tmp_path):
    from safetensors.torch import load_file, save_file

    other = cc.build_camera_wan(cc.TINY_I2V_CONFIG, cc.CameraControlConfig(adapter_channels=16, lora_rank=3,
                                                                          lora_in_channels=8))
    cc.save_camera_control(other, tmp_path / "rank3")
    with pytest.raises(cc.CameraControlWeightsError, match=r"camera_control\.safetensors.*lora_q\.down\.weight"):
        cc.load_camera_control(copy.deepcopy(tiny), tmp_path / "rank3")
    cc.save_camera_control(trained, tmp_path / "partial")
    state = load_file(tmp_path / "partial" / cc.CONTROL_WEIGHTS)
    del state["blocks.1.ref_gate"]
    save_file(state, tmp_path / "partial" / cc.CONTROL_WEIGHTS)
    with pytest.raises(cc.CameraControlWeightsError, match=r"missing keys \[blocks\.1\.ref_gate\]"):
        cc.load_camera_control(copy.deepcopy(tiny), tmp_path / "partial")
    with pytest.raises(FileNotFoundError, match="camera_control.json"):
        cc.load_camera_control(copy.deepcopy(tiny), tmp_path)


@pytest.mark.parametrize("shape", [(2, 2, 4, 4), (2, 3, 6, 8), (1, 3, 6, 8)])
def test_onnx_matches_torch(exported, shape):
    """One export, several frame counts (5 and 9 video frames), resolutions and batch sizes."""
    from navcrafter.models.runtime.onnxio import create_session

    model, path, info = exported
    assert info.inputs == cc.DIT_INPUTS and info.outputs == ["noise_pred"]
    assert info.dynamic["plucker"][2] and info.dynamic["hidden_states"][2] and info.dynamic["hidden_states"][0]
    sess = create_session(path, ["CPUExecutionProvider"])
    inp = cc.example_inputs(model, shape, seed=9)
    got = sess.run(["noise_pred"], {k: v.numpy() for k, v in inp.items()})[0]
    want = _out(model, inp).numpy()
    assert got.shape == want.shape == (shape[0], 16, *shape[1:])
    assert np.abs(got - want).max() <= 1e-4

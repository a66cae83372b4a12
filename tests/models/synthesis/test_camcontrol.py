"""Camera-controlled Wan2.1 DiT: zero-init identity, control paths, weights I/O, ONNX export."""

from __future__ import annotations

import copy
import dataclasses
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
    assert inp["image_reference"].shape == (2, 16, 1, 6, 8)  # one extra reference frame
    ref = _base_out(base, inp)
    assert torch.equal(_out(tiny, inp), ref)
    assert torch.equal(_out(tiny, inp, plucker=None, cond=None), ref)
    assert torch.equal(_out(tiny, cc.example_inputs(tiny, (2, 3, 6, 8), seed=3, reference_images=2)), ref)
    assert torch.equal(_out(tiny, inp, image_reference=None, image_reference_plucker=None), ref)
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


def test_extra_reference_frames_join_the_reference_attention(tiny, trained):
    inp = cc.example_inputs(trained, (1, 2, 4, 4), seed=12, reference_images=2)
    out = _out(trained, inp)
    none = _out(trained, inp, image_reference=None, image_reference_plucker=None)
    assert not torch.allclose(out, none, atol=1e-5)
    # every extra frame's latents and rays count
    for key in ("image_reference", "image_reference_plucker"):
        changed = inp[key].clone()
        changed[:, :, 1] += 1.0
        assert not torch.allclose(out, _out(trained, inp, **{key: changed}), atol=1e-6), key
    # the order of the extra frames does not matter (same rope position, each with its own camera tokens)
    flipped = {k: inp[k].flip(2) for k in ("image_reference", "image_reference_plucker")}
    assert torch.allclose(out, _out(trained, inp, **flipped), atol=1e-5)
    # only the reference branch sees them: a zero gate makes them irrelevant
    gated = copy.deepcopy(trained)
    with torch.no_grad():
        for blk in gated.control.blocks:
            blk.ref_gate.zero_()
    assert torch.equal(_out(gated, inp), _out(gated, inp, image_reference=None, image_reference_plucker=None))
    # errors name the input
    with pytest.raises(ValueError, match="needs image_reference_plucker"):
        _out(trained, inp, image_reference_plucker=None)
    with pytest.raises(ValueError, match="image_reference_plucker must be"):
        _out(trained, inp, image_reference_plucker=inp["image_reference_plucker"][:, :, :1])
    with pytest.raises(ValueError, match="image_reference must be"):
        _out(trained, inp, image_reference=inp["image_reference"][:, :, :, :2])
    with pytest.raises(ValueError, match="without image_reference"):
        _out(trained, inp, image_reference=None)


def test_low_rank_projections(tiny):
    dim = cc.TINY_I2V_CONFIG["num_attention_heads"] * cc.TINY_I2V_CONFIG["attention_head_dim"]
    assert tiny.config.projection_rank == 64
    blk = tiny.control.blocks[0]
    for proj in (blk.pre_proj, blk.attn_proj):  # rank capped at the width; up zero, down random
        assert proj.down.weight.shape == (dim, dim) and proj.up.weight.shape == (dim, dim)
        assert not proj.up.weight.any() and not proj.up.bias.any() and proj.down.weight.abs().sum() > 0
    small = cc.build_camera_wan(cc.TINY_I2V_CONFIG, cc.CameraControlConfig(
        adapter_channels=16, lora_in_channels=8, lora_rank=4, projection_rank=5))
    assert small.control.blocks[1].pre_proj.down.weight.shape == (5, dim)
    assert small.control.blocks[1].attn_proj.up.weight.shape == (dim, 5)
    full = cc.build_camera_wan(cc.TINY_I2V_CONFIG, cc.CameraControlConfig(
        adapter_channels=16, lora_in_channels=8, lora_rank=4, projection_rank=0))
    assert isinstance(full.control.blocks[0].pre_proj, torch.nn.Linear)
    assert {"blocks.0.pre_proj.weight", "blocks.0.attn_proj.bias"} <= set(full.control.state_dict())
    inp = cc.example_inputs(tiny, (1, 2, 4, 4), seed=13)
    for model in (small, full):  # zero-initialised whatever the rank
        assert torch.equal(_out(model, inp), _base_out(_base_only(model), inp))
    with pytest.raises(ValueError, match="projection_rank"):
        cc.CameraControlConfig(projection_rank=-1)


def test_parameter_counts_on_meta_device():
    import time

    t0 = time.perf_counter()
    tiny = cc.control_parameter_counts(cc.TINY_I2V_CONFIG, cc.tiny_camera_config())
    model = cc.tiny_camera_wan()
    assert tiny["base"] == sum(p.numel() for p in model.base.parameters())
    assert tiny["control"] == sum(p.numel() for p in model.control.parameters()) == sum(tiny["parts"].values())
    for preset in (cc.wan_1_3b_camera_config, cc.wan_14b_camera_config):
        base_cfg, control_cfg = preset()
        low = cc.control_parameter_counts(base_cfg, control_cfg)
        full = cc.control_parameter_counts(base_cfg, dataclasses.replace(control_cfg, projection_rank=0))
        dim = base_cfg["num_attention_heads"] * base_cfg["attention_head_dim"]
        assert full["parts"]["projections"] == 2 * base_cfg["num_layers"] * (dim * dim + dim)
        assert low["ratio"] <= 0.10 < full["ratio"], (preset.__name__, low["ratio"], full["ratio"])
    assert cc.WAN_14B_I2V_CONFIG["num_attention_heads"] * cc.WAN_14B_I2V_CONFIG["attention_head_dim"] == 5120
    assert 16e9 < full["base"] < 17e9 and full["parts"]["projections"] > 2e9  # Wan2.1-I2V-14B: 16.4 B
    assert time.perf_counter() - t0 < 30


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
    assert cc.CameraControlConfig().plucker_convention == "relative"
    legacy = {k: v for k, v in cc.CameraControlConfig().to_dict().items() if k != "projection_rank"}
    assert cc.CameraControlConfig.from_dict(legacy).projection_rank == 0  # saved before low-rank projections
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


@pytest.mark.parametrize("convention", ["paper", "ray"])
def test_version_1_weights_load_full_rank_with_their_convention(tiny, tmp_path, convention):
    """A format-version-1 save: full D x D projections, no projection_rank in its config, its own convention."""
    v1_cfg = dataclasses.replace(cc.tiny_camera_config(), projection_rank=0, plucker_convention=convention)
    old = cc.randomize_camera_control(cc.build_camera_wan(cc.TINY_I2V_CONFIG, v1_cfg, seed=0), seed=3)
    cc.save_camera_control(old, tmp_path / "v1")
    meta_path = tmp_path / "v1" / cc.CONTROL_CONFIG
    meta = json.loads(meta_path.read_text())
    assert meta["format_version"] == cc.CONTROL_FORMAT_VERSION == 2
    meta["format_version"] = 1
    del meta["config"]["projection_rank"]
    meta_path.write_text(json.dumps(meta))
    cfg = cc.read_camera_control_config(tmp_path / "v1")
    assert (cfg.projection_rank, cfg.plucker_convention) == (0, convention)
    _base_only(tiny).save_pretrained(tmp_path / "wan" / "transformer")
    loaded = cc.CameraControlledWan.from_pretrained(tmp_path / "wan", tmp_path / "v1").eval()
    assert loaded.config.plucker_convention == convention
    inp = cc.example_inputs(old, (1, 2, 4, 4), seed=8)
    assert torch.equal(_out(loaded, inp), _out(old, inp))
    # into a low-rank model they do not fit, and the error says where
    with pytest.raises(cc.CameraControlWeightsError, match=r"pre_proj"):
        cc.load_camera_control(copy.deepcopy(tiny), tmp_path / "v1")
    meta["format_version"] = 3
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(cc.CameraControlWeightsError, match="readable version"):
        cc.read_camera_control_config(tmp_path / "v1")


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


@pytest.mark.parametrize("shape,refs", [((2, 2, 4, 4), 2), ((2, 3, 6, 8), 1), ((1, 3, 6, 8), 3)])
def test_onnx_matches_torch(exported, shape, refs):
    """One export, several frame counts (5 and 9 video frames), resolutions, batch sizes and numbers of extra
    reference frames."""
    from navcrafter.models.runtime.onnxio import create_session

    model, path, info = exported
    assert info.inputs == cc.DIT_INPUTS and info.outputs == ["noise_pred"]
    assert info.dynamic["plucker"][2] and info.dynamic["hidden_states"][2] and info.dynamic["hidden_states"][0]
    assert info.dynamic["image_reference"][2] and info.dynamic["image_reference_plucker"][2]
    sess = create_session(path, ["CPUExecutionProvider"])
    inp = cc.example_inputs(model, shape, seed=9, reference_images=refs)
    got = sess.run(["noise_pred"], {k: v.numpy() for k, v in inp.items()})[0]
    want = _out(model, inp).numpy()
    assert got.shape == want.shape == (shape[0], 16, *shape[1:])
    assert np.abs(got - want).max() <= 1e-4


def test_the_wan_base_loads_from_safetensors_and_refuses_a_wrong_layout(tmp_path):
    """``load_wan_transformer`` without accelerate (diffusers then refuses Wan): config + safetensors, names checked."""
    from diffusers.models.transformers.transformer_wan import WanTransformer3DModel
    from diffusers.utils import is_accelerate_available
    from safetensors.torch import save_file

    if is_accelerate_available():
        pytest.skip("with accelerate installed diffusers' own from_pretrained loads the base")
    base = cc.build_camera_wan(cc.TINY_I2V_CONFIG, cc.tiny_camera_config(), seed=3).base
    base.save_config(tmp_path)
    state = {k: v.contiguous() for k, v in base.state_dict().items()}
    save_file(state, str(tmp_path / "diffusion_pytorch_model.safetensors"))
    loaded = cc.load_wan_transformer(tmp_path)
    assert isinstance(loaded, WanTransformer3DModel)
    assert all(torch.equal(v, loaded.state_dict()[k]) for k, v in state.items())
    del state["blocks.0.ffn.net.0.proj.weight"]
    state["extra.weight"] = torch.zeros(1)
    save_file(state, str(tmp_path / "diffusion_pytorch_model.safetensors"))
    with pytest.raises(cc.CameraControlWeightsError, match=r"Wan weights do not fit its config\.json: missing keys "
                                                           r"\[blocks\.0\.ffn\.net\.0\.proj\.weight\]; unexpected keys "
                                                           r"\[extra\.weight\]"):
        cc.load_wan_transformer(tmp_path)

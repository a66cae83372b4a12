"""fun-camera (Wan2.1-Fun-V1.1-Control-Camera, models/synthesis/funcamera/): official layout, strict converter,
VideoX-Fun's Plücker convention, the adapter's place, ONNX vs torch, and the sampler on a tiny random export."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

pytest.importorskip("diffusers")

from helpers import TINY_MODELS_SIZE  # noqa: E402

from navcrafter.models.synthesis import funcamera as fc  # noqa: E402
from navcrafter.schemas.config import SynthesisConfig  # noqa: E402

T, H, W = TINY_MODELS_SIZE
CPU = ["CPUExecutionProvider"]


def _random_adapter(model: fc.FunCameraWan, seed: int = 1, std: float = 0.05) -> fc.FunCameraWan:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.control_adapter.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * std)
    return model


def _dit_inputs(model: fc.FunCameraWan, b=2, f=2, h=4, w=4, seed=0):
    return [fc.fun_example_inputs(model, (b, f, h, w), image_tokens=17, seed=seed)[n] for n in fc.FUN_DIT_INPUTS]


# --------------------------------------------------------------------------------------------------
# Official layout and the strict converter
# --------------------------------------------------------------------------------------------------
def test_committed_1_3b_layout_is_what_our_module_converts_to():
    header, layout = fc.read_key_list()
    with torch.device("meta"):
        model = fc.FunCameraWan(fc.FunCameraConfig.wan_1_3b())
    assert list(fc.official_layout(model).items()) == list(layout.items())  # names, shapes and order
    assert len(layout) == header["num_tensors"] == 989
    assert sum(math.prod(s) for s in layout.values()) == header["num_parameters"]
    assert layout["patch_embedding.weight"] == (1536, 32, 1, 2, 2)  # 16 noisy + 16 start-image latents
    assert layout["control_adapter.conv.weight"] == (1536, 24 * 64, 2, 2)  # 6 x 4 packed rays, PixelUnshuffle(8)
    official = fc.FunCameraConfig.wan_1_3b().official_config()
    assert all(official[k] == v for k, v in header["config"].items())  # the constructor args it was generated with
    assert fc.FunCameraConfig.from_official_config(header["config"]) == fc.FunCameraConfig.wan_1_3b()


def test_check_layout_accepts_exactly_the_official_layout():
    _, layout = fc.read_key_list()
    with torch.device("meta"):
        expected = fc.official_layout(fc.FunCameraWan(fc.FunCameraConfig.wan_1_3b()))
    fc.check_layout(layout, expected, "ckpt")
    missing = dict(layout)
    del missing["blocks.7.cross_attn.k_img.weight"]
    with pytest.raises(fc.FunCameraWeightsError,
                       match=r"ckpt: .*missing keys \[blocks\.7\.cross_attn\.k_img\.weight\]"):
        fc.check_layout(missing, expected, "ckpt")
    extra = {**layout, "ref_conv.weight": (1536, 16, 2, 2)}
    with pytest.raises(fc.FunCameraWeightsError, match=r"unexpected keys \[ref_conv\.weight\]"):
        fc.check_layout(extra, expected, "ckpt")
    wrong = {**layout, "patch_embedding.weight": (1536, 36, 1, 2, 2)}  # a Wan2.1 I2V layout (mask channels)
    with pytest.raises(fc.FunCameraWeightsError,
                       match=r"shape mismatch \[patch_embedding\.weight: file \[1536, 36, 1, 2, 2\] vs model "
                             r"\[1536, 32, 1, 2, 2\]\].*official transformer folder"):
        fc.check_layout(wrong, expected, "ckpt")


def test_14b_preset_layout():
    with torch.device("meta"):
        layout = fc.official_layout(fc.FunCameraWan(fc.FunCameraConfig.wan_14b()))
    assert len(layout) == 12 + 40 * 32 + 3 + 8 + 6
    assert layout["blocks.39.ffn.0.weight"] == (13824, 5120)
    assert layout["control_adapter.residual_blocks.0.conv1.weight"] == (5120, 5120, 3, 3)


def test_save_load_round_trip_and_refusals(tmp_path):
    from safetensors.torch import load_file, save_file

    model = _random_adapter(fc.tiny_fun_camera(seed=2))
    d = fc.save_fun_camera(model, tmp_path / "fun")
    sd = load_file(str(d / fc.OFFICIAL_WEIGHTS))
    assert sorted(sd) == sorted(fc.official_layout(model))  # official names (safetensors stores them sorted)
    assert json.loads((d / "config.json").read_text())["add_control_adapter"] is True
    loaded = fc.load_fun_camera(d)
    a, b = model.state_dict(), loaded.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert loaded.config == model.config
    x = _dit_inputs(model)
    with torch.no_grad():
        assert torch.equal(model(*x), loaded(*x))

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "config.json").write_text((d / "config.json").read_text())
    renamed = {("blocks.0.norm2.weight" if k == "blocks.0.norm3.weight" else k): v for k, v in sd.items()}
    save_file(renamed, str(bad / fc.OFFICIAL_WEIGHTS))
    with pytest.raises(fc.FunCameraWeightsError, match=r"missing keys \[blocks\.0\.norm3\.weight\]; unexpected keys "
                                                       r"\[blocks\.0\.norm2\.weight\]"):
        fc.load_fun_camera(bad)
    cfg = json.loads((d / "config.json").read_text())
    (bad / "config.json").write_text(json.dumps({**cfg, "num_layers": 3}))
    save_file(sd, str(bad / fc.OFFICIAL_WEIGHTS))
    with pytest.raises(fc.FunCameraWeightsError, match=r"missing keys \[blocks\.2\."):
        fc.load_fun_camera(bad)
    (bad / "config.json").write_text(json.dumps({**cfg, "add_ref_conv": True}))
    with pytest.raises(fc.FunCameraWeightsError, match="add_ref_conv is true"):
        fc.load_fun_camera(bad)
    (bad / "config.json").write_text(json.dumps({**cfg, "add_control_adapter": False}))
    with pytest.raises(fc.FunCameraWeightsError, match="not a Control-Camera checkpoint"):
        fc.load_fun_camera(bad)
    with pytest.raises(FileNotFoundError, match="config.json"):
        fc.load_fun_camera(tmp_path)


def test_key_mapping_is_a_bijection_onto_diffusers_names():
    model = fc.tiny_fun_camera()
    for k in model.state_dict():
        assert fc.official_to_ours(fc.ours_to_official(k)) == k
    assert fc.official_to_ours("blocks.3.norm3.weight") == "base.blocks.3.norm2.weight"  # affine cross-attn norm
    assert fc.official_to_ours("blocks.3.cross_attn.k_img.bias") == "base.blocks.3.attn2.add_k_proj.bias"
    assert fc.official_to_ours("head.modulation") == "base.scale_shift_table"
    assert fc.official_to_ours("blocks.0.norm2.weight") is None  # the official norm2 has no parameters


# --------------------------------------------------------------------------------------------------
# Plücker convention (videox_fun/data/utils.py: get_relative_pose, ray_condition)
# --------------------------------------------------------------------------------------------------
K_SMALL = np.array([[10.0, 0.0, 2.0], [0.0, 12.0, 1.5], [0.0, 0.0, 1.0]])


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_plucker_identity_pose_by_hand():
    rays = fc.fun_camera_plucker(np.eye(4)[None], K_SMALL, 3, 4)
    assert rays.shape == (1, 3, 4, 6) and rays.dtype == np.float32
    assert not rays[..., :3].any()  # o = 0: no moment
    # pixel (row 0, col 0): centre (0.5, 0.5) -> ((0.5 - 2) / 10, (0.5 - 1.5) / 12, 1)
    np.testing.assert_allclose(rays[0, 0, 0, 3:], _unit([-0.15, -1 / 12, 1.0]), atol=1e-6)
    # pixel (row 2, col 3): centre (3.5, 2.5)
    np.testing.assert_allclose(rays[0, 2, 3, 3:], _unit([0.15, 1 / 12, 1.0]), atol=1e-6)


def test_plucker_known_translation_moment_first():
    first = np.eye(4)
    first[:3, 3] = [5.0, -2.0, 7.0]  # the clip's first camera anywhere in the world
    second = first.copy()
    second[:3, 3] += [2.0, 0.0, 0.0]  # then 2 units along its own +x (right)
    rays = fc.fun_camera_plucker(np.stack([first, second]), K_SMALL, 3, 4)
    assert not rays[0, ..., :3].any()  # frame 0 is the identity
    d = _unit([-0.15, -1 / 12, 1.0])
    np.testing.assert_allclose(rays[1, 0, 0, 3:], d, atol=1e-6)  # no rotation: same direction
    # (o x d) with o = (2, 0, 0): (0, -2 dz, 2 dy); not rescaled (navcrafter's "relative" would divide by |t| = 2)
    np.testing.assert_allclose(rays[1, 0, 0, :3], [0.0, -2 * d[2], 2 * d[1]], atol=1e-6)


def test_plucker_rotation_and_navcrafter_cross_check():
    from navcrafter.models.camera.cameras import axis_angle_to_matrix, make_pose, plucker_rays

    yaw = make_pose(axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.pi / 2), np.zeros(3))
    rays = fc.fun_camera_plucker(np.stack([np.eye(4), yaw]), K_SMALL, 3, 4)
    # the principal-ish ray (0, 0, 1) turned 90 degrees about +y points along +x
    centre = fc.fun_camera_plucker(np.stack([np.eye(4), yaw]), np.array([[10.0, 0, 2], [0, 10, 1.5], [0, 0, 1]]),
                                   3, 4)[1, 1, 2, 3:]  # pixel centre (2.5, 1.5): x = 0.05, y = 0
    np.testing.assert_allclose(centre, _unit([1.0, 0.0, -0.05]), atol=1e-6)
    assert np.allclose(rays[1, ..., :3], 0)
    # a general clip: navcrafter's "relative" lines without scale normalisation (same pixel centres, OpenCV)
    rng = np.random.RandomState(0)
    clip = [make_pose(axis_angle_to_matrix(_unit(rng.randn(3)), rng.uniform(0, 0.5)), rng.randn(3) * 3)
            for _ in range(4)]
    ours = fc.fun_camera_plucker(np.stack(clip), K_SMALL, 3, 4)
    np.testing.assert_allclose(ours, plucker_rays(np.stack(clip), K_SMALL, 3, 4, "relative", scale=1.0), atol=2e-5)
    assert not np.allclose(ours, plucker_rays(np.stack(clip), K_SMALL, 3, 4, "relative"), atol=1e-3)
    with pytest.raises(ValueError, match="skew"):
        fc.fun_camera_plucker(np.stack(clip), K_SMALL + np.array([[0, 0.1, 0], [0, 0, 0], [0, 0, 0]]), 3, 4)


def test_re10k_rows_intrinsics_adjustment(tmp_path):
    from navcrafter.models.camera.camerafiles import read_re10k_cameras

    w2c = np.eye(4)[:3]
    second = np.eye(4)
    second[:3, 3] = [0.0, 0.0, -1.0]  # world-to-camera: the camera moved +1 along z (forward)
    rows = [[0, 0.5, 0.9, 0.5, 0.5, 0, 0, *w2c.reshape(-1)], [1, 0.5, 0.9, 0.5, 0.5, 0, 0, *second[:3].reshape(-1)]]
    path = tmp_path / "clip.txt"
    path.write_text("https://www.youtube.com/watch?v=x\n" + "\n".join(" ".join(str(v) for v in r) for r in rows))
    cams = read_re10k_cameras(path)  # the one RealEstate10K parser (models/camera/camerafiles.py)
    np.testing.assert_array_equal(cams.rows(), rows)
    rays = fc.fun_camera_plucker_from_re10k(cams, width=32, height=32)  # 1280x720 poses on a square sample
    np.testing.assert_array_equal(rays, fc.fun_camera_plucker_from_re10k(rows, width=32, height=32))
    # pose W/H (16/9) > sample W/H (1): fx *= H * 16/9 / W, then pixel fx = fx * W
    K = np.array([[0.5 * 16 / 9 * 32, 0, 16], [0, 0.9 * 32, 16], [0, 0, 1]])
    c2w = np.stack([np.eye(4), np.linalg.inv(second)])
    np.testing.assert_allclose(rays, fc.fun_camera_plucker(c2w, K, 32, 32), atol=1e-6)
    np.testing.assert_allclose(rays[1, 5, 7, :3], np.cross([0, 0, 1.0], rays[1, 5, 7, 3:]), atol=1e-6)
    wide = fc.fun_camera_plucker_from_re10k(rows, width=64, height=16)  # W/H 4 > 16/9: fy is adjusted instead
    K_wide = np.array([[0.5 * 64, 0, 32], [0, (64 / (16 / 9)) * 0.9 / 16 * 16, 8], [0, 0, 1]])
    np.testing.assert_allclose(wide, fc.fun_camera_plucker(c2w, K_wide, 16, 64), atol=1e-6)


def test_temporal_packing_and_pixel_unshuffle():
    c_idx = torch.arange(6).view(1, 6, 1, 1, 1).float()
    t_idx = torch.arange(9).view(1, 1, 9, 1, 1).float()
    rays = (100 * c_idx + t_idx).expand(1, 6, 9, 2, 2)
    packed = fc.fun_camera_pack(rays)
    assert packed.shape == (1, 24, 3, 2, 2)
    for k in range(3):
        for c in range(6):
            for j in range(4):
                frame = 0 if k == 0 else 4 * k - 3 + j
                assert packed[0, 4 * c + j, k, 0, 0].item() == 100 * c + frame
    x = torch.randn(3, 5, 16, 24)
    assert torch.equal(fc.pixel_unshuffle(x, 8), torch.nn.PixelUnshuffle(8)(x))


# --------------------------------------------------------------------------------------------------
# Architecture: the adapter is added after the patch embedding, the rest is diffusers' Wan
# --------------------------------------------------------------------------------------------------
def test_without_camera_it_is_diffusers_wan_and_the_adapter_only_adds_to_the_patch_embedding():
    model = _random_adapter(fc.tiny_fun_camera(seed=4))
    x = _dit_inputs(model)
    with torch.no_grad():
        plain = model.base(x[0], x[1], x[2], encoder_hidden_states_image=x[3], return_dict=False)[0]
        no_cam = model(*x[:4], None)
        cam = model(*x)
        tokens = model.control_adapter(fc.fun_camera_pack(x[4]))
        embedded = []
        hook = model.base.patch_embedding.register_forward_hook(lambda m, i, o: embedded.append(o) or o + tokens)
        try:
            hooked = model.base(x[0], x[1], x[2], encoder_hidden_states_image=x[3], return_dict=False)[0]
        finally:
            hook.remove()
    assert torch.equal(plain, no_cam)
    assert tokens.shape == embedded[0].shape  # [B, D, F, h/2, w/2]: the patch embedding's output grid
    assert (cam - no_cam).abs().max() > 1e-3
    torch.testing.assert_close(cam, hooked, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match=r"plucker must be"):
        model(*x[:4], x[4][:, :, :-4])


def test_init_navcrafter_from_fun_camera_keeps_the_base():
    from navcrafter.models.synthesis.camcontrol import tiny_camera_config

    fun = fc.tiny_fun_camera(seed=5)
    nav = fc.init_navcrafter_from_fun_camera(fun, tiny_camera_config())
    assert nav.base.config.in_channels == 36
    w = nav.base.patch_embedding.weight
    assert not w[:, 16:20].any() and torch.equal(w[:, 20:], fun.base.patch_embedding.weight[:, 16:])
    x = _dit_inputs(fun, seed=3)
    start = x[0][:, 16:].clone()
    start[:, :, 1:] = 0  # the Fun layout: latent frames after the first are zero
    mask = torch.zeros(2, 4, *start.shape[2:])
    mask[:, :, 0] = 1
    with torch.no_grad():
        want = fun(torch.cat([x[0][:, :16], start], 1), *x[1:4], None)
        got = nav(torch.cat([x[0][:, :16], mask, start], 1), *x[1:4])  # untrained control: the base
    torch.testing.assert_close(got, want, rtol=0, atol=1e-5)


# --------------------------------------------------------------------------------------------------
# ONNX and the sampler
# --------------------------------------------------------------------------------------------------
def test_dit_onnx_matches_torch(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    model = _random_adapter(fc.tiny_fun_camera(seed=6))
    info = fc.export_fun_camera_dit(model, tmp_path / "dit.onnx", example_shape=(2, 2, 4, 4), image_tokens=17,
                                    dynamic=False)
    assert fc.PLUCKER_CONVENTION in info.notes
    sess = ort.InferenceSession(str(tmp_path / "dit.onnx"), providers=CPU)
    assert [i.name for i in sess.get_inputs()] == fc.FUN_DIT_INPUTS
    for seed in (1, 2):
        inputs = fc.fun_example_inputs(model, (2, 2, 4, 4), image_tokens=17, seed=seed)
        out = sess.run(None, {k: v.numpy() for k, v in inputs.items()})[0]
        with torch.no_grad():
            ref = model(*[inputs[n] for n in fc.FUN_DIT_INPUTS]).numpy()
        assert np.abs(out - ref).max() <= 1e-4 and np.abs(ref).max() > 0.1


@pytest.fixture(scope="module")
def fun_export(tmp_path_factory, export_cache):
    from navcrafter.models.zoo.exporters import export_fun_camera

    root = tmp_path_factory.mktemp("fun") / "synthesizer"
    args = dict(num_frames=T, height=H, width=W, random="tiny", seed=0, prompt="a room")
    export_cache(root, "tiny-fun-camera", args, lambda out: bool(export_fun_camera(out, **args)))
    return root


def _request(frames=T, seed=0, dx=0.4):
    from navcrafter.models.camera.cameras import Intrinsics
    from navcrafter.models.roles import SynthesisRequest

    traj = np.stack([np.eye(4)] * frames)
    traj[:, 0, 3] = np.linspace(0.0, dx, frames)
    rng = np.random.RandomState(1)
    return SynthesisRequest(image=rng.randint(0, 256, (H, W, 3), dtype=np.uint8), trajectory=traj,
                            intrinsics=Intrinsics.from_fov(60.0, W, H), cloud_points=np.zeros((0, 3), np.float32),
                            cloud_colors=np.zeros((0, 3), np.uint8), seed=seed)


def test_tiny_export_manifest(fun_export):
    from navcrafter.models.runtime.onnxio import load_manifest

    m = load_manifest(fun_export, "synthesizer")
    assert m["architecture"] == fc.ARCHITECTURE and m["weights"]["source"] == "random"
    c = m["config"]
    assert (c["model"], c["plucker_convention"], c["condition_layout"]) == ("fun-camera", "videox-fun", "fun-camera")
    assert c["in_channels"] == 32 and c["control"]["cond_channels"] == 0
    assert c["official_config"]["add_control_adapter"] is True
    assert m["graphs"]["dit"]["inputs"] == fc.FUN_DIT_INPUTS


def test_sampler_end_to_end_onnx_equals_torch(fun_export):
    from navcrafter.models.synthesis import pipeline as pl
    from navcrafter.models.synthesis.onnx_export import tiny_fun_camera_components
    from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer

    synth = OnnxSynthesizer(fun_export, SynthesisConfig(num_frames=T, height=H, width=W, steps=2, model="fun-camera"),
                            providers=CPU)
    assert (synth.model_name, synth.convention) == ("fun-camera", "videox-fun")
    request = _request()
    plucker, renders, masks, ref, ref_rays = synth.conditions(request)
    np.testing.assert_allclose(plucker, fc.fun_camera_plucker(request.trajectory, request.intrinsics.K, H, W))
    assert ref is None and ref_rays is None and not renders.any() and not masks.any()
    frames = synth.synthesize(request)
    assert frames.shape == (T, H, W, 3) and frames.dtype == np.uint8
    assert np.array_equal(frames, synth.synthesize(request))
    assert not np.array_equal(frames, synth.synthesize(_request(dx=-0.4)))  # the camera reaches the DiT

    torch_runner = pl.TorchRunner(tiny_fun_camera_components(seed=0, prompt="a room"))
    cond = pl.prepare_conditions(torch_runner, request.image, plucker, renders, masks)
    assert cond["hidden_cond"].shape == (1, 16, 2, H // 8, W // 8)
    assert cond["hidden_cond"][:, :, 0].any() and not cond["hidden_cond"][:, :, 1:].any()  # frame 0 only
    cfg = synth.sampler_config(request.seed)
    pos, neg = synth.text_emb, synth.neg_text_emb
    lat_ort = pl.sample_latents(synth.runner, request.image, plucker, renders, masks, pos, neg, cfg)
    lat_torch = pl.sample_latents(torch_runner, request.image, plucker, renders, masks, pos, neg, cfg)
    assert np.abs(lat_ort - lat_torch).max() <= 1e-3


def test_synthesizer_refuses_another_model_or_a_navcrafter_convention(fun_export):
    from navcrafter.models.synthesis.onnx_synthesizer import (
        OnnxSynthesizer,
        PluckerConventionError,
        SynthesizerModelError,
    )

    size = dict(num_frames=T, height=H, width=W, steps=2)
    with pytest.raises(SynthesizerModelError, match=r"synthesis.model='navcrafter'.*is 'fun-camera'"):
        OnnxSynthesizer(fun_export, SynthesisConfig(**size), providers=CPU)
    with pytest.raises(PluckerConventionError, match="unset synthesis.plucker_convention"):
        OnnxSynthesizer(fun_export, SynthesisConfig(**size, model="fun-camera", plucker_convention="relative"),
                        providers=CPU)


def test_synthesis_model_is_keyed_only_when_set():
    from navcrafter.schemas.config import RunConfig

    assert SynthesisConfig().model == "navcrafter"
    assert SynthesisConfig.keyed_when_set["model"] == "navcrafter"
    with pytest.raises(ValueError):
        SynthesisConfig(model="wan")
    assert RunConfig.load(preset="tiny").synthesis.model == "navcrafter"


def test_fun_presets_share_navcrafters_base_widths():
    """What init_navcrafter_from_fun_camera relies on: the Fun presets are our I2V presets but for the input
    channels."""
    from navcrafter.models.synthesis.camcontrol import WAN_1_3B_I2V_CONFIG, WAN_14B_I2V_CONFIG

    for fun, ours in [(fc.FunCameraConfig.wan_1_3b(), WAN_1_3B_I2V_CONFIG),
                      (fc.FunCameraConfig.wan_14b(), WAN_14B_I2V_CONFIG)]:
        assert fun.diffusers_kwargs() == {**ours, "in_channels": 32}


def test_cli_export_fun_camera_usage_and_show(fun_export, tmp_path):
    from typer.testing import CliRunner

    from navcrafter.flows.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["models", "export-fun-camera", str(tmp_path / "x")])
    assert res.exit_code == 2 and "give either checkpoint_dir" in res.output, res.output
    res = runner.invoke(app, ["models", "export-fun-camera", str(tmp_path / "x"), "--random", "full"])
    assert res.exit_code == 2 and "not provided" in res.output, res.output
    res = runner.invoke(app, ["models", "show", str(fun_export)])
    assert res.exit_code == 0 and "wan2.1-fun-v1.1-control-camera" in res.output, res.output

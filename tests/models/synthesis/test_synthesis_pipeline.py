"""Synthesizer export + sampler: tiny random Wan2.1-I2V camera model, ONNX vs torch, OnnxSynthesizer."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("diffusers")
pytest.importorskip("onnxruntime")

from helpers import TINY_MODELS_SIZE  # noqa: E402

from navcrafter.models.camera.cameras import Intrinsics, look_at  # noqa: E402
from navcrafter.models.roles import SynthesisRequest, Synthesizer  # noqa: E402
from navcrafter.schemas.config import SynthesisConfig  # noqa: E402

T, H, W = TINY_MODELS_SIZE
CPU = ["CPUExecutionProvider"]


@pytest.fixture(scope="module")
def tiny_export(tiny_models):
    """One tiny export shared by the module's tests (static shapes: several times faster to export), and the
    same tiny modules rebuilt from the seed (for the torch engine)."""
    from navcrafter.models.synthesis.onnx_export import tiny_components

    # the session's shared export: export_synthesizer(..., tiny=True, num_frames=T, height=H, width=W,
    # prompt="a room", seed=0)
    return tiny_models / "synthesizer", tiny_components(seed=0, prompt="a room")


@pytest.fixture(scope="module")
def inputs():
    rng = np.random.RandomState(0)
    return {"image": rng.randint(0, 256, (H, W, 3), dtype=np.uint8),
            "plucker": rng.standard_normal((T, H, W, 6)).astype(np.float32),
            "renders": rng.randint(0, 256, (T, H, W, 3), dtype=np.uint8),
            "masks": rng.rand(T, H, W) > 0.3}


@pytest.fixture(scope="module")
def ort_runner(tiny_export):
    from navcrafter.models.synthesis.pipeline import OrtRunner

    return OrtRunner(tiny_export[0], CPU)


def test_manifest(tiny_export):
    from navcrafter.models.runtime.onnxio import load_manifest

    out, components = tiny_export
    m = load_manifest(out, "synthesizer")  # verifies every sha256
    assert m["architecture"] == "wan2.1-i2v-camera"
    assert set(m["graphs"]) == {"dit", "vae_encoder", "vae_decoder", "image_encoder"}
    assert m["weights"] == {"source": "random", "seed": 0}
    c = m["config"]
    assert (c["num_frames"], c["height"], c["width"], c["vae_num_frames"]) == (T, H, W, T)
    assert c["dynamic_shapes"] is False  # tiny exports default to static graphs
    assert (c["latent_channels"], c["vae_scale_factor_temporal"], c["vae_scale_factor_spatial"]) == (16, 4, 8)
    assert c["patch_size"] == [1, 2, 2] and c["control"]["cond_channels"] == 20
    assert c["plucker_convention"] == c["control"]["plucker_convention"] == "relative"  # the control's own
    assert c["scheduler"]["prediction_type"] == "flow_prediction" and c["scheduler"]["flow_shift"] > 0
    assert "text_embeddings.npy" in m["files"]
    emb = np.load(out / "text_embeddings.npy")
    assert emb.shape == (2, 512, c["text_dim"]) and np.array_equal(emb, components.text_embeddings)
    assert m["graphs"]["dit"]["inputs"][:3] == ["hidden_states", "timestep", "encoder_hidden_states"]
    assert m["graphs"]["dit"]["inputs"][-2:] == ["image_reference", "image_reference_plucker"]


def test_onnx_matches_torch_and_seeds(tiny_export, ort_runner, inputs):
    from navcrafter.models.synthesis import pipeline as pl

    torch_runner = pl.TorchRunner(tiny_export[1])  # rebuilt from the export's seed
    pos, neg = ort_runner.text_embeddings()
    cfg = pl.sampler_settings(SynthesisConfig(steps=2), seed=3)
    lat_ort = pl.sample_latents(ort_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg)
    lat_torch = pl.sample_latents(torch_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg)
    assert lat_ort.shape == (1, 16, 2, H // 8, W // 8)
    assert np.abs(lat_ort - lat_torch).max() <= 1e-3
    v_ort, v_torch = pl.decode_video(ort_runner, lat_ort), pl.decode_video(torch_runner, lat_torch)
    assert v_ort.shape == (T, H, W, 3) and v_ort.dtype == np.uint8
    assert np.abs(v_ort.astype(int) - v_torch.astype(int)).max() <= 2

    # Deterministic given the seed; other seeds, and another camera, give other videos.
    conds = pl.prepare_conditions(ort_runner, **inputs)
    again = pl.sample_latents(ort_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg, conditions=conds)
    assert np.array_equal(again, lat_ort)
    other = pl.sample_latents(ort_runner, **inputs, text_emb=pos, neg_text_emb=neg,
                              cfg=pl.sampler_settings(SynthesisConfig(steps=2), seed=4), conditions=conds)
    assert np.abs(other - lat_ort).max() > 1e-2
    moved = dict(inputs, plucker=inputs["plucker"][::-1].copy())
    camera = pl.sample_latents(ort_runner, **moved, text_emb=pos, neg_text_emb=neg, cfg=cfg)
    assert np.abs(camera - lat_ort).max() > 1e-4

    # Without a reference the extra reference frame is the conditioning image at the first camera.
    assert np.array_equal(conds["image_reference"], conds["hidden_cond"][:, 4:, :1])
    assert np.array_equal(conds["image_reference_plucker"], conds["plucker"][:, :, :1])
    explicit = pl.sample_latents(ort_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg,
                                 reference_image=inputs["image"], reference_plucker=inputs["plucker"][:1])
    assert np.abs(explicit - lat_ort).max() <= 1e-5  # the VAE is causal: the same latents, encoded apart


def test_extra_reference_frame_torch_equals_onnx(tiny_export, ort_runner, inputs):
    """The input photo as an extra reference: VAE-encoded (one frame), its rays next to the clip's."""
    from navcrafter.models.synthesis import pipeline as pl

    torch_runner = pl.TorchRunner(tiny_export[1])
    pos, neg = ort_runner.text_embeddings()
    cfg = pl.sampler_settings(SynthesisConfig(steps=2), seed=3)
    rng = np.random.RandomState(1)
    ref = {"reference_image": rng.randint(0, 256, (H, W, 3), dtype=np.uint8),
           "reference_plucker": rng.standard_normal((1, H, W, 6)).astype(np.float32)}
    conds = pl.prepare_conditions(ort_runner, **inputs, **ref)
    assert conds["image_reference"].shape == (1, 16, 1, H // 8, W // 8)
    assert conds["image_reference_plucker"].shape == (1, 6, 1, H, W)
    lat_ort = pl.sample_latents(ort_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg, conditions=conds)
    lat_torch = pl.sample_latents(torch_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg, **ref)
    assert np.abs(lat_ort - lat_torch).max() <= 1e-3
    plain = pl.sample_latents(ort_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg)
    assert np.abs(lat_ort - plain).max() > 1e-4
    other_rays = dict(ref, reference_plucker=-ref["reference_plucker"])
    moved = pl.sample_latents(ort_runner, **inputs, text_emb=pos, neg_text_emb=neg, cfg=cfg, **other_rays)
    assert np.abs(lat_ort - moved).max() > 1e-5
    with pytest.raises(pl.SynthesisShapeError, match="needs reference_plucker"):
        pl.prepare_conditions(ort_runner, **inputs, reference_image=ref["reference_image"])
    with pytest.raises(pl.SynthesisShapeError, match="reference_image must be"):
        pl.prepare_conditions(ort_runner, **inputs, reference_image=ref["reference_image"][:16],
                              reference_plucker=ref["reference_plucker"])


def _request(seed: int = 7, frames: int = T, start: float = 0.0, reference: bool = False) -> SynthesisRequest:
    rng = np.random.RandomState(seed)
    K = Intrinsics.from_fov(60.0, W, H)
    pts = (rng.rand(400, 3) * [2.0, 2.0, 1.0] + [-1.0, -1.0, 2.0]).astype(np.float32)
    cols = rng.randint(0, 256, (400, 3), dtype=np.uint8)
    traj = np.stack([look_at([start + 0.1 * i, 0.0, 0.0], [0.0, 0.0, 2.5]) for i in range(frames)])
    extra = {"reference_image": rng.randint(0, 256, (H, W, 3), dtype=np.uint8),
             "reference_c2w": np.eye(4)} if reference else {}
    return SynthesisRequest(image=rng.randint(0, 256, (H, W, 3), dtype=np.uint8), trajectory=traj, intrinsics=K,
                            cloud_points=pts, cloud_colors=cols, seed=seed, **extra)


def test_onnx_synthesizer(tiny_export):
    from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer

    config = SynthesisConfig(num_frames=T, height=H, width=W, steps=2)
    synth = OnnxSynthesizer(tiny_export[0], config, providers=CPU)
    assert isinstance(synth, Synthesizer) and synth.backend == "onnx"
    request = _request()
    plucker, renders, masks, ref_image, ref_rays = synth.conditions(request)
    assert plucker.shape == (T, H, W, 6) and renders.shape == (T, H, W, 3) and masks.any()
    assert ref_image is None and ref_rays is None
    frames = synth.synthesize(request)
    assert frames.shape == (T, H, W, 3) and frames.dtype == np.uint8
    assert np.array_equal(frames, synth.synthesize(request))


def test_onnx_synthesizer_extra_reference_in_the_clip_frame(tiny_export):
    """A clip that starts away from the input camera: the photo's rays share the clip's origin and scale."""
    from navcrafter.models.camera.cameras import plucker_rays, relative_poses
    from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer

    synth = OnnxSynthesizer(tiny_export[0], SynthesisConfig(num_frames=T, height=H, width=W, steps=2),
                            providers=CPU)
    assert synth.convention == "relative"
    request = _request(start=0.5, reference=True)
    plucker, _, _, ref_image, ref_rays = synth.conditions(request)
    assert np.array_equal(ref_image, request.reference_image) and ref_rays.shape == (1, H, W, 6)
    rel, scale = relative_poses(request.trajectory)
    photo = np.linalg.inv(request.trajectory[0]) @ request.reference_c2w
    photo[:3, 3] /= scale
    np.testing.assert_allclose(ref_rays, plucker_rays(photo[None], request.intrinsics.K, H, W, "ray"), atol=1e-5)
    assert np.abs(ref_rays[0, ..., :3]).max() > 0.1  # the photo is not at the clip's origin
    np.testing.assert_allclose(plucker, plucker_rays(rel, request.intrinsics.K, H, W, "ray"), atol=1e-5)
    with_ref = synth.synthesize(request)
    without = synth.synthesize(_request(start=0.5))
    assert with_ref.shape == (T, H, W, 3) and not np.array_equal(with_ref, without)
    with pytest.raises(ValueError, match="come together"):
        synth.synthesize(SynthesisRequest(**{**request.__dict__, "reference_c2w": None}))


def test_onnx_synthesizer_refuses_a_convention_mismatch(tiny_export, tmp_path):
    import json
    import shutil

    from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer, PluckerConventionError

    config = dict(num_frames=T, height=H, width=W, steps=2)
    assert OnnxSynthesizer(tiny_export[0], SynthesisConfig(**config, plucker_convention="relative"),
                           providers=CPU).convention == "relative"
    with pytest.raises(PluckerConventionError, match=r"plucker_convention='paper'.*trained with 'relative'"):
        OnnxSynthesizer(tiny_export[0], SynthesisConfig(**config, plucker_convention="paper"), providers=CPU)
    old = tmp_path / "old"
    shutil.copytree(tiny_export[0], old)
    manifest = json.loads((old / "manifest.json").read_text())
    del manifest["config"]["plucker_convention"]
    (old / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(PluckerConventionError, match=rf"{old}.*no plucker_convention.*re-export"):
        OnnxSynthesizer(old, SynthesisConfig(**config), providers=CPU)


def test_wrong_frame_count(tiny_export, ort_runner, inputs):
    from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer
    from navcrafter.models.synthesis.pipeline import SynthesisShapeError, sample_video, sampler_settings

    with pytest.raises(SynthesisShapeError, match="synthesis.num_frames"):
        OnnxSynthesizer(tiny_export[0], SynthesisConfig(num_frames=9, height=H, width=W, steps=2), providers=CPU)
    synth = OnnxSynthesizer(tiny_export[0], SynthesisConfig(num_frames=T, height=H, width=W, steps=2),
                            providers=CPU)
    with pytest.raises(SynthesisShapeError, match="synthesis.num_frames=5"):
        synth.synthesize(_request(frames=9))
    nine = {k: np.concatenate([v, v[1:]]) if k != "image" else v for k, v in inputs.items()}
    pos, neg = ort_runner.text_embeddings()
    with pytest.raises(SynthesisShapeError, match="exported for num_frames=5"):
        sample_video(ort_runner, **nine, text_emb=pos, neg_text_emb=neg,
                     cfg=sampler_settings(SynthesisConfig(steps=2), seed=0))


def test_load_components_from_diffusers_dir(tiny_export, tmp_path):
    """The checkpoint path: a diffusers-format directory (+ camera-control weights) loads with safetensors,
    prompts are encoded with UMT5 (zero past the prompt's tokens) and every source file is hashed."""
    import torch
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, UMT5Config, UMT5EncoderModel

    from navcrafter.models.synthesis.camcontrol import save_camera_control
    from navcrafter.models.synthesis.onnx_export import load_components

    tiny = tiny_export[1]
    base = tmp_path / "wan"
    tiny.dit.base.save_pretrained(base / "transformer")
    tiny.vae.save_pretrained(base / "vae")
    tiny.image_encoder.save_pretrained(base / "image_encoder")
    torch.manual_seed(0)
    UMT5EncoderModel(UMT5Config(vocab_size=8, d_model=tiny.dit.base.config.text_dim, d_kv=8, d_ff=16, num_layers=1,
                                num_heads=2, relative_attention_num_buckets=8)).save_pretrained(base / "text_encoder")
    tok = Tokenizer(models.WordLevel({"<pad>": 0, "</s>": 1, "<unk>": 2, "a": 3, "room": 4}, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="<pad>", eos_token="</s>",
                            unk_token="<unk>").save_pretrained(base / "tokenizer")
    save_camera_control(tiny.dit, tmp_path / "control")

    loaded = load_components(base, tmp_path / "control", prompt="a room", negative_prompt="room")
    for a, b in [(tiny.dit, loaded.dit), (tiny.vae, loaded.vae), (tiny.image_encoder, loaded.image_encoder)]:
        sa, sb = a.state_dict(), b.state_dict()
        assert set(sa) == set(sb) and all(torch.equal(sa[k], sb[k]) for k in sa), type(a).__name__
    emb = loaded.text_embeddings
    assert emb.shape == (2, 512, tiny.dit.base.config.text_dim)
    assert np.abs(emb[0, :2]).sum() > 0 and not emb[0, 2:].any() and not emb[1, 1:].any()
    w = loaded.weights
    assert w["source"] == "checkpoint" and "transformer/diffusion_pytorch_model.safetensors" in w["files"]
    assert set(w["control"]["files"]) == {"camera_control.safetensors", "camera_control.json"}
    with pytest.raises(FileNotFoundError, match="text_encoder"):
        load_components(tmp_path / "control")


def test_sampler_settings_come_from_the_run_config_alone():
    from navcrafter.models.synthesis.pipeline import WAN_FLOW_SHIFT, sampler_settings

    s = sampler_settings(SynthesisConfig(), seed=5)
    assert (s.steps, s.guidance_scale, s.lora_scale, s.seed) == (40, 6.5, 0.7, 5)  # the paper's, defined once
    assert s.flow_shift == WAN_FLOW_SHIFT
    assert sampler_settings(SynthesisConfig(), 0, {"flow_shift": 5.0}).flow_shift == 5.0  # the model's own
    assert sampler_settings(SynthesisConfig(flow_shift=7.0), 0, {"flow_shift": 5.0}).flow_shift == 7.0  # the run's


def test_a_control_trained_without_render_conditioning_samples(tmp_path, inputs):
    """cond_channels = 0 (camera-control training on real datasets, which have no depth for the render
    conditioning): the sampler passes no render condition, and the trained weights load into the tiny base."""
    import dataclasses

    from navcrafter.models.synthesis import pipeline as pl
    from navcrafter.models.synthesis.camcontrol import (
        TINY_I2V_CONFIG,
        build_camera_wan,
        randomize_camera_control,
        save_camera_control,
        tiny_camera_config,
    )
    from navcrafter.models.synthesis.onnx_export import tiny_components

    model = build_camera_wan(TINY_I2V_CONFIG, dataclasses.replace(tiny_camera_config(), cond_channels=0), seed=0)
    save_camera_control(randomize_camera_control(model, seed=1), tmp_path / "control")
    components = tiny_components(seed=0, control_dir=tmp_path / "control")
    assert components.dit.control.cond_embedding is None
    assert components.weights["control"]["path"] == str((tmp_path / "control").resolve())
    runner = pl.TorchRunner(components, T, H, W)
    conds = pl.prepare_conditions(runner, **inputs)
    assert conds["cond"] is None
    pos, neg = components.text_embeddings
    lat = pl.sample_latents(runner, **inputs, text_emb=pos, neg_text_emb=neg,
                            cfg=pl.sampler_settings(SynthesisConfig(steps=2), seed=3), conditions=conds)
    assert lat.shape == (1, 16, 2, H // 8, W // 8) and np.isfinite(lat).all()


def test_an_fp16_dit_agrees_with_fp32_and_samples(tiny_export, tmp_path):
    """``models convert-fp16``: the DiT's weights and activations in fp16, normalisations in fp32, fp32 inputs and
    outputs; the manifest names the new graph with its checksums and precision; the sampler runs it unchanged."""
    import json
    import shutil
    from collections import Counter

    import onnx
    import onnxruntime as ort
    from typer.testing import CliRunner

    from navcrafter.flows.cli import app
    from navcrafter.models.runtime.onnxio import FP32_OPS, ModelDirError, convert_model_dir_fp16, load_manifest
    from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer

    src, half = tiny_export[0], tmp_path / "fp16"
    shutil.copytree(src, half)
    res = CliRunner().invoke(app, ["models", "convert-fp16", str(half)])
    assert res.exit_code == 0, res.output
    manifest = load_manifest(half, "synthesizer")  # every checksum verified
    assert manifest["precision"] == {"dit": "fp16", "image_encoder": "fp32", "vae_decoder": "fp32",
                                     "vae_encoder": "fp32"}
    assert manifest["graphs"]["dit"]["file"] == "dit.fp16.onnx" and not (half / "dit.onnx").exists()
    graph = onnx.load(str(half / "dit.fp16.onnx"), load_external_data=False).graph
    kinds = Counter(onnx.TensorProto.DataType.Name(t.data_type) for t in graph.initializer)
    assert kinds["FLOAT16"] > 10 * kinds["FLOAT"]
    assert all(v.type.tensor_type.elem_type == onnx.TensorProto.FLOAT for v in [*graph.input, *graph.output])
    produced = {o: n for n in graph.node for o in n.output}
    norm_inputs = [produced.get(i) for n in graph.node if n.op_type in FP32_OPS for i in n.input[:1]]
    assert norm_inputs and not any(p is not None and p.op_type == "Cast" and any(
        a.name == "to" and a.i == onnx.TensorProto.FLOAT16 for a in p.attribute) for p in norm_inputs)
    with pytest.raises(ModelDirError, match="fp16 already"):
        convert_model_dir_fp16(half)
    # the DiT: fp16 within 2 % (mean) of fp32 on the same inputs
    runs = {}
    for name, d in (("fp32", src), ("fp16", half)):
        m = json.loads((d / "manifest.json").read_text())
        runs[name] = ort.InferenceSession(str(d / m["graphs"]["dit"]["file"]), providers=CPU)
    rng = np.random.default_rng(0)
    feeds = {i.name: (0.5 * rng.standard_normal([d if isinstance(d, int) else 2 for d in i.shape])).astype(np.float32)
             for i in runs["fp32"].get_inputs()}
    feeds.update(timestep=np.array([500.0, 500.0], np.float32), lora_scale=np.array(0.7, np.float32))
    a, b = (runs[k].run(None, feeds)[0] for k in ("fp32", "fp16"))
    assert b.dtype == np.float32 and np.abs(a - b).mean() < 0.02 * np.abs(a).mean() and not np.array_equal(a, b)
    # the sampler is unchanged: the same request, frames close to the fp32 model's
    config = SynthesisConfig(num_frames=T, height=H, width=W, steps=2)
    request = _request()
    f32 = OnnxSynthesizer(src, config, providers=CPU).synthesize(request)
    f16 = OnnxSynthesizer(half, config, providers=CPU).synthesize(request)
    assert f16.shape == f32.shape and f16.dtype == np.uint8
    assert np.abs(f16.astype(int) - f32.astype(int)).mean() < 3.0


def test_offload_holds_one_graph_at_a_time_and_changes_nothing(tiny_export):
    from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer

    request = _request()
    plain = OnnxSynthesizer(tiny_export[0], SynthesisConfig(num_frames=T, height=H, width=W, steps=2), providers=CPU)
    light = OnnxSynthesizer(tiny_export[0], SynthesisConfig(num_frames=T, height=H, width=W, steps=2, offload=True),
                            providers=CPU)
    seen = []
    session = light.runner.graphs.session

    def spy(graph):
        out = session(graph)
        seen.append(sorted(light.runner.graphs._sessions))
        return out

    light.runner.graphs.session = spy
    frames = light.synthesize(request)
    assert np.array_equal(frames, plain.synthesize(request))
    assert seen and all(len(s) == 1 for s in seen)  # never two graphs' sessions at once
    assert {s[0] for s in seen} == {"vae_encoder", "image_encoder", "dit", "vae_decoder"}
    assert len(plain.runner.graphs._sessions) == 4  # without offload every graph stays loaded

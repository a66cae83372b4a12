"""Difix-architecture refiner: torch network, official checkpoint layouts, ONNX export, onnxruntime role.

One tiny random export is shared by the module (the dynamic-shape export dominates the run time).
"""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from navcrafter.models.refiner.difix import (
    LORA_ADAPTER,
    PROMPT_FILE,
    DifixConfig,
    DifixRefinerModel,
    DifixWeightsError,
    encode_prompt,
    export_refiner,
    load_difix_weights,
    lora_target_modules,
    official_key_shapes,
    official_state_dicts,
    random_prompt_embeds,
    randomize_adapters,
    read_official_key_list,
    save_difix_weights,
    skip_channels,
)
from navcrafter.models.refiner.onnx_refiner import OnnxRefiner
from navcrafter.models.roles import Refiner
from navcrafter.models.runtime import onnxio

TINY = DifixConfig.tiny()
M = TINY.size_multiple  # 4: VAE factor 2 x one UNet downsampling


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def exported(tmp_path_factory, export_cache):
    out = tmp_path_factory.mktemp("models") / "refiner"
    export_cache(out, "refiner", {"config": TINY, "seed": 0}, lambda d: bool(export_refiner(d, TINY, seed=0)))
    return out


def _model(seed: int = 0, config: DifixConfig = TINY) -> DifixRefinerModel:
    torch.manual_seed(seed)  # export_refiner builds its random model the same way
    model = DifixRefinerModel(config).eval()
    randomize_adapters(model, seed)
    return model


def _inputs(h: int, w: int, seed: int, batch: int = 1, views: int = 2):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 3, h, w, generator=g) * 2 - 1
    reference = torch.rand(batch, 3, h, w, generator=g) * 2 - 1
    noise = torch.randn(batch, views, TINY.latent_channels, h // TINY.vae_scale_factor, w // TINY.vae_scale_factor,
                        generator=g)
    return image, reference, noise


def _run(model, image, reference, noise, emb=None):
    emb = torch.from_numpy(random_prompt_embeds(model.config, 0)) if emb is None else emb
    with torch.no_grad():
        return model(image, reference, emb, noise)


def test_onnx_matches_torch_at_two_sizes(exported):
    model = _model(0)  # unmerged LoRA: the export merges it, which must not change the output
    manifest = onnxio.load_manifest(exported, "refiner")
    runner = onnxio.GraphRunner(exported, manifest, ["CPUExecutionProvider"])
    emb = np.load(exported / PROMPT_FILE)
    np.testing.assert_array_equal(emb, random_prompt_embeds(TINY, 0))
    for h, w in [(8 * M, 5 * M), (4 * M, 9 * M)]:
        image, reference, noise = _inputs(h, w, seed=h + w)
        want = _run(model, image, reference, noise, torch.from_numpy(emb)).numpy()
        got = runner.run("refiner", {"image": image.numpy(), "reference": reference.numpy(), "prompt_embeds": emb,
                                     "latent_noise": noise.numpy()})["refined"]
        assert got.shape == want.shape == (1, 3, h, w)
        assert np.abs(got - want).max() <= 1e-4, (h, w)
        assert np.abs(want).max() <= 1.0 and np.abs(want).std() > 1e-3  # clamped, not constant


def test_reference_view_is_mixed_in_and_batches_do_not_mix():
    model = _model(1)
    image, reference, noise = _inputs(6 * M, 4 * M, seed=2)
    base = _run(model, image, reference, noise)
    other = _run(model, image, torch.flip(reference, dims=[3]), noise)
    assert (base - other).abs().max() > 1e-3  # the reference changes the refined input view
    # batch folding is "(b v)": sample 0 of a batch of two equals sample 0 alone
    image2, reference2, noise2 = _inputs(6 * M, 4 * M, seed=3)
    both = _run(model, torch.cat([image, image2]), torch.cat([reference, reference2]), torch.cat([noise, noise2]))
    assert torch.allclose(both[:1], base, atol=1e-5) and not torch.allclose(both[1:], base, atol=1e-3)


def test_identical_pair_equals_single_view_model():
    """Self-attention over two copies of the same tokens equals attention over one copy, so the mixing model on
    an identical pair is exactly the plain (nvidia/difix-style) model on the view alone: checks the fold."""
    mixing = _model(2)
    plain = DifixRefinerModel(DifixConfig.tiny(reference_mixing=False)).eval()
    plain.load_state_dict(mixing.state_dict())
    image, _, noise = _inputs(5 * M, 7 * M, seed=4)
    pair_noise = torch.cat([noise[:, :1], noise[:, :1]], dim=1)
    got = _run(mixing, image, image, pair_noise)
    want = _run(plain, image, None, noise[:, :1])
    assert torch.allclose(got, want, atol=1e-5)
    assert not torch.allclose(got, _run(plain, image, None, noise[:, 1:]), atol=1e-4)  # noise is used


def test_skip_connections_and_lora_follow_the_official_layout():
    assert skip_channels((128, 256, 512, 512)) == [(512, 512), (256, 512), (128, 512), (128, 256)]
    model = _model(0)
    targets = lora_target_modules(model.vae)
    assert "decoder.skip_conv_1" in targets and "decoder.mid_block.attentions.0.to_out.0" in targets
    assert all("encoder" not in t for t in targets)
    vae = official_state_dicts(model)["vae"]
    assert f"decoder.skip_conv_1.lora_A.{LORA_ADAPTER}.weight" in vae and "decoder.skip_conv_1.base_layer.weight" in vae
    assert "decoder.conv_in.base_layer.bias" in vae and "encoder.conv_in.weight" in vae
    layer = model.lora_layers()["decoder.conv_in"]
    assert layer.scaling == TINY.lora_alpha / TINY.lora_rank


def _pkl_checkpoint(model: DifixRefinerModel, path, rank=None) -> None:
    """The GitHub training checkpoint (``save_ckpt``): full UNet, VAE LoRA + skip entries only."""
    parts = official_state_dicts(model)
    torch.save({"vae_lora_target_modules": lora_target_modules(model.vae), "rank_vae": rank or TINY.lora_rank,
                "state_dict_unet": parts["unet"],
                "state_dict_vae": {k: v for k, v in parts["vae"].items() if "lora" in k or "skip" in k},
                "optimizer": {"state": {}, "param_groups": [{"lr": 2e-5, "betas": (0.9, 0.999), "params": [0]}]}},
               path)


def _sd_turbo_base(model: DifixRefinerModel, directory) -> None:
    """An SD-Turbo-like diffusers directory: plain UNet and VAE names, no skip convs, no LoRA."""
    from safetensors.torch import save_file

    parts = official_state_dicts(model)
    vae = {k.replace(".base_layer.", "."): v for k, v in parts["vae"].items() if "lora" not in k and "skip" not in k}
    for part, sd in (("unet", parts["unet"]), ("vae", vae)):
        (directory / part).mkdir(parents=True)
        save_file({k: v.contiguous() for k, v in sd.items()},
                  str(directory / part / "diffusion_pytorch_model.safetensors"))


def test_weights_round_trip_diffusers_dir_and_training_pkl(tmp_path):
    source = _model(3)
    image, reference, noise = _inputs(4 * M, 4 * M, seed=5)
    want = _run(source, image, reference, noise)
    save_difix_weights(source, tmp_path / "difix")
    assert json.loads((tmp_path / "difix" / "unet" / "config.json").read_text())["cross_attention_dim"] == 8
    fresh = _model(4)
    assert not torch.allclose(_run(fresh, image, reference, noise), want)
    report = load_difix_weights(fresh, tmp_path / "difix")
    assert set(report["files"]) == {"unet/diffusion_pytorch_model.safetensors",
                                    "vae/diffusion_pytorch_model.safetensors"}
    assert torch.equal(_run(fresh, image, reference, noise), want)

    _pkl_checkpoint(source, tmp_path / "model_1000.pkl")
    with pytest.raises(DifixWeightsError, match="base=") as err:
        load_difix_weights(_model(5), tmp_path / "model_1000.pkl")
    assert "model_1000.pkl" in str(err.value) and "missing" in str(err.value)
    _sd_turbo_base(source, tmp_path / "sd-turbo")
    other = _model(6)
    report = load_difix_weights(other, tmp_path / "model_1000.pkl", base=tmp_path / "sd-turbo")
    assert "model_1000.pkl" in report["files"] and "base/vae/diffusion_pytorch_model.safetensors" in report["files"]
    assert torch.equal(_run(other, image, reference, noise), want)


def test_wrong_checkpoints_are_named(tmp_path):
    from safetensors.torch import load_file, save_file

    model = _model(0)
    save_difix_weights(model, tmp_path / "bad")
    vae_file = tmp_path / "bad" / "vae" / "diffusion_pytorch_model.safetensors"
    vae = load_file(str(vae_file))
    vae["decoder.conv_out.base_layer.weight"] = torch.zeros(3, 8, 1, 1)
    del vae["decoder.skip_conv_2.lora_B.vae_skip.weight"]
    save_file(vae, str(vae_file))
    with pytest.raises(DifixWeightsError) as err:
        load_difix_weights(_model(0), tmp_path / "bad")
    msg = str(err.value)
    assert str(tmp_path / "bad") in msg and "vae: missing keys [decoder.skip_conv_2.lora_B.vae_skip.weight]" in msg
    assert "shape mismatch [decoder.conv_out.base_layer.weight: file [3, 8, 1, 1]" in msg and "DifixConfig" in msg
    with pytest.raises(DifixWeightsError, match="not a Difix diffusers directory"):
        load_difix_weights(model, tmp_path)
    with pytest.raises(DifixWeightsError, match="single .safetensors file is not a Difix layout"):
        load_difix_weights(model, vae_file)
    with pytest.raises(DifixWeightsError, match="does not exist"):
        load_difix_weights(model, tmp_path / "nope.pkl")
    _pkl_checkpoint(model, tmp_path / "r8.pkl", rank=8)
    with pytest.raises(DifixWeightsError, match=r"rank_vae is 8.*lora_rank=8"):
        load_difix_weights(model, tmp_path / "r8.pkl")
    torch.save({"state_dict_unet": {}, "code": torch.nn.Identity()}, tmp_path / "pickled.pkl")
    with pytest.raises(DifixWeightsError, match="not a tensor-only torch checkpoint"):
        load_difix_weights(model, tmp_path / "pickled.pkl")


def test_checkpoint_export_needs_a_prompt_embedding(tmp_path):
    """Refused before the (slow) graph export: no text encoder next to the weights, or a wrong-shape embedding."""
    save_difix_weights(_model(0), tmp_path / "difix")
    with pytest.raises(FileNotFoundError, match="no text encoder to embed the prompt 'remove degradation'"):
        export_refiner(tmp_path / "out", TINY, weights=tmp_path / "difix")
    with pytest.raises(ValueError, match=r"shape \(1, 77, 4\), the model needs \(1, 77, 8\)"):
        export_refiner(tmp_path / "out", TINY, weights=tmp_path / "difix", prompt_embeds=np.zeros((1, 77, 4)))
    assert not (tmp_path / "out" / "manifest.json").exists()


def test_onnx_refiner_role(exported):
    refiner = OnnxRefiner(exported, ["CPUExecutionProvider"])
    assert isinstance(refiner, Refiner) and refiner.backend == "onnx"
    rng = np.random.default_rng(0)
    rendered = rng.integers(0, 256, (30, 45, 3), dtype=np.uint8)  # not a multiple of 4: resized and back
    reference = rng.integers(0, 256, (30, 45, 3), dtype=np.uint8)
    assert refiner.working_size(30, 45) == (32, 44) and refiner.working_size(1, 1) == (M, M)
    out = refiner.refine(rendered, reference, seed=1)
    assert out.dtype == np.uint8 and out.shape == rendered.shape
    np.testing.assert_array_equal(out, refiner.refine(rendered, reference, seed=1))  # deterministic
    assert not np.array_equal(out, refiner.refine(rendered, reference, seed=2))  # seeded posterior noise
    np.testing.assert_array_equal(refiner.refine(rendered, None, seed=1), refiner.refine(rendered, rendered, seed=1))
    with pytest.raises(ValueError, match="uint8"):
        refiner.refine(rendered.astype(np.float32), None, seed=0)

    # at a working size the pixels are the torch model's, converted as the official pipeline
    image, guide = rng.integers(0, 256, (2, 8 * M, 6 * M, 3), dtype=np.uint8)
    got = refiner.refine(image, guide, seed=3)
    to_model = lambda a: torch.from_numpy(a.astype(np.float32).transpose(2, 0, 1)[None] / 127.5 - 1)
    noise = np.random.default_rng(3).standard_normal((1, 2, 4, 16, 12), dtype=np.float32)
    want = _run(_model(0), to_model(image), to_model(guide), torch.from_numpy(noise))
    want = np.round(np.clip(want[0].numpy().transpose(1, 2, 0) * 0.5 + 0.5, 0, 1) * 255).astype(np.uint8)
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1
    mean = OnnxRefiner(exported, ["CPUExecutionProvider"], size=(8, 8), sample_posterior=False)
    assert mean.refine(rendered, None, seed=1).shape == rendered.shape
    with pytest.raises(ValueError, match="multiples of 4"):
        OnnxRefiner(exported, ["CPUExecutionProvider"], size=(6, 8))


def test_manifest_kind_and_corruption(exported, tmp_path):
    manifest = onnxio.load_manifest(exported, "refiner")
    assert manifest["architecture"] == "difix" and DifixConfig.from_dict(manifest["config"]) == TINY
    assert manifest["weights"] == {"source": "random", "seed": 0}
    assert manifest["io"]["inputs"] == ["image", "reference", "prompt_embeds", "latent_noise"]
    assert manifest["io"]["size_multiple"] == M and PROMPT_FILE in manifest["files"]
    dims = manifest["graphs"]["refiner"]["dynamic"]
    assert dims["image"][2] and dims["image"][3] and dims["latent_noise"][3]  # dynamic height and width
    with pytest.raises(onnxio.ModelDirError, match="holds a 'refiner' model, expected 'monodepth'"):
        onnxio.load_manifest(exported, "monodepth")
    with pytest.raises(onnxio.ModelDirError, match="export-refiner"):
        OnnxRefiner(tmp_path)
    copy = tmp_path / "copy"
    shutil.copytree(exported, copy)
    m = json.loads((copy / "manifest.json").read_text())
    (copy / "manifest.json").write_text(json.dumps({**m, "architecture": "other"}))
    with pytest.raises(onnxio.ModelDirError, match="expected 'difix'"):
        OnnxRefiner(copy)
    (copy / "manifest.json").write_text(json.dumps(m))
    np.save(copy / PROMPT_FILE, np.zeros((1, 77, 8), np.float32))
    with pytest.raises(onnxio.ModelDirError, match=f"checksum of {PROMPT_FILE}"):
        OnnxRefiner(copy)


def _safetensors_size(shapes: dict[str, tuple[int, ...]]) -> int:
    """Bytes of a safetensors file of these fp32 tensors with metadata {"format": "pt"} (the format's header:
    JSON, tensors sorted by name, padded to 8 bytes)."""
    header, offset = {"__metadata__": {"format": "pt"}}, 0
    for name, shape in sorted(shapes.items()):
        n = 4 * math.prod(shape)
        header[name] = {"dtype": "F32", "shape": list(shape), "data_offsets": [offset, offset + n]}
        offset += n
    text = json.dumps(header, separators=(",", ":")).encode()
    return 8 + len(text) + (-len(text)) % 8 + offset


def test_full_size_layout_matches_official_key_list():
    with torch.device("meta"):
        model = DifixRefinerModel(DifixConfig.sd_turbo())
    mine = official_key_shapes(model)
    committed = read_official_key_list()
    for part in ("unet", "vae"):
        assert list(mine[part].items()) == list(committed[part].items()), part
    assert len(model.lora_layers()) == 43
    # nvidia/difix's published file sizes (unet, vae), reproduced byte-exactly by this layout
    assert _safetensors_size(committed["unet"]) == 3_463_726_504
    assert _safetensors_size(committed["vae"]) == 338_717_612
    assert model._sqrt_abar == pytest.approx(0.8690, abs=1e-4)  # sqrt(alphas_cumprod[199]), scaled-linear


def test_encode_prompt_pads_to_77_tokens(tmp_path):
    """The prompt path with a tiny CLIP text encoder and a letters-only CLIP tokenizer built here."""
    import string

    from transformers import CLIPTextConfig, CLIPTextModel

    chars = list(string.ascii_lowercase)  # byte-level BPE maps ASCII letters to themselves
    vocab = {c: i for i, c in enumerate(chars + [c + "</w>" for c in chars] + ["<|startoftext|>", "<|endoftext|>"])}
    (tmp_path / "tokenizer").mkdir()
    (tmp_path / "tokenizer" / "vocab.json").write_text(json.dumps(vocab))
    (tmp_path / "tokenizer" / "merges.txt").write_text("#version: 0.2\n")
    torch.manual_seed(0)
    text = CLIPTextModel(CLIPTextConfig(vocab_size=len(vocab), hidden_size=8, intermediate_size=16,
                                        num_hidden_layers=1, num_attention_heads=2, max_position_embeddings=77,
                                        eos_token_id=vocab["<|endoftext|>"], bos_token_id=vocab["<|startoftext|>"],
                                        pad_token_id=vocab["<|endoftext|>"])).eval()
    text.save_pretrained(str(tmp_path / "text_encoder"))
    emb = encode_prompt(tmp_path, "remove degradation")
    assert emb.shape == (1, 77, 8) and emb.dtype == np.float32
    ids = [vocab["<|startoftext|>"], *(vocab[c] for c in "remov"), vocab["e</w>"]]
    with torch.no_grad():
        head = text(torch.tensor([ids]))[0].numpy()
    np.testing.assert_allclose(emb[0, : len(ids)], head[0], atol=1e-5)  # causal: the prefix is independent


def test_export_command_needs_a_source(tmp_path):
    from typer.testing import CliRunner

    from navcrafter.flows.cli.models import models_app
    from navcrafter.models.zoo.exporters import export_refiner as export_role

    res = CliRunner().invoke(models_app, ["export-refiner", str(tmp_path / "r")])
    assert res.exit_code == 2 and "--checkpoint" in res.output and "--random" in res.output
    with pytest.raises(ValueError, match="--base and --prompt-embeds go with --checkpoint"):
        export_role(tmp_path / "r", random="tiny", base=tmp_path)
    assert not (tmp_path / "r").exists()


def test_onnx_backend_serves_the_refiner_and_the_refine_step_runs_it(exported, demo_photos, tmp_path, monkeypatch):
    """The onnx backend finds MODEL_DIR/refiner; the refine step accepts the ONNX refiner's output (here on a
    simulation-explored scene, with the simulation's refiner swapped for the exported Difix graph)."""
    import shutil

    import navcrafter.models.simulation.backend as sim_backend
    from navcrafter.schemas.config import RunConfig
    from navcrafter.schemas.layout import REFINE
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.backends import _onnx_backend, onnx_problems
    from navcrafter.tasks.ingest import ingest
    from navcrafter.tasks.runner import run_scene

    models = tmp_path / "models"
    shutil.copytree(exported, models / "refiner")
    onnx = RunConfig.load(preset="tiny", overrides={"backend": "onnx", "model_dir": str(models), "fit.enabled": True,
                                                    "refine.enabled": True})
    assert not any("refiner" in p for p in onnx_problems(onnx))  # the other roles are missing, not this one
    backend = _onnx_backend(str(models.resolve()), onnx.synthesis.model_dump_json())
    out = backend.refiner.refine(np.zeros((24, 32, 3), np.uint8), None, seed=0)
    assert out.shape == (24, 32, 3) and out.dtype == np.uint8

    monkeypatch.setattr(sim_backend, "SimulationRefiner",
                        lambda truth, config: OnnxRefiner(models / "refiner", ["CPUExecutionProvider"]))
    cfg = RunConfig.load(preset="tiny", overrides={"fit.enabled": True, "fit.iterations": 10, "refine.enabled": True,
                                                   "refine.views": 2, "refine.iterations": 5})
    store = str(tmp_path / "store")
    sid = ingest(store, str(demo_photos / "tabletop-0.png"), cfg, "t").scene_id
    run_scene(store, sid, cfg, "t")
    scene = Store(store).scene(sid)
    a, g = scene.status(REFINE).attrs, scene.read_all(REFINE)
    assert a["refiner"] == "onnx" and g["refined"].shape == g["renders"].shape and g["refined"].dtype == np.uint8

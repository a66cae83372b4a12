"""MoGe-2-architecture monodepth: torch network, official checkpoint layout, ONNX export, onnxruntime role.

One tiny random export is shared by the module (exporting dominates the run time).
"""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from navcrafter.models.geometry.moge import (
    MoGe2,
    MoGe2Config,
    MoGeWeightsError,
    load_moge2_weights,
    moge2_state_dict_official,
    official_key_shapes,
    postprocess,
    preprocess_image,
    read_official_key_list,
    save_moge2_weights,
    token_grid,
)
from navcrafter.models.geometry.onnx_monodepth import OnnxMonoDepth
from navcrafter.models.roles import MonoDepth
from navcrafter.models.runtime import onnxio

TINY = MoGe2Config.tiny()


def _model(seed: int = 0) -> MoGe2:
    torch.manual_seed(seed)  # export_monodepth builds its random model the same way
    return MoGe2(TINY).eval()


def _outputs(model: MoGe2, image: torch.Tensor, aspect: torch.Tensor | None = None) -> dict[str, np.ndarray]:
    with torch.no_grad():
        return {k: v.numpy() for k, v in zip(model.output_names, model(image, aspect))}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def exported(tiny_models):
    return tiny_models / "monodepth"  # export_monodepth(out, MoGe2Config.tiny(), seed=0), shared by the session


def test_onnx_matches_torch_at_two_sizes(exported):
    model = _model(0)
    manifest = onnxio.load_manifest(exported, "monodepth")
    runner = onnxio.GraphRunner(exported, manifest, ["CPUExecutionProvider"])
    generator = torch.Generator().manual_seed(1)
    for shape, aspect in [((1, 3, 42, 70), [1.61]), ((2, 3, 84, 56), [0.7, 0.62])]:  # grids 3 x 5 and 6 x 4
        image = torch.rand(shape, generator=generator)
        aspect = torch.tensor(aspect)
        want = _outputs(model, image, aspect)
        got = runner.run("monodepth", {"image": image.numpy(), "aspect_ratio": aspect.numpy()})
        assert sorted(got) == sorted(want) == sorted(["points_raw", "normal_raw", "mask_logits", "metric_scale"])
        for name, value in want.items():
            assert got[name].shape == value.shape, name
            assert np.abs(got[name] - value).max() <= 1e-4, (shape, name)
        rows, cols = shape[2] // 14 * 16, shape[3] // 14 * 16  # the heads' resolution: 16 x the token grid
        assert want["points_raw"].shape == (shape[0], rows, cols, 3)
        assert want["mask_logits"].shape == (shape[0], rows, cols) and want["metric_scale"].shape == (shape[0],)


def test_manifest_round_trip_and_corruption(exported, tmp_path):
    manifest = onnxio.load_manifest(exported, "monodepth")
    assert manifest["architecture"] == "moge-2"
    assert MoGe2Config.from_dict(manifest["config"]) == TINY
    assert manifest["weights"] == {"source": "random", "seed": 0}
    graph = manifest["graphs"]["monodepth"]
    assert graph["inputs"] == ["image", "aspect_ratio"]
    assert graph["outputs"] == ["points_raw", "normal_raw", "mask_logits", "metric_scale"]
    assert graph["dynamic"]["aspect_ratio"][0]
    assert graph["dynamic"]["image"][1] == "" and all(graph["dynamic"]["image"][i] for i in (0, 2, 3))

    broken = tmp_path / "monodepth"
    shutil.copytree(exported, broken)
    data = broken / "monodepth.onnx.data"
    raw = bytearray(data.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    data.write_bytes(bytes(raw))
    with pytest.raises(onnxio.ModelDirError, match="checksum of monodepth.onnx.data"):
        OnnxMonoDepth(broken)
    (broken / "monodepth.onnx.data").unlink()
    with pytest.raises(onnxio.ModelDirError, match="missing"):
        OnnxMonoDepth(broken)


def test_onnx_monodepth_role(exported):
    depth = OnnxMonoDepth(exported, providers=["CPUExecutionProvider"])
    assert isinstance(depth, MonoDepth) and depth.backend == "onnx"
    image = np.random.default_rng(0).integers(0, 256, (45, 61, 3), dtype=np.uint8)  # not multiples of 14
    pred = depth.predict(image, seed=0)
    assert pred.inv_depth.shape == (45, 61) and pred.inv_depth.dtype == np.float32
    assert pred.sky.shape == (45, 61) and pred.sky.dtype == np.bool_
    assert np.isfinite(pred.inv_depth).all() and (pred.inv_depth >= 0).all()
    assert (pred.inv_depth[pred.sky] == 0).all() and (pred.inv_depth[~pred.sky] > 0).all()


def test_weights_round_trip_safetensors_and_pt(tmp_path):
    source, target = _model(1), _model(2)
    image = torch.rand(1, 3, 42, 56, generator=torch.Generator().manual_seed(3))
    path = save_moge2_weights(source, tmp_path / "moge.safetensors")
    load_moge2_weights(target, path)
    want, got = _outputs(source, image), _outputs(target, image)
    assert all(np.array_equal(want[k], got[k]) for k in want)
    official = moge2_state_dict_official(source)
    back = moge2_state_dict_official(target)
    assert list(back) == list(official) and all(torch.equal(back[k], official[k]) for k in official)

    # the official .pt format: {"model_config", "model"} (read with weights_only=True); buffers may be absent
    pt = tmp_path / "model.pt"
    state = {k: v for k, v in official.items() if k not in ("encoder.image_mean", "encoder.image_std")}
    torch.save({"model_config": TINY.to_official(), "model": state}, pt)
    fresh = load_moge2_weights(_model(4), pt)
    got = _outputs(fresh, image)
    assert all(np.array_equal(want[k], got[k]) for k in want)
    other = MoGe2Config.tiny().to_official()
    other["remap_output"] = "linear"
    torch.save({"model_config": other, "model": state}, pt)
    with pytest.raises(MoGeWeightsError, match="remap_output"):
        load_moge2_weights(_model(4), pt)


def test_wrong_checkpoint_is_named(tmp_path):
    from safetensors.torch import save_file

    state = moge2_state_dict_official(_model(1))
    state["neck.input_blocks.1.weight"] = torch.zeros(3, 2, 1, 1)
    del state["scale_head.0.bias"]
    state["head.extra"] = torch.zeros(1)
    path = tmp_path / "bad.safetensors"
    save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    with pytest.raises(MoGeWeightsError) as err:
        load_moge2_weights(_model(0), path)
    message = str(err.value)
    assert "bad.safetensors" in message
    assert "shape mismatch [neck.input_blocks.1.weight: file [3, 2, 1, 1] vs model [16, 2, 1, 1]]" in message
    assert "missing keys [scale_head.0.bias]" in message and "unexpected keys [head.extra]" in message


def test_full_size_layout_matches_official_key_list():
    with torch.device("meta"):
        model = MoGe2(MoGe2Config.vitl_normal())
    official = read_official_key_list()
    assert len(official) == 521
    assert list(official_key_shapes(model).items()) == list(official.items())
    assert MoGe2Config.from_official(MoGe2Config.vitl_normal().to_official()) == MoGe2Config.vitl_normal()


def test_position_embedding_is_dinov2_bicubic_with_offset():
    encoder = _model(0).encoder
    pos = encoder.backbone.embeddings.position_embeddings.detach()
    m, dim = TINY.pos_grid, pos.shape[-1]
    grid = pos[:, 1:].reshape(1, m, m, dim).permute(0, 3, 1, 2)
    for h, w in [(3, 5), (6, 4), (9, 7)]:
        want = F.interpolate(grid, scale_factor=((h + 0.1) / m, (w + 0.1) / m), mode="bicubic")
        want = torch.cat([pos[:, :1], want.permute(0, 2, 3, 1).reshape(1, h * w, dim)], dim=1)
        assert torch.allclose(encoder.position_embedding(h, w, pos), want, atol=1e-6)
    assert torch.allclose(encoder.position_embedding(m, m, pos), pos, atol=1e-6)  # as is at the pretraining grid


def test_preprocess_token_grid_and_antialiased_resize():
    assert token_grid(480, 640, 3600) == (52, 69) and token_grid(1000, 500, 1200) == (49, 24)
    image = np.random.default_rng(1).integers(0, 256, (97, 131, 3), dtype=np.uint8)
    x = preprocess_image(image, num_tokens=30)
    rows, cols = token_grid(97, 131, 30)
    assert x.shape == (1, 3, rows * 14, cols * 14) and x.dtype == np.float32
    ref = F.interpolate(torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255, (rows * 14, cols * 14),
                        mode="bilinear", align_corners=False, antialias=True)
    assert np.abs(x - ref.numpy()).max() < 1e-4


def test_postprocess_recovers_shift_scale_and_masks():
    height, width, focal, shift, scale = 40, 60, 1.3, 0.7, 2.5  # focal relative to half the diagonal
    rng = np.random.default_rng(2)
    z = rng.uniform(2.0, 4.0, (height, width)).astype(np.float32)
    diagonal = math.hypot(width, height)
    u = (2 * np.arange(width) + 1 - width) / diagonal
    v = (2 * np.arange(height) + 1 - height) / diagonal
    uu, vv = np.meshgrid(u, v, indexing="xy")
    points = np.stack([uu * z / focal, vv * z / focal, z - shift], axis=-1).astype(np.float32)
    mask = np.full((height, width), 0.9, np.float32)
    mask[:5] = 0.1  # sky
    points[10, 10] = np.nan
    result = postprocess(points, mask, scale, size=(height, width))
    assert result.valid.sum() == height * width - 5 * width - 1
    assert not result.valid[:5].any() and not result.valid[10, 10]
    assert np.allclose(result.depth[result.valid], (z * scale)[result.valid], rtol=1e-3)
    assert np.isinf(result.depth[~result.valid]).all() and (result.inv_depth[~result.valid] == 0).all()
    assert np.allclose(result.inv_depth[result.valid], 1 / (z * scale)[result.valid], rtol=1e-3)
    fx = focal / 2 * math.hypot(width, height) / width
    assert abs(result.intrinsics[0, 0] - fx) < 1e-3 * fx
    with pytest.raises(ValueError, match="head_maps_to_size"):  # maps are never resized after the remaps
        postprocess(points, mask, scale, size=(80, 120))


def test_uv_channels_use_the_original_aspect_ratio():
    """The aspect ratio input reaches the heads (the UV channels' exact values against the official
    ``normalized_view_plane_uv`` are covered end to end by test_moge_official.py)."""
    model = _model(0)
    image = torch.rand(1, 3, 42, 70, generator=torch.Generator().manual_seed(5))
    grid, original = _outputs(model, image), _outputs(model, image, torch.tensor([1.61]))
    assert np.abs(grid["points_raw"] - original["points_raw"]).max() > 1e-4  # the aspect reaches the heads
    same = _outputs(model, image, torch.tensor([70 / 42]))  # the grid's own aspect is the default
    assert all(np.allclose(same[k], grid[k], atol=1e-6) for k in grid)


def test_head_maps_are_resized_once_then_remapped():
    from navcrafter.models.geometry.moge import head_maps_to_size

    rng = np.random.default_rng(4)
    raw, logits, normal = (rng.normal(size=s).astype(np.float32) for s in [(48, 80, 3), (48, 80), (48, 80, 3)])
    points, mask, unit = head_maps_to_size(raw, logits, normal, size=(45, 61), remap_output="exp")
    want = F.interpolate(torch.from_numpy(np.concatenate([raw, logits[..., None], normal], -1)).permute(2, 0, 1)[None],
                         (45, 61), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
    z = want[..., 2:3].exp()
    remapped = torch.cat([want[..., :2] * z, z], -1).numpy()
    assert np.abs(points - remapped).max() < 1e-6 * np.abs(remapped).max()
    assert np.abs(mask - want[..., 3].sigmoid().numpy()).max() < 1e-6
    assert np.abs(unit - F.normalize(want[..., 4:], dim=-1).numpy()).max() < 1e-6
    assert points.dtype == mask.dtype == unit.dtype == np.float32 and mask.shape == (45, 61)

"""The clip store of camera-control training on tiny simulated RealEstate10K and DL3DV datasets: plan, splits,
precompute (shapes, cameras, render conditioning, extra reference), resume, and the clear errors."""

from __future__ import annotations

import dataclasses
import re
import shutil

import numpy as np
import pytest
import zarr

from navcrafter.models.camera.cameras import project, unproject_depth
from navcrafter.models.simulation.datasets import depth_path, write_dataset
from navcrafter.models.synthesis.encoders import PixelShuffleEncoders
from navcrafter.models.synthesis.pipeline import _to_video
from navcrafter.schemas.datasets import open_dataset
from navcrafter.schemas.training import (
    CLIP_ARRAYS,
    CLIP_ATTRS,
    CLIP_REQUIRED,
    CameraTrainingConfig,
    DataSource,
    TrainingDataConfig,
)
from navcrafter.tasks.training.clips import (
    ClipDataset,
    ClipStoreError,
    plan_clips,
    precompute_clip,
    resize_center_crop_depth,
)

T, RES = 5, 32


class CountingEncoders(PixelShuffleEncoders):
    """The pixel-shuffle stand-in, counting its encode_video calls."""

    def __init__(self) -> None:
        super().__init__(4, image_dim=4, text_dim=8)
        self.calls = 0

    def encode_video(self, video):
        self.calls += 1
        return super().encode_video(video)


def make_config(sources, **data) -> CameraTrainingConfig:
    fields = {"sources": tuple(sources), "num_frames": T, "resolution": RES, "clips_per_source": 4,
              "validation_clips": 2, **data}
    return CameraTrainingConfig(random_base="tiny", seed=3, data=TrainingDataConfig(**fields))


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim")
    write_dataset(root / "re", "re10k", sequences=3, frames=12, resolution=RES, seed=0)
    write_dataset(root / "dl", "dl3dv", sequences=3, frames=12, resolution=(RES, 48), seed=1)  # cropped to 32²
    return root, [DataSource(kind="re10k", root=str(root / "re")), DataSource(kind="dl3dv", root=str(root / "dl"))]


@pytest.fixture(scope="module")
def store(datasets, tmp_path_factory):
    _, sources = datasets
    config = make_config(sources)
    refs = plan_clips(config)
    path = tmp_path_factory.mktemp("run") / "clips.zarr"
    enc = CountingEncoders()
    for ref in refs:
        assert precompute_clip(path, ref, enc, config) == ref.clip_id
    return path, refs, config, enc.calls


def test_plan_ids_and_splits(datasets):
    _, sources = datasets
    config = make_config(sources)
    refs = plan_clips(config)
    assert refs == plan_clips(config)  # deterministic
    ids = [r.clip_id for r in refs]
    assert len(set(ids)) == len(ids) and all(re.fullmatch(r"[A-Za-z0-9._-]+", i) for i in ids)
    assert {r.kind for r in refs} == {"re10k", "dl3dv"}
    val = [r for r in refs if r.split == "validation"]
    assert len(val) == 2
    # the held-out clips come from the last sequences (last source, last names) and no sequence is in both splits
    assert {(r.source_index, r.sequence) for r in val} == {(1, "sim-00002-tabletop-pan")}
    train_seqs = {(r.source_index, r.sequence) for r in refs if r.split == "train"}
    assert not train_seqs & {(r.source_index, r.sequence) for r in val}
    assert all(r.num_frames == T and r.resolution == RES for r in refs)
    assert all(r.start + (T - 1) * r.stride < 12 for r in refs)
    with pytest.raises(ValueError, match="holds out every clip"):
        plan_clips(make_config(sources[:1], clips_per_source=None, validation_clips=3))
    with pytest.raises(ValueError, match="data.sources is empty"):
        plan_clips(make_config([]))


def test_precompute_writes_complete_groups(store, datasets):
    path, refs, config, _ = store
    ds = ClipDataset(path)
    assert len(ds) == len(refs) and ds.ids == sorted(r.clip_id for r in refs)
    assert len(ClipDataset(path, "validation")) == 2 and len(ClipDataset(path, "train")) == len(refs) - 2
    null = zarr.open_group(str(path), mode="r")["null_text_embeds"][...]
    assert null.shape == (512, 8) and not null.any()
    by_id = {r.clip_id: r for r in refs}
    with_ref = 0
    for i in range(len(ds)):
        clip = ds[i]
        a, ref = clip["attrs"], by_id[ds.ids[i]]
        assert all(k in a for k in CLIP_ATTRS) and a["done"] is True and a["split"] == ref.split
        assert (a["num_frames"], a["height"], a["width"], a["start"]) == (T, RES, RES, ref.start)
        for name in CLIP_REQUIRED + ("render_latents", "visibility"):
            assert clip[name].dtype == np.dtype(CLIP_ARRAYS[name][0]), name
        for name in ("latents", "image_latents", "render_latents"):
            assert clip[name].shape == (48, T, RES // 4, RES // 4)
        assert clip["image_embeds"].shape == (16, 4) and clip["text_embeds"].shape == (512, 8)
        assert clip["c2w"].shape == (T, 4, 4) and clip["K"].shape == (T, 3, 3)
        np.testing.assert_allclose(clip["c2w"][0], np.eye(4), atol=1e-12)
        assert clip["visibility"].shape == (T, RES, RES) and set(np.unique(clip["visibility"])) <= {0, 1}

        # the latents are the reader's frames, exactly (the stand-in is invertible)
        opts = {"split": None} if ref.kind == "re10k" else {}
        reader = open_dataset(ref.kind, ref.root, num_frames=T - 1, resolution=RES, **opts)
        sample = reader.clip(ref.sequence, ref.start)
        enc = PixelShuffleEncoders(4, image_dim=4, text_dim=8)
        video = _to_video(sample.images)
        np.testing.assert_array_equal(enc.decode_video(clip["latents"]), video)
        cond = enc.decode_video(clip["image_latents"])
        np.testing.assert_array_equal(cond[:, 0], video[:, 0])
        assert not cond[:, 1:].any()
        np.testing.assert_allclose(clip["c2w"], sample.relative_c2w(), atol=1e-12)
        np.testing.assert_allclose(clip["K"], sample.K)
        # frame 0's points rendered into frame 0 cover every pixel with depth, each showing the colour of the
        # nearest point whose splat (render_points' max_radius: 3 px) covers it: a pixel of its 7x7 neighbourhood
        renders = np.round((enc.decode_video(clip["render_latents"]) + 1) * 127.5).astype(np.uint8)
        seen = clip["visibility"][0].astype(bool)
        depth0 = resize_center_crop_depth(np.load(depth_path(sample.paths[0])), RES, RES)
        assert seen[depth0 > 0].all() and (seen == (depth0 > 0)).mean() > 0.95
        img = np.pad(sample.images[0].astype(int), ((3, 3), (3, 3), (0, 0)), constant_values=-1)
        r0 = renders[:, 0].transpose(1, 2, 0).astype(int)
        hits = [(r0 == img[dy:dy + RES, dx:dx + RES]).all(-1) for dy in range(7) for dx in range(7)]
        assert np.any(hits, axis=0)[seen].all()
        assert not renders[:, ~clip["visibility"].astype(bool)].any()  # black where nothing is rendered

        if ref.start > 0:  # the extra reference frame, 1..2T frames before the clip, in frame 0's camera frame
            with_ref += 1
            k = a["reference_index"]
            assert ref.start - 2 * T <= k < ref.start
            assert clip["reference_latents"].shape == (48, 1, RES // 4, RES // 4)
            info = reader.sequence(ref.sequence)
            np.testing.assert_allclose(clip["reference_c2w"], np.linalg.inv(info.c2w[ref.start]) @ info.c2w[k],
                                       atol=1e-9)
            one = open_dataset(ref.kind, ref.root, num_frames=1, resolution=RES, **opts).clip(ref.sequence, k)
            np.testing.assert_array_equal(enc.decode_video(clip["reference_latents"])[:, 0],
                                          _to_video(one.image[None])[:, 0])
        else:
            assert "reference_latents" not in clip and a["reference_index"] is None
    assert with_ref > 0


def test_cropped_depth_lifts_onto_the_later_frames(datasets):
    """DL3DV frames are 48x32 and cropped to 32²: the depth, cropped the same way, lifts with the clip's K to
    points whose depth in a later frame is that frame's depth."""
    root, _ = datasets
    reader = open_dataset("dl3dv", root / "dl", num_frames=T - 1, resolution=RES)
    sample = reader.clip("sim-00000-room-orbit", 2)
    depths = [resize_center_crop_depth(np.load(depth_path(p)), RES, RES) for p in sample.paths]
    assert np.load(depth_path(sample.paths[0])).shape == (RES, 48)
    c2w = sample.relative_c2w()
    pts, _ = unproject_depth(depths[0], c2w[0], sample.K[0])
    uv, z = project(pts, c2w[-1], sample.K[-1])
    j, i = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (z > 0) & (i >= 0) & (i < RES) & (j >= 0) & (j < RES)
    rel = np.abs(depths[-1][i[ok], j[ok]] - z[ok]) / z[ok]
    assert ok.mean() > 0.3 and np.median(rel) < 0.03
    # at the native size the crop is the identity
    d = np.random.default_rng(0).uniform(1, 2, (6, 8)).astype(np.float32)
    np.testing.assert_array_equal(resize_center_crop_depth(d, 6, 8), d)


def test_resume_skips_done_and_redoes_partial(store, tmp_path):
    path, refs, config, calls = store
    copy = tmp_path / "clips.zarr"
    shutil.copytree(path, copy)
    enc = CountingEncoders()
    for ref in refs:
        precompute_clip(copy, ref, enc, config)
    assert enc.calls == 0  # every group complete: nothing recomputed

    victim = refs[1]
    before = ClipDataset(copy)[ClipDataset(copy).ids.index(victim.clip_id)]
    g = zarr.open_group(str(copy), mode="r+")[f"clips/{victim.clip_id}"]
    g.update_attributes({"done": False})  # a run killed while writing this group
    del g["latents"]
    assert victim.clip_id not in ClipDataset(copy).ids  # partial groups are not listed
    for ref in refs:
        precompute_clip(copy, ref, enc, config)
    assert 0 < enc.calls <= calls // len(refs) + 1  # only that clip was computed again
    after = ClipDataset(copy)[ClipDataset(copy).ids.index(victim.clip_id)]
    for name in CLIP_ARRAYS:
        if name in before:
            np.testing.assert_array_equal(after[name], before[name])

    with pytest.raises(ClipStoreError, match="other settings"):
        precompute_clip(copy, dataclasses.replace(victim, split="validation"), enc, config)
    with pytest.raises(ClipStoreError, match="encoders"):
        precompute_clip(copy, victim, PixelShuffleEncoders(2, image_dim=4, text_dim=8), config)


def test_missing_depth_is_a_clear_error(tmp_path):
    write_dataset(tmp_path / "re", "re10k", sequences=1, frames=T, resolution=16, seed=0, depth=False)
    sources = [DataSource(kind="re10k", root=str(tmp_path / "re"))]
    config = make_config(sources, resolution=16, clips_per_source=None, validation_clips=0)
    (ref,) = plan_clips(config)
    enc = PixelShuffleEncoders(4, image_dim=4, text_dim=8)
    with pytest.raises(FileNotFoundError, match=r"0\.depth\.npy does not exist.*data\.render_condition=false"):
        precompute_clip(tmp_path / "clips.zarr", ref, enc, config)
    assert len(ClipDataset(tmp_path / "clips.zarr")) == 0
    no_render = make_config(sources, resolution=16, clips_per_source=None, validation_clips=0,
                            render_condition=False)
    precompute_clip(tmp_path / "clips.zarr", ref, enc, no_render)
    (clip,) = [ClipDataset(tmp_path / "clips.zarr")[0]]
    assert "render_latents" not in clip and "visibility" not in clip and clip["latents"].shape == (48, T, 4, 4)
    with pytest.raises(FileNotFoundError, match="no clip store"):
        ClipDataset(tmp_path / "nowhere.zarr")

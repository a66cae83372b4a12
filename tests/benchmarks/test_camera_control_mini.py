"""The measurements of benchmarks/camera_control_mini.py (direction accuracy, the pixel-alignment camera estimator
and Table III's per-frame errors) on true renders of one small scene: each can fail."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def mini():
    from benchmarks import camera_control_mini

    return camera_control_mini


@pytest.fixture(scope="module")
def held(mini, monkeypatch_module):
    from navcrafter.models.synthesis.encoders import PixelShuffleEncoders

    monkeypatch_module.setattr(mini, "GRID", 6)  # a coarse estimator grid keeps the test fast
    enc = PixelShuffleEncoders(4, temporal=4, image_dim=8, text_dim=16, image_tokens=16)
    return mini.build_scenes(("street",), [3], 5, 16, enc, grid=True, seed=0)


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


def _mirror(entry, clip):
    return next(m for m in entry["clips"] if m["family"] == clip["family"] and m["amplitude"] == -clip["amplitude"])


def test_paths_mirror_and_start_at_the_first_camera(mini, held):
    e = held[0]
    assert len(e["clips"]) == 2 * len(mini.FAMILIES)
    for c in e["clips"]:
        np.testing.assert_allclose(c["poses"][0], e["scene"].c2w0, atol=1e-12)
        m = _mirror(e, c)
        assert not np.allclose(c["poses"][-1], m["poses"][-1])
        assert np.array_equal(c["truth"][0], m["truth"][0])  # the same first frame: direction is not in it
    pan = next(c for c in e["clips"] if c["family"] == "pan" and c["amplitude"] > 0)
    r, t = mini.pose_errors_per_frame(pan["poses"], _mirror(e, pan)["poses"])
    np.testing.assert_allclose(r[-1], 2 * pan["amplitude"], rtol=1e-9)  # mirror: twice the angle apart
    np.testing.assert_allclose(t, 0.0, atol=1e-9)  # a pan does not move the centre


@pytest.fixture(scope="module")
def room(mini):
    """Development room 0 (the one whose first camera stands 0.76 m before the back wall), 5 frames at 16²."""
    from navcrafter.models.synthesis.encoders import PixelShuffleEncoders

    enc = PixelShuffleEncoders(4, temporal=4, image_dim=8, text_dim=16, image_tokens=16)
    return mini.build_scenes(("room",), [0], 5, 16, enc, grid=False, seed=0)[0]


def test_dollies_are_collision_free_mirrored_and_longer_than_along_the_view_axis(mini, room):
    """Issue 32: a dolly and its mirror image have the same amplitude along one axis (the path negated), keep
    CLEARANCE from every surface, point into the picture, and reach further than the view-axis dolly of
    SCENES_VERSION 1 (0.07-0.11 L in the rooms: the back wall 0.5-0.8 m behind the first camera)."""
    sc = room["scene"]
    c2w0, axis = sc.c2w0, sc.dolly_axis
    np.testing.assert_allclose(np.linalg.norm(axis), 1.0, atol=1e-12)
    local = c2w0[:3, :3].T @ axis
    half = np.deg2rad(sc.sim.camera_fov_x_deg) / 2
    assert local[2] > 0 and abs(np.arctan2(local[0], local[2])) <= mini.DOLLY_CONE * half + 1e-9  # in the picture
    fwd = next(c for c in room["clips"] if c["family"] == "dolly" and c["amplitude"] > 0)
    back = next(c for c in room["clips"] if c["family"] == "dolly" and c["amplitude"] < 0)
    assert back["amplitude"] == -fwd["amplitude"]
    np.testing.assert_allclose(fwd["poses"][:, :3, 3] - c2w0[:3, 3], -(back["poses"][:, :3, 3] - c2w0[:3, 3]),
                               atol=1e-12)
    np.testing.assert_allclose(fwd["poses"][:, :3, :3], np.broadcast_to(c2w0[:3, :3], (5, 3, 3)))  # no turn
    np.testing.assert_allclose(np.cross(fwd["poses"][-1, :3, 3] - c2w0[:3, 3], axis), 0.0, atol=1e-12)
    for fam in mini.FAMILIES:  # every path of the room, both directions, densely sampled, keeps CLEARANCE
        for c in room["clips"]:
            if c["family"] == fam:
                dense = mini.path_poses(fam, c["amplitude"], 40, c2w0, sc.L, axis)[:, :3, 3]
                assert np.all(sc.sim.distance(dense) >= mini.CLEARANCE), c["id"]
    # the view-axis dolly (version 1) of the same amplitude is not collision-free both ways: the back wall
    view = [mini.path_poses("dolly", s * fwd["amplitude"], 40, c2w0, sc.L, c2w0[:3, 2])[:, :3, 3] for s in (1, -1)]
    assert np.any(sc.sim.distance(np.concatenate(view)) < mini.CLEARANCE)
    assert fwd["amplitude"] * sc.L > 0.5  # metres


def test_mirror_pairs_tell_identical_directions_from_mirrored_ones(mini, held):
    pairs = mini.mirror_pairs(held)
    assert set(pairs) == set(mini.FAMILIES)
    for v in pairs.values():
        assert v["mirror_psnr"] < mini.PSNR_CAP and v["amplitude"][0] > 0
    same = [dict(held[0], clips=[dict(c, truth=next(m for m in held[0]["clips"] if m["family"] == c["family"]
                                                     and m["amplitude"] > 0)["truth"]) for c in held[0]["clips"]])]
    assert all(v["mirror_psnr"] == mini.PSNR_CAP for v in mini.mirror_pairs(same).values())


def test_direction_accuracy_truth_is_one_mirror_is_zero(mini, held):
    e = held[0]
    truth = [c["truth"] for c in e["clips"]]
    mirrored = [_mirror(e, c)["truth"] for c in e["clips"]]
    assert mini.measure(truth, held)["direction_accuracy"] == 1.0
    assert mini.measure(mirrored, held)["direction_accuracy"] == 0.0
    v = e["clips"][0]["truth"]
    assert mini.direction_correct(v, v, v) == 0.5  # a tie counts one half


def test_estimator_recovers_true_cameras_and_punishes_mirrored_ones(mini, held):
    e = held[0]
    truth = mini.measure([c["truth"] for c in e["clips"]], held)
    mirrored = mini.measure([_mirror(e, c)["truth"] for c in e["clips"]], held)
    # the truth is found to within the grid's step (1.25 x 35 deg / 6 for pans); the mirror is far off
    assert truth["r_err"] < 4.0
    assert mirrored["r_err"] > 3 * truth["r_err"]
    assert mirrored["t_err"] > truth["t_err"]
    assert truth["psnr"] == mini.PSNR_CAP and truth["ssim"] == pytest.approx(1.0)


def test_estimate_cameras_picks_the_nearest_candidate(mini):
    rng = np.random.default_rng(0)
    cands = rng.integers(0, 256, (5, 4, 4, 3), dtype=np.uint8)
    poses = np.stack([np.eye(4) * (i + 1) for i in range(5)])
    video = cands[[3, 0, 4]].astype(np.int16) + rng.integers(-3, 4, (3, 4, 4, 3))
    est = mini.estimate_cameras(np.clip(video, 0, 255).astype(np.uint8), cands, poses)
    np.testing.assert_array_equal(est, poses[[3, 0, 4]])


def test_pose_errors_per_frame_and_bad_input(mini):
    z = np.array([0.0, 0.0, 1.0])
    req = np.stack([mini.family_pose("pan", a, np.eye(4), 1.0, z) for a in (0.0, 10.0, 20.0)])
    est = np.stack([mini.family_pose("pan", a, np.eye(4), 1.0, z) for a in (0.0, 12.0, 15.0)])
    r, t = mini.pose_errors_per_frame(est, req)
    np.testing.assert_allclose(r, [2.0, 5.0], atol=1e-9)
    dolly = np.stack([mini.family_pose("dolly", a, np.eye(4), 2.0, z) for a in (0.0, 0.5)])
    _, t = mini.pose_errors_per_frame(dolly, dolly[[0, 0]], scale=2.0)
    np.testing.assert_allclose(t, [0.5])
    with pytest.raises(ValueError, match="equal shape"):
        mini.pose_errors_per_frame(est, req[:2])
    with pytest.raises(ValueError, match="unknown path family"):
        mini.family_pose("zoom", 1.0, np.eye(4), 1.0, z)


def test_cosine_trainer_warms_up_then_decays_to_zero_without_touching_the_product(mini):
    import argparse

    from navcrafter.models.synthesis.camcontrol import build_camera_wan
    from navcrafter.models.synthesis.training import CameraTrainer

    args = argparse.Namespace(heads=2, head_dim=8, layers=1, ffn=16, adapter_channels=4, reference_frames=1)
    base, control = mini.model_configs(args, 4)
    model = build_camera_wan(base, control, seed=0)
    cfg = mini.training_config(stage="control", steps=100, lr=1e-3, seed=0, frames=5, resolution=16, warmup=10)
    tr = mini.cosine_trainer(model, [{}], cfg)
    assert tr.lr_at(0) == pytest.approx(1e-4)  # warmup: (0 + 1) / 10 of the peak
    assert tr.lr_at(50) == pytest.approx(0.5e-3)  # half way down the cosine
    assert tr.lr_at(100) == pytest.approx(0.0, abs=1e-12)
    assert CameraTrainer(model, [{}], cfg).lr_at(100) == pytest.approx(1e-3)  # the product's schedule: constant
    assert control.num_reference_frames == 1
    assert mini.turn_frames(9) == [0, 2, 4, 6, 8] and mini.turn_frames(17) == [0, 4, 8, 12, 16]


def test_texture_scale_enlarges_every_material_and_keeps_the_scene(mini):
    plain, coarse = mini.make_scene("room", 3, 16, 1.0), mini.make_scene("room", 3, 16, 4.0)
    assert [m.scale * 4.0 for m in plain.sim.materials] == pytest.approx([m.scale for m in coarse.sim.materials])
    assert [m.color_a for m in plain.sim.materials] == [m.color_a for m in coarse.sim.materials]
    np.testing.assert_array_equal(plain.c2w0, coarse.c2w0)
    assert plain.L == coarse.L
    assert not np.array_equal(mini.render_rgb(plain, plain.c2w0), mini.render_rgb(coarse, coarse.c2w0))
    with pytest.raises(ValueError, match="texture_scale must be positive"):
        mini.make_scene("room", 3, 16, 0.0)


def test_camera_guidance_extrapolates_from_the_camera_free_base(mini):
    import torch

    class Const(torch.nn.Module):
        def __init__(self, value):
            super().__init__()
            self.value, self.calls = value, []

        def forward(self, hidden, ts, text, image, plucker, cond, lora, **kw):
            self.calls.append(plucker)
            return torch.full_like(hidden, self.value)

    model, base = Const(2.0), Const(0.5)
    x, cam = torch.zeros(1, 3), torch.ones(1)
    out = mini.CameraGuided(model, base, 3.0)(x, None, None, None, cam, None, 1.0)
    torch.testing.assert_close(out, torch.full_like(x, 0.5 + 3.0 * (2.0 - 0.5)))
    assert base.calls == [None]  # the unconditional branch sees no cameras
    torch.testing.assert_close(mini.CameraGuided(model, base, 1.0)(x, None, None, None, cam, None, 1.0),
                               torch.full_like(x, 2.0))  # w = 1: the model alone
    with pytest.raises(ValueError, match="needs the frozen base"):
        mini.sample_videos(model, [], None, plucker_from=None, steps=1, lora=1.0, shift=3.0, seed=0, device="cpu",
                           camera_guidance=2.0)


def test_mirrored_cameras_turn_the_other_way(mini):
    # a level camera (OpenCV axes: x right, y down = world -z, z forward = world +y): mirroring a pan or an
    # orbit gives the opposite one; a tilt and a dolly along the view axis are unchanged (a slanted dolly's axis
    # is mirrored with the world); every rotation stays proper
    c2w0 = np.eye(4)
    c2w0[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    c2w0[:3, 3] = [0.3, -1.0, 1.5]

    def rel(p):
        return np.linalg.inv(p[0]) @ p

    for fam, a in (("pan", 30.0), ("orbit", 25.0), ("tilt", 12.0), ("dolly", 0.3)):
        fwd = mini.path_poses(fam, a, 5, c2w0, 2.0, c2w0[:3, 2])
        back = mini.path_poses(fam, -a, 5, c2w0, 2.0, c2w0[:3, 2])
        m = mini.mirror_relative_poses(fwd)
        np.testing.assert_allclose(np.linalg.det(m[:, :3, :3]), 1.0, atol=1e-12)
        expected = rel(back) if fam in ("pan", "orbit") else rel(fwd)
        np.testing.assert_allclose(m, expected, atol=1e-12)
        if fam in ("pan", "orbit"):
            assert not np.allclose(m, rel(fwd), atol=1e-3)


def test_condition_all_gives_frame_0_to_every_latent_frame(mini, held):
    from navcrafter.models.synthesis.encoders import PixelShuffleEncoders

    enc = PixelShuffleEncoders(4, temporal=4, image_dim=8, text_dim=16, image_tokens=16)
    c, K = held[0]["clips"][0], held[0]["scene"].K.K
    first = mini.make_clip(enc, c["truth"], c["poses"], K, "x", "first")["image_latents"]
    every = mini.make_clip(enc, c["truth"], c["poses"], K, "x", "all")["image_latents"]
    np.testing.assert_array_equal(first[:, 0], every[:, 0])
    assert not first[:, 1:].any()  # Wan's I2V condition: frame 0, then zeros
    for f in range(1, every.shape[1]):  # a still video of frame 0: every latent frame is latent frame 0
        np.testing.assert_array_equal(every[:, f], every[:, 0])
    with pytest.raises(ValueError, match="condition"):
        mini.make_clip(enc, c["truth"], c["poses"], K, "x", "middle")


def test_saved_models_load_bit_for_bit_and_only_with_the_same_training_settings(mini, tmp_path):
    import argparse

    import torch

    from navcrafter.models.synthesis.camcontrol import build_camera_wan

    args = argparse.Namespace(heads=2, head_dim=8, layers=1, ffn=16, adapter_channels=4, reference_frames=1,
                              seed=10, resolution=16, frames=5, lr=1e-3, warmup=10, batch=1, control_batch=1,
                              condition="first", flip=False, texture_scale=4.0, autoencoder="pca", latent_channels=4)
    size = {"train_scenes": 2, "base_steps": 3, "control_steps": 2}
    base_cfg, control_cfg = mini.model_configs(args, 4)
    model, base = build_camera_wan(base_cfg, control_cfg, seed=0), build_camera_wan(base_cfg, control_cfg, seed=1)
    sig = mini.training_signature(args, size)
    path = tmp_path / "m.safetensors"
    mini.save_models(path, model, base, sig, {"base_final_loss": 0.5})
    m2, b2 = build_camera_wan(base_cfg, control_cfg, seed=2), build_camera_wan(base_cfg, control_cfg, seed=3)
    assert mini.load_models(path, m2, b2, sig) == {"base_final_loss": 0.5}
    for a, b in ((model, m2), (base, b2)):
        for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items()):
            assert ka == kb and torch.equal(va, vb)
    assert any(not torch.equal(va, vb) for va, vb in zip(model.state_dict().values(), base.state_dict().values()))
    with pytest.raises(ValueError, match="base_steps"):
        mini.load_models(path, m2, b2, mini.training_signature(args, {**size, "base_steps": 4}))
    # the development option --base-flow-shift: in the base stage's config and, when set, in the signature
    assert mini.training_config(stage="base", steps=1, lr=1e-3, seed=0, frames=5, resolution=16,
                                flow_shift=1.5).flow_shift == 1.5
    assert "base_flow_shift" not in sig
    shifted = argparse.Namespace(**vars(args), base_flow_shift=1.5)
    assert mini.training_signature(shifted, size) == {**sig, "base_flow_shift": 1.5}
    with pytest.raises(ValueError, match="base_flow_shift"):
        mini.load_models(path, m2, b2, mini.training_signature(shifted, size))
    # --patch: in the model's config and always in the signature; a file saved before the option (no "patch" in its
    # signature) was trained with Wan's 2x2 patch and loads only at --patch 2
    assert sig["patch"] == mini.PATCH == 1 and base_cfg["patch_size"] == (1, 1, 1)
    wan = argparse.Namespace(**vars(args), patch=2)
    assert mini.model_configs(wan, 4)[0]["patch_size"] == (1, 2, 2)
    old = {k: v for k, v in mini.training_signature(wan, size).items() if k != "patch"}
    mw, bw = (build_camera_wan(*mini.model_configs(wan, 4), seed=s) for s in (4, 5))
    mini.save_models(path, mw, bw, old, {})
    mini.load_models(path, mw, bw, mini.training_signature(wan, size))
    with pytest.raises(ValueError, match="patch"):
        mini.load_models(path, m2, b2, sig)


@pytest.mark.parametrize("stage", ["base", "control"])
def test_batched_step_is_the_products_accumulated_step(mini, held, stage):
    """One step of the benchmark's batched trainer (one model call for the batch) against the product's trainer
    (one clip at a time, gradients accumulated): the same loss and the same updated weights."""
    import argparse
    import copy

    import torch

    from navcrafter.models.synthesis.camcontrol import build_camera_wan
    from navcrafter.models.synthesis.training import CameraTrainer, flow_loss, sample_generator

    args = argparse.Namespace(heads=2, head_dim=8, layers=1, ffn=16, adapter_channels=4, reference_frames=1)
    base, control = mini.model_configs(args, 192)
    model = build_camera_wan(base, control, seed=0)
    with torch.no_grad():  # a non-zero control, so that the cameras change the prediction
        for p in model.control.parameters():
            p.add_(0.05 * torch.randn_like(p))
    clips = [c["clip"] for c in held[0]["clips"][:3]]
    cfg = mini.training_config(stage=stage, steps=10, lr=1e-3, seed=0, frames=5, resolution=16, warmup=1, batch=3)
    ours, product = copy.deepcopy(model), copy.deepcopy(model)
    tr = mini.cosine_trainer(ours, clips, cfg)
    assert type(tr).__name__ == "BatchedCosineTrainer"
    ref = CameraTrainer(product, clips, cfg)
    ref.lr_at = tr.lr_at  # the same schedule: only the step differs
    a, b = tr.train_step(), ref.train_step()
    assert a.loss == pytest.approx(b.loss, rel=1e-5)
    # The gradients (kept after the step: the trainers zero them at the start of a step) agree; the weights agree
    # wherever the gradient's sign is decided. Adam's first step is ≈ lr·sign(grad), so where a gradient is near
    # zero (CI failed on one entry of base.blocks.0.attn2.add_k_proj.bias) its float noise, summed in another order
    # on another CPU, has a random sign and moves the weight by up to ±lr in either trainer: bounded there.
    scale = max(float(q.grad.abs().max()) for q in product.parameters() if q.grad is not None)
    lr = tr.lr_at(0)
    moved = decided = total = 0
    for (k, p), q, p0 in zip(ours.named_parameters(), product.parameters(), model.parameters()):
        assert (p.grad is None) == (q.grad is None), k
        if q.grad is None:
            assert torch.equal(p, q), k
            continue
        # float32 noise measured here: up to 3.4e-7 x the largest gradient (patch_embedding); CI's CPU sums in
        # another order, so 30x that
        assert torch.allclose(p.grad, q.grad, rtol=1e-3, atol=1e-5 * scale), k
        sure = q.grad.abs() > 1e-3 * scale  # 100x the tolerated noise: the sign is decided
        decided += int(sure.sum())
        total += sure.numel()
        assert torch.allclose(p[sure], q[sure], atol=5e-5, rtol=0), k  # 5 % of the step
        assert float((p - q).abs().max()) <= 2.05 * lr, k
        moved += int(not torch.equal(p, p0))
    assert moved > 0 and decided > total // 10  # control stage: 17 % of the entries, base more
    # per clip: the batched loss is the mean of the product's flow_loss of each clip
    product.train()
    from navcrafter.models.synthesis.training import clip_conditions

    cs = [clip_conditions(product, c) for c in clips]
    want = np.mean([float(flow_loss(product, product, c, sample_generator(7, i), cfg)) for i, c in enumerate(cs)])
    got = float(mini.batch_flow_loss(product, product, cs, [sample_generator(7, i) for i in range(3)], cfg))
    assert got == pytest.approx(want, rel=1e-5)
    assert mini.cosine_trainer(model, clips, mini.training_config(stage=stage, steps=10, lr=1e-3, seed=0, frames=5,
                                                                  resolution=16)).__class__.__name__ == "CosineTrainer"


def test_parse_sweep(mini):
    assert mini.parse_sweep("3:0.7:40, 5:1:20:5") == [(3.0, 0.7, 40, mini.FLOW_SHIFT), (5.0, 1.0, 20, 5.0)]
    assert mini.parse_sweep(None) == []
    with pytest.raises(ValueError, match="camera_guidance:lora_scale:sampling_steps"):
        mini.parse_sweep("3:0.7")


def test_scenes_file_round_trips_without_the_simulator_and_only_with_the_same_settings(mini, held, tmp_path):
    """--scenes: what build_scenes rendered loads back (no simulator object in the file, clips encoded again and
    equal), and a file of other settings is refused (None: the caller renders afresh)."""
    import pickle

    import numpy as np

    from navcrafter.models.synthesis.encoders import PixelShuffleEncoders

    enc = PixelShuffleEncoders(4, temporal=4, image_dim=8, text_dim=16, image_tokens=16)
    key = {"frames": 5, "resolution": 16, "condition": "first", "version": mini.SCENES_VERSION}
    path = tmp_path / "scenes.pkl"
    mini.save_scenes(path, key, held, held)
    with open(path, "rb") as f:
        raw = pickle.load(f)
    assert all(isinstance(e["scene"], mini.SceneMeta) and "clip" not in e["clips"][0] for e in raw["train"])
    train, back = mini.load_scenes(path, key, enc)
    assert len(train) == len(back) == len(held)
    for e, b in zip(held, back):
        assert b["scene"].L == e["scene"].L and np.array_equal(b["scene"].c2w0, e["scene"].c2w0)
        assert np.array_equal(b["scene"].dolly_axis, e["scene"].dolly_axis)
        assert np.array_equal(b["grid"][0], e["grid"][0])
        for c, d in zip(e["clips"], b["clips"]):
            assert c["id"] == d["id"] and np.array_equal(c["truth"], d["truth"])
            for k, v in c["clip"].items():
                if isinstance(v, np.ndarray):
                    assert np.array_equal(v, d["clip"][k]), k
    assert mini.load_scenes(path, dict(key, frames=9), enc) is None
    assert mini.load_scenes(tmp_path / "missing.pkl", key, enc) is None

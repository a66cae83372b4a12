"""The camera-control trainer: loss, exact resume after SIGKILL, DDP (2 gloo processes) = one process with the
doubled batch, checkpoints in safetensors."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from navcrafter.models.synthesis.camcontrol import TINY_I2V_CONFIG, build_camera_wan, tiny_camera_config
from navcrafter.models.synthesis.training import (
    CameraTrainer,
    camera_gap,
    clip_conditions,
    flow_loss,
    latest_checkpoint,
    sample_clip,
    sample_generator,
    shift_sigma,
    stack_conditions,
)
from navcrafter.schemas.training import CameraTrainingConfig

T, HW = 5, 32


def synthetic_clip(i: int) -> dict:
    """A clip whose latents depend on its camera (a sideways move), so the camera carries information."""
    r = np.random.default_rng(i)
    c2w = np.tile(np.eye(4), (T, 1, 1))
    c2w[:, 0, 3] = np.linspace(0.0, 0.4 * ((i % 3) - 1), T)
    K = np.tile(np.array([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]]), (T, 1, 1))
    lat = r.normal(size=(16, 2, 4, 4)).astype(np.float32) * 0.5
    lat[:, 1] += 5.0 * c2w[-1, 0, 3]  # what the second latent frame holds follows the camera
    return {"latents": lat, "image_latents": np.concatenate([lat[:, :1], np.zeros_like(lat[:, 1:])], 1),
            "image_embeds": r.normal(size=(4, 4)).astype(np.float32),
            "text_embeds": r.normal(size=(512, 32)).astype(np.float32), "c2w": c2w, "K": K,
            "attrs": {"clip_id": f"c{i}"}}


def config(**kw) -> CameraTrainingConfig:
    base = dict(random_base="tiny", steps=6, checkpoint_every=2, text_dropout=0.0, gradient_checkpointing=False)
    base.update(kw)
    return CameraTrainingConfig(**base)


def model():
    return build_camera_wan(TINY_I2V_CONFIG, dataclasses.replace(tiny_camera_config(), cond_channels=0), seed=0)


def test_sampling_a_batch_equals_sampling_each_clip_with_its_own_seed():
    """sample_clip over stack_conditions (a GPU's batch) gives each clip what sampling it alone gives (its own
    noise seed, whatever its place in the batch); a seed count that does not match the batch is refused."""
    net = model().eval()
    cs = [clip_conditions(net, synthetic_clip(i)) for i in range(3)]
    kw = dict(steps=3, guidance_scale=1.0, lora_scale=0.7, flow_shift=3.0)
    with torch.no_grad():
        one = [sample_clip(net, c, seed=10 + i, **kw) for i, c in enumerate(cs)]
        batch = sample_clip(net, stack_conditions(cs), seed=[10, 11, 12], **kw)
    assert batch.shape == (3, *one[0].shape[1:])
    for i in range(3):
        torch.testing.assert_close(batch[i:i + 1], one[i], rtol=1e-4, atol=1e-4)
    assert not torch.allclose(one[0], one[1])  # the seeds differ, so must the clips
    with pytest.raises(ValueError, match="one seed per clip"):
        sample_clip(net, stack_conditions(cs), seed=[10, 11], **kw)
    with pytest.raises(ValueError, match="None in some clips"):
        stack_conditions([cs[0], {**cs[1], "cond": torch.zeros(1)}])


def test_sigma_shift_and_flow_target():
    assert float(shift_sigma(0.5, 3.0)) == pytest.approx(0.75)
    assert float(shift_sigma(0.0, 3.0)) == 0.0 and float(shift_sigma(1.0, 3.0)) == pytest.approx(1.0)
    m = model().train()
    c = clip_conditions(m, synthetic_clip(0))
    # the loss at sigma -> 0 with a model predicting (noise - x0) exactly would be 0; check the target itself
    g1, g2 = sample_generator(0, 3), sample_generator(0, 3)
    a = flow_loss(m, m, c, g1, config())
    b = flow_loss(m, m, c, g2, config())
    assert torch.equal(a, b)  # seeded per sample
    assert not torch.equal(a, flow_loss(m, m, c, sample_generator(0, 4), config()))


def test_only_the_control_trains_and_the_base_is_frozen():
    m = model()
    before = {k: v.clone() for k, v in m.base.state_dict().items()}
    tr = CameraTrainer(m, [synthetic_clip(i) for i in range(3)], config(steps=2))
    tr.train(None)
    assert all(torch.equal(before[k], v) for k, v in m.base.state_dict().items())
    assert any(p.abs().sum() > 0 for n, p in m.control.named_parameters() if "up" in n or "proj" in n)


def test_training_learns_the_camera_gap_grows_from_zero():
    clips = [synthetic_clip(i) for i in range(4)]
    cfg = config(steps=40, optim={"learning_rate": 3e-3})
    m = model()
    assert camera_gap(m, clips, cfg)["camera_gap"] == pytest.approx(0.0, abs=1e-6)  # zero-init ignores cameras
    CameraTrainer(m, clips, cfg).train(None)
    assert camera_gap(m, clips, cfg)["camera_gap"] > 1e-3


def test_resume_continues_the_same_loss_curve(tmp_path):
    clips = [synthetic_clip(i) for i in range(4)]
    full = CameraTrainer(model(), clips, config()).train(tmp_path / "a")
    CameraTrainer(model(), clips, config()).train(tmp_path / "b", steps=3)  # checkpoints at 2 and 3
    tr = CameraTrainer(model(), clips, config())
    assert tr.resume(tmp_path / "b") and tr.state.step == 3
    resumed = tr.train(tmp_path / "b")
    assert [h["loss"] for h in resumed.history] == [h["loss"] for h in full.history]
    ck = latest_checkpoint(tmp_path / "b")
    assert ck.name == "step-00000006"
    names = sorted(p.name for p in ck.iterdir())
    assert names == ["camera_control.json", "camera_control.safetensors", "optimizer.safetensors", "state.json"]
    state = json.loads((ck / "state.json").read_text())
    assert state["data_position"] == 6 and len(state["torch_rng"]) > 0


SCRIPT = textwrap.dedent("""
    import os, signal, sys
    sys.path.insert(0, {tests!r})
    from models.synthesis.test_training import config, model, synthetic_clip
    from navcrafter.models.synthesis.training import CameraTrainer
    kill_at = int(sys.argv[2])
    clips = [synthetic_clip(i) for i in range(4)]
    tr = CameraTrainer(model(), clips, config())
    tr.resume(sys.argv[1])
    def on_step(log):
        if log.step == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
    tr.train(sys.argv[1], on_step=on_step)
""")


@pytest.mark.subprocess  # a training script run twice, SIGKILLed in between
@pytest.mark.slow
def test_a_run_killed_with_sigkill_resumes_to_the_same_curve(tmp_path):
    tests = str(Path(__file__).resolve().parents[2])
    script = tmp_path / "run.py"
    script.write_text(SCRIPT.format(tests=tests))
    run = tmp_path / "run"
    killed = subprocess.run([sys.executable, str(script), str(run), "5"], capture_output=True, text=True)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert latest_checkpoint(run).name == "step-00000004"  # step 5 was lost with the process
    done = subprocess.run([sys.executable, str(script), str(run), "0"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    state = json.loads((latest_checkpoint(run) / "state.json").read_text())
    full = CameraTrainer(model(), [synthetic_clip(i) for i in range(4)], config()).train(None)
    assert [h["loss"] for h in state["history"]] == pytest.approx([h["loss"] for h in full.history], rel=1e-6)


DDP = textwrap.dedent("""
    import os, sys, json
    sys.path.insert(0, {tests!r})
    import torch, torch.distributed as dist
    from models.synthesis.test_training import config, model, synthetic_clip
    from navcrafter.models.synthesis.training import CameraTrainer
    dist.init_process_group("gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    clips = [synthetic_clip(i) for i in range(4)]
    tr = CameraTrainer(model(), clips, config(optim={{"batch_size": 1}}), rank=rank, world_size=world)
    st = tr.train(None, steps=3)
    if rank == 0:
        torch.save(tr.model.control.state_dict(), sys.argv[1])
        json.dump([h["loss"] for h in st.history], open(sys.argv[1] + ".json", "w"))
    dist.barrier()  # no rank tears the group down while the other still writes
    dist.destroy_process_group()
    sys.stdout.flush(); sys.stderr.flush()
    os._exit(0)  # gloo's threads can abort the interpreter's normal exit ("terminate called ...")
""")


@pytest.mark.subprocess  # torchrun with 2 gloo processes
@pytest.mark.slow
def test_two_gloo_processes_equal_one_process_with_the_doubled_batch(tmp_path):
    tests = str(Path(__file__).resolve().parents[2])
    script = tmp_path / "ddp.py"
    script.write_text(DDP.format(tests=tests))
    out = tmp_path / "ddp.pt"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           str(script), str(out)], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    single = CameraTrainer(model(), [synthetic_clip(i) for i in range(4)], config(optim={"batch_size": 2}))
    st = single.train(None, steps=3)
    ddp_state = torch.load(out)
    for k, v in single.model.control.state_dict().items():
        torch.testing.assert_close(ddp_state[k], v, rtol=1e-4, atol=1e-6)
    assert json.loads(Path(str(out) + ".json").read_text()) == pytest.approx([h["loss"] for h in st.history],
                                                                          rel=1e-5)

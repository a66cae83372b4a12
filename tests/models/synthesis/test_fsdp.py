"""FSDP2 training (``parallel="fsdp"``): 2 gloo processes with batch 1 = one process with batch 2, checkpoints that
are the same files as a single process writes (each kind of run resumes the other's), unused parameters (a dropped
camera on one rank, or on every rank) handled as a single process handles them, with activation checkpointing too."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file
from test_training import config, model, synthetic_clip  # the module pytest imported (its folder is on sys.path)

from navcrafter.models.synthesis.training import CameraTrainer, latest_checkpoint, sample_generator

DROPOUT_SEED = 7  # camera dropped for samples [1, 1, 0, 0, 1, 0]: step 1 on both ranks, step 3 on one

FSDP = textwrap.dedent("""
    import json, os, sys
    from pathlib import Path
    sys.path.insert(0, {tests!r})
    import torch, torch.distributed as dist
    from models.synthesis.test_training import config, model, synthetic_clip
    from navcrafter.models.synthesis.distributed import full_module_state
    from navcrafter.models.synthesis.training import CameraTrainer
    dist.init_process_group("gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    out = Path(sys.argv[1])
    clips = [synthetic_clip(i) for i in range(4)]

    def run(name, cfg, run_dir=None, resume=None, steps=3):
        tr = CameraTrainer(model(), clips, cfg, rank=rank, world_size=world)
        assert tr.sharded
        if resume is not None:
            assert tr.resume(resume) and tr.state.step == 3
        st = tr.train(run_dir, steps=steps)
        control = full_module_state(tr.model.control)  # collective
        if rank == 0:
            torch.save(control, out / (name + ".pt"))
            (out / (name + ".json")).write_text(json.dumps([h["loss"] for h in st.history]))

    fsdp = dict(parallel="fsdp", optim={{"batch_size": 1}})
    run("plain", config(**fsdp), run_dir=out / "fsdp-run")  # checkpoints at steps 2 and 3
    run("resumed", config(**fsdp), resume=out / "single-run", steps=6)  # from a single-process checkpoint
    # (with activation checkpointing, the default of real runs; the reference runs without: same numbers)
    run("dropout", config(**fsdp, camera_dropout=0.5, seed={dropout_seed}, gradient_checkpointing=True))
    dist.barrier()  # no rank tears the group down while the other still writes
    dist.destroy_process_group()
    sys.stdout.flush(); sys.stderr.flush()
    os._exit(0)  # gloo's threads can abort the interpreter's normal exit ("terminate called ...")
""")


def _camera_dropped(seed: int, index: int) -> bool:
    """flow_loss's draws of a sample: u, the noise, the text and then the camera dropout."""
    g = sample_generator(seed, index)
    torch.rand((), generator=g)
    torch.randn((1,) + synthetic_clip(0)["latents"].shape, generator=g)
    torch.rand((), generator=g)
    return bool(torch.rand((), generator=g) < 0.5)


def _assert_states_close(a: dict, b: dict) -> None:
    assert sorted(a) == sorted(b)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-6, msg=k)


@pytest.mark.system
def test_two_fsdp_gloo_processes_equal_one_process_and_share_its_checkpoints(tmp_path):
    clips = [synthetic_clip(i) for i in range(4)]
    single_cfg = config(optim={"batch_size": 2})
    ref = CameraTrainer(model(), clips, single_cfg)
    ref.train(tmp_path / "single-run", steps=3)  # checkpoints at 2 and 3 (the FSDP run resumes step 3)
    ref_control = {k: v.clone() for k, v in ref.model.control.state_dict().items()}
    ref_losses = [h["loss"] for h in ref.train(None).history]  # steps 1..6, uninterrupted

    drop_cfg = config(optim={"batch_size": 2}, camera_dropout=0.5, seed=DROPOUT_SEED)
    drops = [_camera_dropped(DROPOUT_SEED, i) for i in range(6)]
    assert drops[0] and drops[1] and drops[4] != drops[5], drops  # both ranks, then one rank, drop the camera
    drop_ref = CameraTrainer(model(), clips, drop_cfg)
    drop_ref.train(None, steps=1)
    assert 0 < len(drop_ref.opt.state) < len(drop_ref.params)  # no sample used the camera branch: no state
    drop_losses = [h["loss"] for h in drop_ref.train(None, steps=3).history]

    tests = str(Path(__file__).resolve().parents[2])
    script = tmp_path / "fsdp.py"
    script.write_text(FSDP.format(tests=tests, dropout_seed=DROPOUT_SEED))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           str(script), str(tmp_path)], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]

    def losses(name):
        return json.loads((tmp_path / (name + ".json")).read_text())

    # 2 processes x batch 1 = 1 process x batch 2 (loss curve and weights)
    assert losses("plain") == pytest.approx(ref_losses[:3], rel=1e-5)
    _assert_states_close(torch.load(tmp_path / "plain.pt"), ref_control)

    # the FSDP checkpoint holds the same files as the single-process one, with the same contents
    fsdp_ck, single_ck = latest_checkpoint(tmp_path / "fsdp-run"), latest_checkpoint(tmp_path / "single-run")
    assert fsdp_ck.name == single_ck.name == "step-00000003"
    assert sorted(p.name for p in fsdp_ck.iterdir()) == sorted(p.name for p in single_ck.iterdir())
    for f in ("camera_control.safetensors", "optimizer.safetensors"):
        _assert_states_close(load_file(fsdp_ck / f), load_file(single_ck / f))
    assert json.loads((fsdp_ck / "camera_control.json").read_text()) == \
        json.loads((single_ck / "camera_control.json").read_text())
    fsdp_state, single_state = (json.loads((ck / "state.json").read_text()) for ck in (fsdp_ck, single_ck))
    assert fsdp_state["optimizer"] == single_state["optimizer"]  # index-keyed param groups and scalars
    assert fsdp_state["data_position"] == single_state["data_position"] == 6

    # a single process resumes the FSDP checkpoint ...
    tr = CameraTrainer(model(), clips, single_cfg)
    assert tr.resume(tmp_path / "fsdp-run") and tr.state.step == 3
    assert [h["loss"] for h in tr.train(None).history] == pytest.approx(ref_losses, rel=1e-5)
    # ... and FSDP resumes the single-process one
    assert losses("resumed") == pytest.approx(ref_losses, rel=1e-5)

    # unused parameters: camera dropped on both ranks (no gradient anywhere) and on one rank only
    assert losses("dropout") == pytest.approx(drop_losses, rel=1e-5)
    _assert_states_close(torch.load(tmp_path / "dropout.pt"), drop_ref.model.control.state_dict())


def test_fsdp_with_one_process_is_a_plain_single_process_run(tmp_path):
    clips = [synthetic_clip(i) for i in range(4)]
    a = CameraTrainer(model(), clips, config(parallel="fsdp"))
    assert not a.sharded and a.wrapped is a.model
    b = CameraTrainer(model(), clips, config())
    assert [h["loss"] for h in a.train(tmp_path / "a", steps=2).history] == \
        [h["loss"] for h in b.train(tmp_path / "b", steps=2).history]

"""The training steps of ``navcrafter train-camera`` as plain functions over a run folder (the flow calls them).

``RUN/config.json`` is the run's ``CameraTrainingConfig`` (written by ``prepare_run``; a rerun with a different
config is refused, so that a resumed run cannot silently change what it trains). Then: ``build_model`` /
``build_encoders`` (from ``config.base`` or the tiny random base), ``train`` (one process, or ``launch`` for
``torchrun`` DDP with the worker ``python -m navcrafter.tasks.training.worker RUN``), ``validate`` (the
camera-conditioning gap on the validation clips + a loss-curve PNG) and ``export_control`` (``RUN/control``,
the input of ``navcrafter models export-synthesizer --control``).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from navcrafter.models.synthesis.encoders import WanEncoders
from navcrafter.models.synthesis.pipeline import video_to_frames
from navcrafter.schemas.training import CLIP_STORE, FINAL_CONTROL_DIR, CameraTrainingConfig
from navcrafter.tasks.training.clips import ClipDataset

CONFIG_FILE = "config.json"
VALIDATION_FILE = "validation.json"


class TrainingRunError(ValueError):
    """The run folder does not fit the request (the message names the folder and the fix)."""


def prepare_run(run_dir: str | os.PathLike, config: CameraTrainingConfig) -> Path:
    """Create ``run_dir`` and record ``config``; an existing run must have been started with the same config."""
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    path = run / CONFIG_FILE
    now = json.loads(config.model_dump_json())
    if path.is_file():
        before = json.loads(path.read_text())
        if before != now:
            diff = sorted(k for k in set(before) | set(now) if before.get(k) != now.get(k))
            raise TrainingRunError(f"{run} was started with a different config (differs in: {', '.join(diff)}); "
                                   f"use a new run folder, or the config in {path}")
        return run
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(now, indent=2, sort_keys=True))
    os.replace(tmp, path)
    return run


def load_run_config(run_dir: str | os.PathLike) -> CameraTrainingConfig:
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise TrainingRunError(f"{path} missing: start the run with `navcrafter train-camera`")
    return CameraTrainingConfig.model_validate(json.loads(path.read_text()))


def control_config(config: CameraTrainingConfig):
    """The ``CameraControlConfig`` of the run: the preset of the base's width, then ``config.control``."""
    # deferred: torch and diffusers (models.synthesis.camcontrol) load only when the control is configured
    from navcrafter.models.synthesis.camcontrol import CameraControlConfig, tiny_camera_config

    start = tiny_camera_config() if config.random_base == "tiny" else CameraControlConfig()
    known = {f.name for f in dataclasses.fields(CameraControlConfig)}
    unknown = sorted(set(config.control) - known)
    if unknown:
        raise TrainingRunError(f"control: unknown CameraControlConfig keys {unknown}; known: {sorted(known)}")
    return dataclasses.replace(start, **config.control)


def build_model(config: CameraTrainingConfig, device: str = "cpu"):
    """The camera-controlled DiT to train: the pretrained base (``config.base``) or the tiny random one, with a
    fresh zero-initialised control of ``control_config(config)``."""
    # deferred: torch and diffusers (the camera-controlled Wan) load only when a model is built
    from navcrafter.models.synthesis.camcontrol import TINY_I2V_CONFIG, CameraControlledWan, build_camera_wan

    ccfg = control_config(config)
    if config.base is None and config.random_base is None:
        raise TrainingRunError("no base model: set base to a diffusers-format Wan2.1 I2V folder (or "
                               "random_base='tiny' for a random tiny one)")
    if config.random_base == "tiny":
        model = build_camera_wan(TINY_I2V_CONFIG, ccfg, seed=config.seed)
    else:
        model = CameraControlledWan.from_pretrained(config.base, config=ccfg)
    return model.to(device)


def build_encoders(config: CameraTrainingConfig):
    """The encoders of the clip store: the base's Wan VAE, CLIP and text encoder (tiny random ones for the tiny
    base)."""
    # deferred: torch loads only when the encoders are built
    from navcrafter.models.synthesis.onnx_export import load_components, tiny_components

    if config.random_base == "tiny":
        components = tiny_components(seed=config.seed, prompt=config.data.prompt)
    else:
        components = load_components(config.base, prompt=config.data.prompt)
    return WanEncoders(components)


def open_clips(run_dir: str | os.PathLike, split: str):
    return ClipDataset(Path(run_dir) / CLIP_STORE, split=split)


def null_text(run_dir: str | os.PathLike) -> np.ndarray | None:
    """The null prompt's text embeddings of the clip store (text dropout), or None."""
    import zarr

    store = Path(run_dir) / CLIP_STORE
    if not store.exists():
        return None
    root = zarr.open_group(str(store), mode="r")
    return np.asarray(root["null_text_embeds"][...]) if "null_text_embeds" in root else None


def train(run_dir: str | os.PathLike, *, rank: int = 0, world_size: int = 1, device: str = "cpu",
          on_step: Callable | None = None, on_validate: Callable | None = None,
          steps: int | None = None) -> dict[str, Any]:
    """Train (resuming from the newest checkpoint of ``run_dir``) up to ``config.steps``; returns a summary.

    Every ``validate_every`` steps rank 0 measures the camera-conditioning gap on the validation clips (when
    there are at least 2), appends it to the run's validation history (saved with the checkpoints) and calls
    ``on_validate(history)``."""
    # deferred: torch and diffusers load only when training runs
    from navcrafter.models.synthesis.training import CameraTrainer, camera_gap, trainable_parameters

    config = load_run_config(run_dir)
    model = build_model(config, device)
    clips = open_clips(run_dir, "train")
    trainer = CameraTrainer(model, clips, config, device=device, rank=rank, world_size=world_size,
                            null_text=null_text(run_dir) if config.text_dropout > 0 else None)
    resumed_at = trainer.state.step if trainer.resume(run_dir) else 0
    held = open_clips(run_dir, "validation")
    # FSDP: every rank takes part in every forward (the shards are gathered collectively), so all validate
    everyone = config.parallel == "fsdp" and world_size > 1
    held = [held[i] for i in range(len(held))] if len(held) >= 2 and (rank == 0 or everyone) else []

    def step_hook(log) -> None:
        if on_step is not None:
            on_step(log)
        if held and log.step % config.validate_every == 0:
            gap = camera_gap(model, held, config, device=device)
            trainer.state.validation.append({"step": log.step, **gap})
            if on_validate is not None and rank == 0:
                on_validate(trainer.state.validation)

    state = trainer.train(run_dir, steps=steps, on_step=step_hook)
    losses = [h["loss"] for h in state.history]
    return {"steps": state.step, "resumed_at": resumed_at, "train_clips": len(clips),
            "trainable_parameters": trainable_parameters(model, config),
            "loss_first": losses[0] if losses else None, "loss_last": losses[-1] if losses else None}


def launch(run_dir: str | os.PathLike, nproc: int, *, timeout: float | None = None) -> None:
    """Train with ``nproc`` DDP processes (``torchrun --standalone``, gloo on CPU, NCCL on CUDA)."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={int(nproc)}",
           "-m", "navcrafter.tasks.training.worker", str(run_dir)]
    proc = subprocess.run(cmd, timeout=timeout, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stdout + proc.stderr)[-4000:]
        raise RuntimeError(f"distributed training ({nproc} processes) failed with exit code {proc.returncode}:\n"
                           f"{tail}")


def validate(run_dir: str | os.PathLike) -> dict[str, Any]:
    """The camera-conditioning gap of the newest checkpoint on the validation clips (train clips when there
    are fewer than 2), written to ``RUN/validation.json``."""
    # deferred: torch and diffusers load only when validating
    from navcrafter.models.synthesis.training import camera_gap

    config, ckpt, model = checkpoint_model(run_dir, "validate")
    clips = open_clips(run_dir, "validation")
    split = "validation"
    if len(clips) < 2:
        clips, split = open_clips(run_dir, "train"), "train"
    held = [clips[i] for i in range(len(clips))]
    result = {"checkpoint": ckpt.name, "split": split, "clips": len(clips), **camera_gap(model, held, config)}
    (Path(run_dir) / VALIDATION_FILE).write_text(json.dumps(result, indent=2))
    return result


def sample_frames_png(run_dir: str | os.PathLike, index: int = 0, frames: int = 5) -> bytes:
    """A PNG strip: the first validation clip as stored (decoded latents) over a clip sampled by the newest
    checkpoint with that clip's cameras (``validation_sampling_steps`` DPM-solver steps, LoRA at inference
    strength ``synthesis.lora_scale``, no CFG)."""
    from PIL import Image

    # deferred: torch and diffusers load only when sampling; schemas.config loads torch
    from navcrafter.models.synthesis.training import clip_conditions, sample_clip
    from navcrafter.schemas.config import SynthesisConfig

    config, _, model = checkpoint_model(run_dir, "sample")
    clips = open_clips(run_dir, "validation")
    if len(clips) == 0:
        clips = open_clips(run_dir, "train")
    clip = clips[index]
    encoders = build_encoders(config)
    z = sample_clip(model, clip_conditions(model, clip), seed=config.seed, steps=config.validation_sampling_steps,
                    guidance_scale=1.0, lora_scale=SynthesisConfig().lora_scale, flow_shift=config.flow_shift)

    rows = [video_to_frames(encoders.decode_video(np.asarray(latents, np.float32)))
            for latents in (clip["latents"], z[0].numpy())]
    T, H, W = rows[0].shape[:3]
    pick = np.linspace(0, T - 1, min(frames, T)).round().astype(int)
    strip = np.concatenate([np.concatenate([r[i] for i in pick], axis=1) for r in rows], axis=0)
    buf = io.BytesIO()
    Image.fromarray(strip).save(buf, format="PNG")
    return buf.getvalue()


def checkpoint_model(run_dir: str | os.PathLike, what: str, *, with_base: bool = True):
    """``(config, checkpoint folder, model)`` of the run's newest checkpoint: the control weights loaded, and the
    base too when the run trained it and ``with_base``; ``what`` names the caller's action in the error."""
    # deferred: torch and diffusers load only when a checkpoint is read
    from navcrafter.models.synthesis.camcontrol import load_camera_control
    from navcrafter.models.synthesis.training import latest_checkpoint

    config = load_run_config(run_dir)
    ckpt = latest_checkpoint(run_dir)
    if ckpt is None:
        raise TrainingRunError(f"{run_dir}: no checkpoint to {what}; train first")
    model = build_model(config)
    load_camera_control(model, ckpt)
    if with_base and (ckpt / "base.safetensors").is_file():
        from safetensors.torch import load_file

        model.base.load_state_dict(load_file(str(ckpt / "base.safetensors")), strict=True)
    return config, ckpt, model


def export_control(run_dir: str | os.PathLike) -> Path:
    """``RUN/control``: the newest checkpoint's control weights, their config's ``extra`` recording the
    training data and steps (what ``export-synthesizer --control`` copies into the manifest)."""
    # deferred: torch and diffusers load only when the control is exported
    from navcrafter.models.synthesis.camcontrol import save_camera_control
    from navcrafter.models.synthesis.training import STATE_FILE

    config, ckpt, model = checkpoint_model(run_dir, "export", with_base=False)  # only the control is written
    state = json.loads((ckpt / STATE_FILE).read_text())
    model.config.extra = {**model.config.extra, "training": {
        "steps": state["step"], "samples": state["data_position"],
        "data": [s.model_dump() for s in config.data.sources], "num_frames": config.data.num_frames,
        "resolution": config.data.resolution, "frame_stride": config.data.frame_stride,
        "optim": config.optim.model_dump(), "base": config.base or f"random {config.random_base}",
        "trainable": config.trainable, "final_loss": state["history"][-1]["loss"] if state["history"] else None}}
    return save_camera_control(model, Path(run_dir) / FINAL_CONTROL_DIR)


def loss_curve_png(history: list[dict[str, float]], size: tuple[int, int] = (480, 240)) -> bytes:
    """A PNG of the training loss (grey: per step; black: running mean) — PIL only."""
    from PIL import Image, ImageDraw

    W, H = size
    img = Image.new("RGB", size, (250, 250, 247))
    d = ImageDraw.Draw(img)
    if history:
        y = np.array([h["loss"] for h in history], dtype=np.float64)
        x = np.arange(1, len(y) + 1)
        k = max(1, len(y) // 50)
        smooth = np.convolve(y, np.ones(k) / k, mode="valid")
        lo, hi = float(np.min(y)), float(np.max(y))
        span = hi - lo or 1.0

        def pt(i: float, v: float) -> tuple[float, float]:
            return 30 + (W - 40) * (i - 1) / max(len(y) - 1, 1), 10 + (H - 40) * (1 - (v - lo) / span)

        d.line([pt(i, v) for i, v in zip(x, y)], fill=(180, 180, 180))
        d.line([pt(i + k - 1, v) for i, v in zip(x, smooth)], fill=(20, 20, 20), width=2)
        d.text((32, H - 25), f"steps 1..{len(y)}   loss {lo:.4g}..{hi:.4g}", fill=(0, 0, 0))
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()

"""Settings of a camera-control training run (``CameraTrainingConfig``) and the trainer's checkpoint layout.

What a training run stores besides (the clip store, the final control folder) is declared in schemas/training.py,
which re-exports these.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from navcrafter.models.settings import Section as _Section

# RUN/checkpoints/step-XXXXXXXX/ holds these files (models/synthesis/training.py writes them)
CHECKPOINT_DIR = "checkpoints"
CHECKPOINT_FILES = ("camera_control.safetensors", "camera_control.json", "optimizer.safetensors", "state.json")


class DataSource(_Section):
    """One dataset in its own format (readers: ``schemas/datasets``)."""

    kind: Literal["re10k", "dl3dv"] = Field(description="RealEstate10K (camera .txt + frames) or DL3DV "
                                                        "(transforms.json + images).")
    root: str = Field(description="The dataset's folder.")
    split: str | None = Field(None, description="RealEstate10K split folder ('train'/'test'); None: the root.")


class TrainingDataConfig(_Section):
    sources: tuple[DataSource, ...] = Field((), description="Datasets to draw clips from.")
    num_frames: int = Field(81, ge=2, description="Frames per training clip (4k+1 for the Wan VAE).")
    resolution: int = Field(256, ge=16, description="Square size frames are resized/cropped to.")
    frame_stride: int = Field(1, ge=1, description="Take every n-th frame of a sequence.")
    clips_per_source: int | None = Field(None, ge=1, description="Clips drawn per dataset; None: one per "
                                                                  "sequence.")
    validation_clips: int = Field(2, ge=0, description="Clips held out for validation (the last sequences).")
    render_condition: bool = Field(True, description="Precompute the point-cloud render conditioning "
                                                     "(needs depth of frame 0: the simulation engine writes it).")
    extra_reference: bool = Field(True, description="Precompute an extra reference frame before the clip "
                                                    "(the input photo of iterations k >= 2).")
    prompt: str = Field("", description="Caption used for every clip (the datasets have none).")


class OptimConfig(_Section):
    learning_rate: float = Field(1e-4, gt=0)
    weight_decay: float = Field(3e-2, ge=0)
    betas: tuple[float, float] = (0.9, 0.999)
    grad_clip: float | None = Field(1.0, gt=0, description="Global grad-norm clip; None: off.")
    batch_size: int = Field(1, ge=1, description="Clips per step per process.")
    warmup_steps: int = Field(0, ge=0)


class CameraTrainingConfig(BaseModel):
    """A camera-control training run (see the module docstring for what it writes)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    data: TrainingDataConfig = TrainingDataConfig()
    optim: OptimConfig = OptimConfig()
    steps: int = Field(10_000, ge=1)
    seed: int = 0
    checkpoint_every: int = Field(500, ge=1)
    keep_checkpoints: int = Field(2, ge=1)
    validate_every: int = Field(500, ge=1, description="Steps between validations (camera gap on the "
                                                       "validation clips).")
    validation_sampling_steps: int = Field(20, ge=1, description="DPM-solver steps of the validation sample "
                                                                 "shown in the run's artifact.")
    flow_shift: float = Field(3.0, gt=0, description="σ shift of the training timesteps "
                                                     "(σ' = sσ / (1 + (s-1)σ), Wan's flow matching).")
    text_dropout: float = Field(0.1, ge=0, le=1, description="Probability a clip's text is replaced by the "
                                                             "empty prompt (for CFG).")
    camera_dropout: float = Field(0.0, ge=0, le=1, description="Probability the camera is dropped "
                                                               "(plucker = None).")
    mixed_precision: Literal["bf16", "no"] = Field("bf16", description="bf16 autocast on CUDA (fp32 master "
                                                                       "weights); CPU always runs fp32.")
    gradient_checkpointing: bool = True
    parallel: Literal["ddp", "fsdp"] = Field("ddp", description="With several processes: 'ddp' (each holds the "
                                                                "whole model) or 'fsdp' (torch FSDP2 shards the "
                                                                "base blocks and the control, for 14B width).")
    trainable: Literal["control", "base", "all"] = Field(
        "control", description="'control': the paper (base frozen); 'base': only the base DiT (pretraining the "
        "stand-in of a pretrained Wan for tiny benchmarks; the control stays zero); 'all': both.")
    base: str | None = Field(None, description="Diffusers-format Wan2.1 I2V folder; None with random_base.")
    random_base: Literal["tiny"] | None = Field(None, description="Build a random tiny base (tests).")
    control: dict = Field(default_factory=dict, description="CameraControlConfig overrides.")
    log_every: int = Field(10, ge=1)

    @model_validator(mode="after")
    def _check(self) -> CameraTrainingConfig:
        if (self.data.num_frames - 1) % 4:
            raise ValueError(f"data.num_frames must be 4k+1 (Wan VAE), got {self.data.num_frames}")
        if self.base is not None and self.random_base is not None:
            raise ValueError("give either base (a diffusers-format Wan2.1 I2V folder) or random_base, not both")
        return self

    @classmethod
    def from_file(cls, path: str | Path) -> CameraTrainingConfig:
        return cls.model_validate(yaml.safe_load(Path(path).read_text()) or {})

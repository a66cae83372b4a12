"""Camera-control training (``navcrafter train-camera``): its configuration and what it stores.

One config (``CameraTrainingConfig``) declares every parameter of a training run once; the flow
(``flows/train_camera.py``), the tasks (``tasks/training/``) and the trainer (``models/synthesis/training.py``)
read it and nothing else. Defaults are the paper's (Module I): 81-frame clips at 256², AdamW lr 1e-4 with
weight decay 3e-2, bf16 on CUDA, rectified-flow loss with shifted σ, base DiT frozen.

Stored (a training run is a folder, ``RUN``):

* ``RUN/clips.zarr`` — the **clip store** (``CLIP_ARRAYS``, ``CLIP_ATTRS``): one Zarr group per clip
  ``clips/<clip_id>`` holding what the trainer needs, precomputed once (VAE latents, CLIP image features, text
  embeddings, the point-cloud render conditioning, cameras relative to frame 0). Each group is written by one
  task and marked complete by its ``done`` attribute, written last: a killed precompute resumes by
  skipping complete groups (one writer per group, no shared chunk).
* ``RUN/checkpoints/step-XXXXXXXX/`` — training checkpoints (``CHECKPOINT_FILES``): the camera-control
  weights in ``save_camera_control``'s layout, ``optimizer.safetensors`` (AdamW state), ``state.json`` (step,
  RNG states, data position, loss history). ``RUN/checkpoints/latest`` names the newest complete one.
* ``RUN/control/`` — the final control weights (``save_camera_control``), the input of
  ``navcrafter models export-synthesizer --control RUN/control``; its config's ``extra`` records the
  training data and steps.
"""

from __future__ import annotations

# the trainer's settings and its checkpoint layout live beside the trainer (models/synthesis); re-exported here
from navcrafter.models.synthesis.training_config import (
    CHECKPOINT_DIR,
    CHECKPOINT_FILES,
    CameraTrainingConfig,
    DataSource,
    OptimConfig,
    TrainingDataConfig,
)

__all__ = ["CHECKPOINT_DIR", "CHECKPOINT_FILES", "CLIP_ARRAYS", "CLIP_ATTRS", "CLIP_REQUIRED", "CLIP_STORE",
           "CLIP_STORE_FORMAT", "CLIP_STORE_VERSION", "FINAL_CONTROL_DIR", "CameraTrainingConfig", "DataSource",
           "OptimConfig", "TrainingDataConfig"]

CLIP_STORE = "clips.zarr"
CLIP_STORE_FORMAT = "navcrafter-training-clips"
CLIP_STORE_VERSION = 1

# name -> (dtype, shape in words). C = latent channels, F = latent frames, T = video frames.
CLIP_ARRAYS: dict[str, tuple[str, str]] = {
    "latents": ("float32", "[C, F, h, w] normalised VAE latents of the clip (the x0 of the flow loss)"),
    "image_latents": ("float32", "[C, F, h, w] VAE latents of the I2V condition video (frame 0, then black)"),
    "image_embeds": ("float32", "[L_img, image_dim] CLIP image features of frame 0"),
    "text_embeds": ("float32", "[512, text_dim] text-encoder embeddings of the clip's caption ('' if none)"),
    "c2w": ("float64", "[T, 4, 4] OpenCV camera-to-world relative to frame 0 (c2w[0] = I), dataset units"),
    "K": ("float64", "[T, 3, 3] pixel intrinsics of the stored frames"),
    # optional (config.data.render_condition): the paper's V(T, P_curr) for a cloud lifted from frame 0
    "render_latents": ("float32", "[C, F, h, w] VAE latents of frame 0's points rendered along the clip"),
    "visibility": ("uint8", "[T, H, W] 1 where those renders cover the pixel"),
    # optional: an extra reference frame from the same sequence outside the clip (the input photo at inference)
    "reference_latents": ("float32", "[C, 1, h, w] VAE latents of the extra reference frame"),
    "reference_c2w": ("float64", "[4, 4] its camera-to-world relative to the clip's frame 0"),
}
CLIP_REQUIRED = ("latents", "image_latents", "image_embeds", "text_embeds", "c2w", "K")
CLIP_ATTRS = ("source", "sequence", "start", "stride", "split", "height", "width", "num_frames", "done")

FINAL_CONTROL_DIR = "control"

"""Settings of video synthesis (composed into the run config by schemas/config.py)."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field

from navcrafter.models.settings import Section as _Section

WAN_FLOW_SHIFT = 3.0  # Wan2.1's scheduler shift: exported models record it; used when a manifest has none


class SynthesisConfig(_Section):
    """Video synthesis (paper: Wan2.1 DiT sampled with DPM-solver, 81-frame 256x256 clips)."""

    num_frames: int = Field(81, ge=2, description="Frames per synthesized clip (trajectory length).")
    height: int = Field(256, ge=16)
    width: int = Field(256, ge=16)
    steps: int = Field(40, ge=1, description="DPM-solver steps (onnx backend).")
    guidance_scale: float = Field(6.5, description="Classifier-free guidance scale (onnx backend).")
    lora_scale: float = Field(0.7, description="Camera LoRA weight alpha at inference (onnx backend).")
    flow_shift: float | None = Field(
        None, gt=0, description="Shift of the flow-matching sigmas (onnx backend); None: the exported model's own "
        "scheduler setting (its manifest), else 3.0 (Wan2.1's).")
    fps: int = Field(16, ge=1, description="Frame rate of exported videos (Wan2.1 native rate).")
    # Literal[..., None] is Literal[...] | None (PEP 586), spelled so that its values enumerate as one Literal
    plucker_convention: Literal["relative", "ray", "paper", None] = Field(
        None, description="Plücker-ray convention the run expects the camera control to use (onnx backend; "
        "models.camera.cameras.plucker_rays); None: the exported weights' recorded convention. When set, a model "
        "recorded with another convention is refused (re-export the matching weights).")

    offload: bool = Field(
        False, description="onnx backend: hold one graph of the synthesizer at a time (VAE encoder, image encoder, "
        "DiT, VAE decoder in turn; the others released and reloaded when next needed): less GPU memory, a few "
        "session loads per clip; the frames are the same.")
    model: Literal["navcrafter", "fun-camera"] = Field(
        "navcrafter", description="Synthesizer model (onnx backend): 'navcrafter' (NavCrafter's camera control on "
        "Wan2.1 I2V, models/synthesis/camcontrol/) or 'fun-camera' (VideoX-Fun's Wan2.1-Fun-V1.1-Control-Camera, "
        "models/synthesis/funcamera/). The exported synthesizer's manifest must hold that model.")

    # added after stores existed: keys the synthesize step only when set (schemas.keys)
    keyed_when_set: ClassVar[dict[str, Any]] = {"flow_shift": None, "plucker_convention": None,
                                                "model": "navcrafter"}

"""Settings of the evaluation suite (composed into the run config by schemas/config.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from navcrafter.models.settings import Section as _Section


class EvaluationConfig(_Section):
    """The evaluation suite (``navcrafter evaluate``; ``flows/evaluate.py``)."""

    pose_frames: int = Field(
        14, ge=3, description="Frames of each clip scored (the paper scores 14): with frame_choice 'first' the "
        "pose_frames frames after the conditioning frame (image metrics, FID/FVD; COLMAP for R_err/T_err also gets "
        "the conditioning frame: pose_frames + 1); with 'spaced' pose_frames frames evenly spaced over the clip."
    )
    frame_choice: Literal["first", "spaced"] = Field(
        "first", description="'first': the conditioning frame and the `pose_frames` frames after it, as the paper "
        "scores (image metrics on frames 1..pose_frames, COLMAP on 0..pose_frames); 'spaced': evenly spaced over "
        "the clip (first and last frame included; the same frames for both)."
    )
    lpips_net: Literal["alex", "vgg"] = Field("alex", description="LPIPS backbone.")
    weights_dir: Path | None = Field(
        None, description="Folder with the official evaluation weights (LPIPS, FID Inception, FVD I3D); "
        "default $NAVCRAFTER_EVAL_WEIGHTS or ~/.cache/navcrafter/eval. Missing files make those metrics "
        "'unavailable'."
    )
    camera_guidance: bool = Field(True, description="Run COLMAP on the synthesized clips (R_err/T_err).")

"""The dataset clip benchmark's files (``navcrafter dataset-clips``, ``generate-clips``, ``evaluate-clips``;
written and read by ``tasks/clips/``). Layout::

    <clips>/<clip>/condition.png            the conditioning image
    <clips>/<clip>/reference/0001.png ...   the T-1 ground-truth frames after it
    <clips>/<clip>/cameras.json             T OpenCV c2w (relative: the first is the identity) and K
    <generated>/<clip>/0001.png ...         what a generator made: T-1 frames (or T, the first being
                                            its copy of the conditioning image, which is then dropped)
    <generated>/<clip>/generation.json      what made them (``tasks/clips/generation.py``; version GENERATION_VERSION)
    <generated>/<clip>/cloud.npz            the conditioning image's point cloud the synthesizer was given
"""

from __future__ import annotations

import re

CONDITION = "condition.png"
REFERENCE = "reference"
CAMERAS = "cameras.json"
GENERATION = "generation.json"
CLOUD = "cloud.npz"
GENERATION_VERSION = 1


def clip_key(clip_id: str) -> str:
    """A folder name for a clip id such as ``re10k/0a1b2c@17``."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", clip_id).strip("_")

"""Benchmark clips from the public datasets, and scoring of clips generated for them.

The paper scores its video model on RealEstate10K, DL3DV and Tanks and Temples clips (a conditioning
image and the camera path of the next 14 frames). ``export_clips`` writes such clips, read by
``schemas/datasets/``, as plain files any generator can consume; ``score_clips`` scores the frames a
generator wrote for them with the same metrics as ``navcrafter evaluate`` (Table I image quality on the
14 frames, Table II FID/FVD over all clips, Table III camera pose errors by COLMAP on the conditioning image
and the 14 frames: per-frame means, R_err in radians, and per-clip sums). The files: ``schemas/clips.py``.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from navcrafter.models.metrics import pose
from navcrafter.models.simulation.datasets import MANIFEST
from navcrafter.schemas.clips import CAMERAS, CONDITION, GENERATION, REFERENCE, clip_key
from navcrafter.schemas.config import EvaluationConfig
from navcrafter.tasks.score import frechet_rows, image_quality_rows, pose_error_rows, row


def _save_png(image: np.ndarray, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(image)).save(path)


def simulation_sequences(root: str | Path | None) -> dict[str, dict[str, Any]]:
    """Per sequence name, the provenance record of a dataset written by the simulation data engine
    (``models/simulation/datasets.py``: ``<root>/simulation.json``); empty for any other dataset."""

    path = None if root is None else Path(root) / MANIFEST
    if path is None or not path.is_file():
        return {}
    return {r["name"]: r for r in json.loads(path.read_text()).get("sequences", [])}


def export_clips(samples, out: str | Path) -> list[str]:
    """Write every ``Sample`` of a dataset reader as a clip folder; returns the clip folder names.

    A clip of a simulated dataset also records its hidden truth (``simulation``: the scene's spec and the
    conditioning camera in the scene's frame), which only the simulated generator (``tasks/clips/generation.py``)
    reads."""
    out = Path(out)
    keys = []
    simulated = simulation_sequences(getattr(samples, "root", None))
    for s in samples:
        key = clip_key(s.clip_id)
        d = out / key
        _save_png(s.image, d / CONDITION)
        for i, frame in enumerate(s.frames, start=1):
            _save_png(frame, d / REFERENCE / f"{i:04d}.png")
        doc = {"clip_id": s.clip_id, "dataset": s.dataset, "sequence": s.sequence, "width": s.width,
               "height": s.height, "frame_ids": [str(f) for f in s.frame_ids],
               "c2w": s.relative_c2w().tolist(), "K": np.asarray(s.K).tolist(),
               "convention": "OpenCV camera-to-world, relative to the conditioning camera; K in pixels"}
        if s.sequence in simulated:
            rec = simulated[s.sequence]
            doc["simulation"] = {"scene": rec["scene"], "condition_c2w": rec["c2w"][int(s.indices[0])],
                                 "note": "hidden truth of a simulated dataset: the scene frame (metres)"}
        (d / CAMERAS).write_text(json.dumps(doc, indent=1))
        keys.append(key)
    return keys


def _read_frames(folder: Path) -> list[np.ndarray]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    return [np.asarray(Image.open(p).convert("RGB")) for p in files]


def load_clip(clips: Path, key: str) -> dict[str, Any]:
    d = clips / key
    doc = json.loads((d / CAMERAS).read_text())
    return {"doc": doc, "condition": np.asarray(Image.open(d / CONDITION).convert("RGB")),
            "reference": np.stack(_read_frames(d / REFERENCE)),
            "c2w": np.asarray(doc["c2w"], dtype=np.float64), "K": np.asarray(doc["K"], dtype=np.float64)}


def load_generated(generated: Path, key: str, clip: dict[str, Any]) -> np.ndarray:
    """The generated frames of a clip, checked against its reference (count and size)."""
    folder = generated / key
    if not folder.is_dir():
        raise FileNotFoundError(f"no generated frames for clip {key}: expected images in {folder}")
    frames = _read_frames(folder)
    ref = clip["reference"]
    if len(frames) == len(ref) + 1:
        frames = frames[1:]  # the generator's copy of the conditioning image
    if len(frames) != len(ref):
        raise ValueError(f"{folder} holds {len(frames)} images; clip {key} needs {len(ref)} (the frames after "
                         f"the conditioning image) or {len(ref) + 1} (with it)")
    shapes = {f.shape for f in frames}
    if shapes != {ref.shape[1:]}:
        raise ValueError(f"{folder}: frames are {sorted(shapes)}, the reference is {ref.shape[1:]}; "
                         "generate at the clip's resolution")
    return np.stack(frames)


def score_clip(clips: Path, generated: Path, key: str, config: EvaluationConfig) -> list[dict[str, Any]]:
    """Table I and III rows of one generated clip (a clip that cannot be read: one failed Table I row)."""
    try:
        clip = load_clip(clips, key)
        fake = load_generated(generated, key, clip)
    except (OSError, ValueError) as exc:
        return [row("I", "PSNR", status="failed", note=str(exc), scene_id=key)]
    rows = image_quality_rows(fake, clip["reference"], config, scene_id=key)
    if config.camera_guidance:
        frames = np.concatenate([clip["condition"][None], fake])
        with tempfile.TemporaryDirectory(prefix="navcrafter-colmap-") as work:
            res = pose.camera_guidance_precision(frames, clip["c2w"], clip["K"][0], work, scale="farthest",
                                                 num_threads=2)
        note = f"COLMAP (known K) on the conditioning image (frame 0) and the {len(fake)} frames after it"
        rows += pose_error_rows([("", res, np.arange(len(frames)))], note, scene_id=key)
    return rows


def clip_distribution_rows(clips: Path, generated: Path, keys: list[str],
                           config: EvaluationConfig) -> list[dict[str, Any]]:
    """FID over all frames and FVD over all clips (when the weights are there)."""

    def load() -> tuple[list[np.ndarray], list[np.ndarray]]:
        real, fake = [], []
        for key in keys:
            try:
                clip = load_clip(clips, key)
                fake.append(load_generated(generated, key, clip))
                real.append(clip["reference"])
            except (OSError, ValueError):
                continue
        return real, fake

    return frechet_rows(load, config)


def clip_keys(clips: str | Path) -> list[str]:
    clips = Path(clips)
    if not clips.is_dir():
        raise FileNotFoundError(f"{clips} is not a folder of clips; make one with `navcrafter dataset-clips`")
    keys = sorted(p.name for p in clips.iterdir() if (p / CAMERAS).is_file())
    if not keys:
        raise FileNotFoundError(f"{clips} holds no clips (folders with {CAMERAS}); make them with "
                                "`navcrafter dataset-clips`")
    return keys


def generator_backend(generated: Path, keys: list[str]) -> str:
    """The backend that made the clips' frames when ``navcrafter generate-clips`` made them all with one
    (``simulation`` or ``onnx``, from their ``generation.json``), else ``external``."""
    seen = set()
    for key in keys:
        path = Path(generated) / key / GENERATION
        seen.add(json.loads(path.read_text())["settings"]["backend"] if path.is_file() else "external")
    return seen.pop() if len(seen) == 1 else "external"

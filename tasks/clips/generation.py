"""Generate frames for dataset clips with the configured synthesizer (``navcrafter generate-clips``).

A dataset clip (``tasks/clips/dataset.py``: a conditioning image, the 14 ground-truth frames after it and the 15
cameras) asks for a video along its cameras. Wan-based synthesizers make ``4k + 1`` frames, so the camera path is
extended to ``generation_frames(T)`` poses, the smallest ``4k + 1 >= T`` (17 for the paper's 15: the conditioning
frame + 14): the poses after the clip's last continue its last relative motion (constant velocity, the last
step's rotation and translation repeated). Of the video the first ``T`` frames are kept and written as
``<generated>/<clip>/0001.png ... 00T.png`` (``0001`` is the model's frame 0, its copy of the conditioning image,
which ``evaluate-clips`` drops), with ``generation.json`` (what made them) and ``cloud.npz`` (the conditioning
image's point cloud the synthesizer was given, which the Table IV fit of ``evaluate-clips`` starts from).

Frames and point cloud (the synthesizer's ``SynthesisRequest``): the world is the conditioning camera's frame in
the clip's units; the conditioning image is lifted by the backend's geometry role like a scene's input photo
(``tasks/geometry.py``). A geometry model's depth has its own scale, the clip's cameras the dataset's: the cloud is
taken as being in the clip's units, which holds for metric depth on a metric dataset (DL3DV, Tanks and Temples
COLMAP models are not metric either, nor is RealEstate10K's ORB-SLAM scale: there the point-cloud conditioning
of the NavCrafter control is at a mismatched scale, a limit of the protocol, stated in ``generation.json``).
In simulation the simulated geometry's scale is known and divided out (standing for a metric model).

Backends:

* ``simulation``: only clips of a simulated dataset (``navcrafter simulate-datasets`` / ``models/simulation/
  datasets.py``, whose ``cameras.json`` carries the scene's hidden truth): the honest simulated video model
  (``models/simulation/backend.py``: drift from the requested cameras, hallucination where the conditioning image
  saw nothing, breakdown near surfaces) renders the clip. A real dataset's clip fails with a message saying so.
* ``onnx``: the exported NavCrafter camera-controlled synthesizer (``--model-dir``), exported for
  ``synthesis.num_frames`` = ``generation_frames(T)`` frames at the clip's size. The public Fun-Camera model is
  not built yet (README, "Not built").

Clips whose ``generation.json`` records the same settings are skipped (a batch resumes); a clip that fails is
reported and the others still run.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from navcrafter.models.camera.cameras import Intrinsics, invert_pose
from navcrafter.models.roles import SynthesisRequest
from navcrafter.models.simulation import LABEL as SIM_LABEL
from navcrafter.models.simulation.backend import SimulationError, SimulationTruth
from navcrafter.schemas.clips import CLOUD, GENERATION, GENERATION_VERSION
from navcrafter.schemas.config import RunConfig
from navcrafter.tasks.backends import create_backend
from navcrafter.tasks.clips.dataset import load_clip
from navcrafter.tasks.geometry import view_cloud


def generation_frames(n: int) -> int:
    """The smallest ``4k + 1 >= n``: the frame counts a Wan video model makes (``n`` = the clip's cameras)."""
    if n < 1:
        raise ValueError(f"a clip needs at least one camera, got {n}")
    return 4 * ((n - 1 + 3) // 4) + 1


def extend_path(c2w: np.ndarray, n: int) -> np.ndarray:
    """``c2w`` [T, 4, 4] continued to ``n`` poses by repeating its last relative motion (constant velocity)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    if n <= len(c2w):
        return c2w[:n].copy()
    step = invert_pose(c2w[-2]) @ c2w[-1] if len(c2w) >= 2 else np.eye(4)
    out = [*c2w]
    for _ in range(n - len(c2w)):
        out.append(out[-1] @ step)
    return np.stack(out)


def clip_seed(key: str, seed: int) -> int:
    """A clip's seed: stable across runs and independent of which other clips are generated."""
    return int.from_bytes(hashlib.sha256(f"{seed}/{key}".encode()).digest()[:4], "little")


def settings(config: RunConfig) -> dict[str, Any]:
    """What decides a clip's frames: the backend and its model settings (``generation.json`` records them)."""
    out: dict[str, Any] = {"version": GENERATION_VERSION, "backend": config.backend, "seed": config.seed}
    if config.backend == "simulation":
        out["simulation"] = config.simulation.model_dump(mode="json")
    else:
        out["model_dir"] = str(Path(config.model_dir).resolve()) if config.model_dir else None
        out["synthesis"] = config.synthesis.model_dump(mode="json")
    return out


def _backend(config: RunConfig, doc: dict[str, Any], key: str, height: int, width: int, K: np.ndarray):

    if config.backend != "simulation":
        return create_backend(config)

    sim = doc.get("simulation")
    if sim is None:
        raise SimulationError(
            f"clip {key} is not from a simulated dataset (its cameras.json has no 'simulation' record): the simulation "
            "backend can only generate for clips of `navcrafter simulate-datasets`; real clips need an exported "
            "synthesizer and `--backend onnx --model-dir DIR`")
    truth = SimulationTruth.from_record({"scene": sim["scene"], "photo_c2w": sim["condition_c2w"],
                                         "work_intrinsics": Intrinsics.from_matrix(K, width, height).to_dict()},
                                        world_scale=1.0)
    return create_backend(config, simulation_truth=truth)


def generate_clip(clips: str | Path, generated: str | Path, key: str, config: RunConfig) -> dict[str, Any]:
    """Generate (or keep, when already made with the same settings) the frames of clip ``key``; returns its
    ``generation.json`` record (``"skipped": True`` when it was already there)."""

    folder = Path(generated) / key
    want = settings(config)
    done = folder / GENERATION
    if done.is_file():
        rec = json.loads(done.read_text())
        if rec.get("settings") == want:
            return {**rec, "skipped": True}
    clip = load_clip(Path(clips), key)
    cond, c2w, K = clip["condition"], clip["c2w"], clip["K"]
    H, W = cond.shape[:2]
    T = len(c2w)
    n = generation_frames(T)
    seed = clip_seed(key, config.seed)
    backend = _backend(config, clip["doc"], key, H, W, K[0])

    pred = backend.geometry.predict(cond[None], seed=seed, hint_c2w=np.eye(4)[None])
    depth = pred.depth[0].astype(np.float64)
    if backend.is_simulation:  # the simulated geometry's own scale, known here: a metric model's depth
        depth = depth / float(pred.extras["simulation_scale"])
    cloud = view_cloud(cond, depth.astype(np.float32), pred.confidence[0], K[0], config.lift)
    trajectory = extend_path(c2w, n)
    request = SynthesisRequest(image=cond, trajectory=trajectory, intrinsics=Intrinsics.from_matrix(K[0], W, H),
                               cloud_points=cloud.points, cloud_colors=cloud.colors, seed=seed)
    frames = backend.synthesizer.synthesize(request)
    if frames.shape != (n, H, W, 3) or frames.dtype != np.uint8:
        raise ValueError(f"clip {key}: the synthesizer returned {frames.dtype} {frames.shape}, expected uint8 "
                         f"{(n, H, W, 3)}")
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    for i, frame in enumerate(frames[:T], start=1):
        Image.fromarray(frame).save(folder / f"{i:04d}.png")
    np.savez_compressed(folder / CLOUD, points=cloud.points.astype(np.float32), colors=cloud.colors)

    rec = {"clip": key, "settings": want, "generated_frames": n, "kept_frames": T,
           "extension": f"cameras {T + 1}..{n} continue the clip's last relative motion; frames after {T} dropped",
           "cloud": {"points": int(len(cloud)), "units": "the clip's (depth taken as metric in the clip's units)"},
           "label": SIM_LABEL if backend.is_simulation else "learned synthesizer"}
    tmp = folder / (GENERATION + ".tmp")
    tmp.write_text(json.dumps(rec, indent=1))
    tmp.replace(done)  # written last: a clip with generation.json is complete
    return {**rec, "skipped": False}

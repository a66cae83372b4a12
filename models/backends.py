"""Backend selection: which implementation serves the model roles for a run.

``simulation``: procedural ground truth stands in for the learned models (demo images only).
``onnx``: exported models run by onnxruntime from ``model_dir``::

    model_dir/synthesizer/  camera-controlled Wan2.1 I2V (``navcrafter models export-synthesizer``)
    model_dir/geometry/     VGGT-architecture multi-view geometry (``navcrafter models export-geometry``)
    model_dir/monodepth/    MoGe-2-architecture monocular geometry (``navcrafter models export-monodepth``)

Each role is created on first use, so a run that never needs a role (``monodepth`` is only used by
``fit``) does not need its directory. Sessions and checksum verification happen once per process and
model directory. Models exported with random weights (tiny test configs, or full-size architectures for
timing) run like any other, and every output of such a run carries ``RANDOM_WEIGHTS_LABEL``.
"""

from __future__ import annotations

import functools
import threading
from pathlib import Path

from navcrafter.models.roles import Backend
from navcrafter.schemas.config import RunConfig

ROLE_DIRS = {"synthesizer": "synthesizer", "geometry": "geometry", "monodepth": "monodepth", "refiner": "refiner"}
RANDOM_WEIGHTS_LABEL = ("RANDOM WEIGHTS: these models were exported with random weights (test or timing "
                        "configurations); their outputs are noise, not results")
CAMERA_CONTROL_UNTRAINED_LABEL = (
    "CAMERA CONTROL UNTRAINED: the synthesizer is a Wan base exported without trained camera-control weights; "
    "its videos ignore the requested cameras, so the planned cameras that later steps use do not match the frames")
# the short text burnt into frames and figures, by label
BANDS = {RANDOM_WEIGHTS_LABEL: "RANDOM WEIGHTS", CAMERA_CONTROL_UNTRAINED_LABEL: "CAMERA CONTROL UNTRAINED"}


def is_untrained_control(manifest: dict) -> bool:
    """A synthesizer exported from a checkpoint without camera-control weights (``weights.control``)."""
    weights = manifest.get("weights", {})
    return (manifest.get("kind") == "synthesizer" and weights.get("source") == "checkpoint"
            and not weights.get("control"))


class _LazyRole:
    """Creates the role object on first attribute access (under a lock; roles are shared by threads)."""

    def __init__(self, backend: str, factory) -> None:
        self.backend = backend
        self._factory, self._obj, self._lock = factory, None, threading.Lock()

    def _get(self):
        with self._lock:
            if self._obj is None:
                self._obj = self._factory()
            return self._obj

    @property
    def loaded(self) -> bool:
        return self._obj is not None

    def release(self) -> bool:
        """Forget the role object (its onnxruntime sessions are freed once no caller holds it); True if one was
        loaded. The next use creates it again (checksums are verified once per process)."""
        with self._lock:
            was, self._obj = self._obj is not None, None
            return was

    def __getattr__(self, name):
        return getattr(self._get(), name)

    def synthesize(self, request):
        return self._get().synthesize(request)

    def predict(self, *args, **kwargs):
        return self._get().predict(*args, **kwargs)

    def refine(self, *args, **kwargs):
        return self._get().refine(*args, **kwargs)


def role_dir(model_dir: Path, role: str) -> Path:
    return Path(model_dir) / ROLE_DIRS[role]


def model_manifests(model_dir: Path) -> dict[str, dict]:
    """The manifests present under ``model_dir`` (role → manifest), without checksum verification."""
    from navcrafter.models.runtime.onnxio import load_manifest

    out = {}
    for role in ROLE_DIRS:
        d = role_dir(model_dir, role)
        if (d / "manifest.json").is_file():
            out[role] = load_manifest(d, role, verify=False)
    return out


def onnx_problems(config: RunConfig) -> list[str]:
    """What is missing or inconsistent in ``config.model_dir`` for this run (checked before any work)."""
    from navcrafter.models.runtime.onnxio import ModelDirError, load_manifest

    root = Path(config.model_dir)
    if not root.is_dir():
        return [f"model directory {root} does not exist; export models into it with "
                f"`navcrafter models export-all {root}` (see models/runtime/README.md)"]
    needed = (["synthesizer", "geometry"] + (["monodepth"] if config.fit.enabled else [])
              + (["refiner"] if config.fit.enabled and config.refine.enabled else []))
    problems = []
    for role in needed:
        try:
            manifest = load_manifest(role_dir(root, role), role, verify=False)
        except (ModelDirError, ValueError) as exc:
            problems.append(str(exc))
            continue
        if role == "synthesizer":
            want = (config.synthesis.num_frames, config.synthesis.height, config.synthesis.width)
            cfg = manifest.get("config", {})
            have = (cfg.get("num_frames"), cfg.get("height"), cfg.get("width"))
            if None not in have and tuple(have) != want:
                problems.append(
                    f"the synthesizer in {role_dir(root, role)} was exported for {have[0]} frames at "
                    f"{have[2]}x{have[1]}, the run asks for {want[0]} at {want[2]}x{want[1]}: set synthesis."
                    f"num_frames/height/width to match or export it again with those sizes")
            model = cfg.get("model", "navcrafter")
            if model != config.synthesis.model:
                problems.append(
                    f"the synthesizer in {role_dir(root, role)} is {model!r}, the run asks for synthesis.model="
                    f"{config.synthesis.model!r}: set synthesis.model={model!r} or export a {config.synthesis.model!r} "
                    f"synthesizer there (navcrafter models export-synthesizer / export-fun-camera)")
    return problems


def run_label(config: RunConfig) -> str | None:
    """The label every user-facing output of this run must carry, if any."""
    if config.backend == "simulation":
        from navcrafter.models.simulation import LABEL

        return LABEL
    if config.backend == "onnx" and config.model_dir is not None:
        from navcrafter.models.runtime.onnxio import is_random_weights

        manifests = model_manifests(config.model_dir)
        if any(is_random_weights(m) for m in manifests.values()):
            return RANDOM_WEIGHTS_LABEL
        if any(is_untrained_control(m) for m in manifests.values()):
            return CAMERA_CONTROL_UNTRAINED_LABEL
    return None


def run_band(config: RunConfig) -> str | None:
    """The short form of ``run_label`` burnt into the frames of videos and figures ("SIMULATION", ...)."""
    label = run_label(config)
    if label is None:
        return None
    return "SIMULATION" if config.backend == "simulation" else BANDS[label]


@functools.lru_cache(maxsize=8)
def _onnx_backend(model_dir: str, synthesis_key: str) -> Backend:
    from navcrafter.schemas.config import SynthesisConfig

    root = Path(model_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"model directory {root} does not exist; export models into it with "
                                f"`navcrafter models export-all {root}` (see models/runtime/README.md)")
    synthesis = SynthesisConfig.model_validate_json(synthesis_key)

    def synthesizer():
        from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer

        return OnnxSynthesizer(role_dir(root, "synthesizer"), synthesis)

    def geometry():
        from navcrafter.models.geometry.onnx_geometry import OnnxGeometry

        return OnnxGeometry(role_dir(root, "geometry"))

    def mono_depth():
        from navcrafter.models.geometry.onnx_monodepth import OnnxMonoDepth

        return OnnxMonoDepth(role_dir(root, "monodepth"))

    def refiner():
        from navcrafter.models.refiner.onnx_refiner import OnnxRefiner

        return OnnxRefiner(role_dir(root, "refiner"))

    has_refiner = (role_dir(root, "refiner") / "manifest.json").is_file()
    return Backend(name="onnx", synthesizer=_LazyRole("onnx", synthesizer), geometry=_LazyRole("onnx", geometry),
                   mono_depth=_LazyRole("onnx", mono_depth),
                   refiner=_LazyRole("onnx", refiner) if has_refiner else None)


def create_backend(config: RunConfig, simulation_truth=None) -> Backend:
    """The role implementations for one scene.

    ``simulation_truth`` (a ``SimulationTruth``) is required by, and only used by, the simulation
    backend.
    """
    if config.backend == "simulation":
        from navcrafter.models.simulation.backend import SimulationError, simulation_backend

        if simulation_truth is None:
            raise SimulationError(
                "this image has no simulation ground truth: the simulation backend can only explore "
                "demo images made by `navcrafter demo-data` (their ground truth sits in "
                "<folder>/.groundtruth/). Real photos need exported models and `--backend onnx`.")
        return simulation_backend(simulation_truth, config.simulation)
    if config.backend == "onnx":
        return _onnx_backend(str(Path(config.model_dir).resolve()), config.synthesis.model_dump_json())
    raise ValueError(f"unknown backend {config.backend!r}")

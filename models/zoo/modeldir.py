"""An exported model directory: one folder per role, its labels, and the ``onnx`` backend built from it.

``model_dir/synthesizer/`` camera-controlled Wan2.1 I2V (``navcrafter models export-synthesizer``),
``model_dir/geometry/`` VGGT-architecture multi-view geometry (``export-geometry``), ``model_dir/monodepth/``
MoGe-2-architecture monocular geometry (``export-monodepth``), ``model_dir/refiner/`` the Difix-architecture refiner.

Each role is created on first use, so a run that never needs a role (``monodepth`` is only used by ``fit``) does not
need its directory. Sessions and checksum verification happen once per process and model directory. Models exported
with random weights run like any other; ``model_dir_label`` names what every output of such a run must carry.
The run configuration's side (which backend a run uses, its checks) is tasks/backends.py.
"""

from __future__ import annotations

import functools
import threading
from pathlib import Path

from navcrafter.models.geometry.onnx_geometry import OnnxGeometry
from navcrafter.models.geometry.onnx_monodepth import OnnxMonoDepth
from navcrafter.models.refiner.onnx_refiner import OnnxRefiner
from navcrafter.models.roles import Backend
from navcrafter.models.runtime.onnxio import is_random_weights, load_manifest
from navcrafter.models.synthesis.config import SynthesisConfig
from navcrafter.models.synthesis.onnx_synthesizer import OnnxSynthesizer

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
    out = {}
    for role in ROLE_DIRS:
        d = role_dir(model_dir, role)
        if (d / "manifest.json").is_file():
            out[role] = load_manifest(d, role, verify=False)
    return out


def model_dir_label(model_dir: Path) -> str | None:
    """The label every output made with the models in ``model_dir`` must carry (random weights, untrained
    camera control), or None."""
    manifests = model_manifests(model_dir)
    if any(is_random_weights(m) for m in manifests.values()):
        return RANDOM_WEIGHTS_LABEL
    if any(is_untrained_control(m) for m in manifests.values()):
        return CAMERA_CONTROL_UNTRAINED_LABEL
    return None


@functools.lru_cache(maxsize=8)
def onnx_backend(model_dir: str, synthesis_key: str) -> Backend:
    root = Path(model_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"model directory {root} does not exist; export models into it with "
                                f"`navcrafter models export-all {root}` (see models/runtime/README.md)")
    synthesis = SynthesisConfig.model_validate_json(synthesis_key)

    def synthesizer():
        return OnnxSynthesizer(role_dir(root, "synthesizer"), synthesis)

    def geometry():
        return OnnxGeometry(role_dir(root, "geometry"))

    def mono_depth():
        return OnnxMonoDepth(role_dir(root, "monodepth"))

    def refiner():
        return OnnxRefiner(role_dir(root, "refiner"))

    has_refiner = (role_dir(root, "refiner") / "manifest.json").is_file()
    return Backend(name="onnx", synthesizer=_LazyRole("onnx", synthesizer), geometry=_LazyRole("onnx", geometry),
                   mono_depth=_LazyRole("onnx", mono_depth),
                   refiner=_LazyRole("onnx", refiner) if has_refiner else None)



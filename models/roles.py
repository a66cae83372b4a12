"""The four model roles of the pipeline and their data types (see DESIGN.md, "Model roles").

Each backend (``simulation``, ``onnx``) provides objects satisfying these protocols. Tasks only talk
to the protocols, so a backend can be swapped by configuration.

``hint_*`` arguments carry the simulation's hidden truth of the frames: ``hint_c2w`` the world poses at which
they were really taken (the synthesize step's stored truth, which differs from the requested trajectory when the
video model drifts), ``hint_depth`` the depth of what they show (hallucinated content included). Learned
backends ignore them: a real geometry model estimates cameras and depth from pixels. The simulated roles need
them, since their outputs are the truth corrupted like a model's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics


@dataclass
class SynthesisRequest:
    image: np.ndarray  # [H, W, 3] uint8 conditioning image: the view at trajectory[0] (frame 0 of the clip)
    trajectory: np.ndarray  # [T, 4, 4] float64 world c2w; trajectory[0] is the current pose
    intrinsics: Intrinsics  # of the working image and of every synthesized frame
    cloud_points: np.ndarray  # [N, 3] float32 current scene cloud (world)
    cloud_colors: np.ndarray  # [N, 3] uint8
    seed: int
    # The scene's input photo and its world c2w, an extra reference frame for clips that start elsewhere
    # (iteration k >= 2 starts at the previous clip's last pose). None for the first clip (image is the photo).
    reference_image: np.ndarray | None = None  # [H, W, 3] uint8
    reference_c2w: np.ndarray | None = None  # [4, 4] float64


@dataclass
class GeometryPrediction:
    """Feed-forward multi-view geometry (VGGT-style output).

    Cameras and depth are expressed in the frame of the first input view (``c2w[0] = I``) at the
    model's own, unknown scale; lifting aligns them to the scene.
    """

    c2w: np.ndarray  # [S, 4, 4] float64
    K: np.ndarray  # [S, 3, 3] float64
    depth: np.ndarray  # [S, H, W] float32 z-depth, 0 = invalid
    confidence: np.ndarray  # [S, H, W] float32 in [0, 1]
    extras: dict[str, float] = field(default_factory=dict)  # backend diagnostics, stored as attrs


@dataclass
class MonoDepthPrediction:
    """Monocular relative depth: inverse depth up to an unknown scale and shift, plus sky mask."""

    inv_depth: np.ndarray  # [H, W] float32 affine-invariant inverse depth
    sky: np.ndarray  # [H, W] bool


@runtime_checkable
class Synthesizer(Protocol):
    backend: str

    def synthesize(self, request: SynthesisRequest) -> np.ndarray:
        """Frames ``[T, H, W, 3]`` uint8 following ``request.trajectory``."""


@runtime_checkable
class Geometry(Protocol):
    backend: str

    def predict(self, frames: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None,
                hint_depth: list[np.ndarray | None] | None = None) -> GeometryPrediction:
        """Cameras, depth and confidence for frames ``[S, H, W, 3]`` uint8."""


@runtime_checkable
class MonoDepth(Protocol):
    backend: str

    def predict(self, image: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None, hint_depth: np.ndarray | None = None) -> MonoDepthPrediction:
        """Relative inverse depth and sky mask of one image ``[H, W, 3]`` uint8."""


@runtime_checkable
class Refiner(Protocol):
    backend: str

    def refine(self, rendered: np.ndarray, reference: np.ndarray | None, *, seed: int,
               hint_c2w: np.ndarray | None = None, hint_intrinsics: Intrinsics | None = None) -> np.ndarray:
        """A refined version ``[H, W, 3]`` uint8 of a rendered view ``[H, W, 3]`` uint8 (a render of the fitted
        3DGS scene at a novel camera), optionally guided by a ``reference`` real view ``[H, W, 3]`` uint8 (the
        nearest training frame). ``hint_c2w`` [4, 4] is the novel camera (used by the simulation backend only)."""


@dataclass
class Backend:
    """The role implementations used for one scene."""

    name: str
    synthesizer: Synthesizer
    geometry: Geometry
    mono_depth: MonoDepth
    refiner: Refiner | None = None

    @property
    def is_simulation(self) -> bool:
        return self.name == "simulation"

    def release(self) -> list[str]:
        """Drop the loaded models of every role that can reload itself (the onnx backend's lazily created roles),
        so only the running step's models stay in memory; returns the roles released. A role in use by another
        thread finishes with its own reference; the next use loads it again."""
        out = []
        for name in ("synthesizer", "geometry", "mono_depth", "refiner"):
            role = getattr(self, name)
            if hasattr(role, "release") and role.release():
                out.append(name)
        return out

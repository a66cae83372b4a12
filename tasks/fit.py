"""Fit: geometry-aware 3D Gaussian Splatting from the scene's cloud and frames (paper, Sec. III-D).

The place for: initialisation from the fused cloud, monocular depth calibrated to the geometry depth,
DropGaussian, the L1 + LPIPS + depth loss, diffusion refinement of rendered views, and the
``gaussians/`` and ``renders/`` groups. Not built yet: enabling it stops the run before any work.
"""

from __future__ import annotations

from navcrafter.schemas.config import RunConfig
from navcrafter.tasks.common import StepRef

NOT_BUILT = ("3D Gaussian Splatting fitting (fit.enabled) is not built yet; it is tracked as its own "
             "issue. Run with fit.enabled=false.")


def fit(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> StepRef:
    raise NotImplementedError(NOT_BUILT)

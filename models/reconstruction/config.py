"""Settings of lifting frames into the scene cloud (composed into the run config by schemas/config.py)."""

from __future__ import annotations

from pydantic import Field

from navcrafter.models.settings import Section as _Section


class LiftConfig(_Section):
    """Lifting synthesized frames to points and fusing them into the scene cloud."""

    max_views: int = Field(12, ge=1, description="Frames of a clip passed to the geometry model.")
    pixel_stride: int = Field(2, ge=1, description="Unproject every n-th pixel in each direction.")
    confidence_threshold: float = Field(0.5, ge=0, le=1)
    voxel_size: float = Field(0.02, gt=0, description="Fusion voxel edge, in scene units (metres).")
    max_depth: float = Field(50.0, gt=0, description="Ignore predicted depth beyond this.")
    icp: bool = Field(True, description=(
        "Refine each lifted view's pose by ICP against the existing cloud (accepted only with enough overlap "
        "and a small correction); the scale always comes from the reference view."))
    icp_distance: float = Field(0.03, gt=0, description=(
        "ICP correspondence distance, relative to the reference view's median depth."))

"""Synthesize: a video clip along the planned trajectory (the Synthesizer role)."""

from __future__ import annotations

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.roles import SynthesisRequest
from navcrafter.schemas.layout import INGEST, PLAN
from navcrafter.tasks.steps import StepContext


def synthesize(ctx: StepContext) -> dict:
    work = ctx.scene.read(INGEST, None, "work_image")
    plan = ctx.scene.read_all(PLAN, ctx.k)
    cloud = ctx.cloud(ctx.k - 1)
    H, W = work.shape[:2]
    request = SynthesisRequest(image=work, trajectory=plan["trajectory"],
                               intrinsics=Intrinsics.from_matrix(plan["K"], W, H),
                               cloud_points=cloud.points, cloud_colors=cloud.colors, seed=ctx.seed)
    frames = ctx.backend.synthesizer.synthesize(request)
    expected = (len(plan["trajectory"]), H, W, 3)
    if frames.shape != expected or frames.dtype != np.uint8:
        raise ValueError(f"synthesizer returned {frames.dtype} {frames.shape}, expected uint8 {expected}")
    ctx.write("frames", frames)
    return {"num_frames": int(len(frames))}

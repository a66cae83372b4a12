"""Synthesize: a video clip along the planned trajectory (the Synthesizer role)."""

from __future__ import annotations

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.roles import SynthesisRequest
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import INGEST, PLAN, SYNTHESIZE
from navcrafter.tasks.common import StepRef, load_backend, load_cloud, open_store, run_step


def synthesize(store_uri: str, scene_id: str, k: int, config: RunConfig, run_id: str) -> StepRef:
    def body(writer, seed: int, _) -> dict:
        scene = open_store(store_uri).scene(scene_id)
        work = scene.read(INGEST, None, "work_image")
        plan = scene.read_all(PLAN, k)
        cloud = load_cloud(scene, k - 1)
        H, W = work.shape[:2]
        request = SynthesisRequest(image=work, trajectory=plan["trajectory"],
                                   intrinsics=Intrinsics.from_matrix(plan["K"], W, H),
                                   cloud_points=cloud.points, cloud_colors=cloud.colors, seed=seed)
        frames = load_backend(scene, config).synthesizer.synthesize(request)
        expected = (len(plan["trajectory"]), H, W, 3)
        if frames.shape != expected or frames.dtype != np.uint8:
            raise ValueError(f"synthesizer returned {frames.dtype} {frames.shape}, expected uint8 {expected}")
        writer.write("frames", frames)
        return {"num_frames": int(len(frames))}

    return run_step(store_uri, scene_id, SYNTHESIZE, k, config, run_id, body)

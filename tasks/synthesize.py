"""Synthesize: a video clip along the planned trajectory (the Synthesizer role).

The clip is conditioned on the view at its first camera, which an I2V model reproduces as frame 0: for
iteration 1 the working image (the input camera), for k >= 2 the last frame of clip k-1, since iteration k
starts where clip k-1's last frame is estimated to be (``readers.current_pose``). A trajectory that starts anywhere
else has no view to condition on and fails the step. From k >= 2 the working image and the input camera's world
pose come as an extra reference frame (``SynthesisRequest.reference_image`` / ``reference_c2w``).

In simulation mode the step also stores the clip's hidden truth (``true_c2w``, ``true_depth``, ``true_quality``:
where each frame was really taken and what it shows, ``models.simulation.backend.SimulatedClip``), continuing
from the truth of the frame it was conditioned on; only the simulated roles and the ground-truth metrics read it.
"""

from __future__ import annotations

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.roles import SynthesisRequest
from navcrafter.models.simulation.backend import ClipStart
from navcrafter.schemas.layout import INGEST, PLAN, SYNTHESIZE
from navcrafter.tasks.readers import current_pose, input_pose
from navcrafter.tasks.steps import StepContext


def synthesize(ctx: StepContext) -> dict:
    scene, k = ctx.scene, ctx.k
    work = scene.read(INGEST, None, "work_image")
    plan = scene.read_all(PLAN, k)
    cloud = ctx.cloud(k - 1)
    H, W = work.shape[:2]
    # plan k-1 (read by current_pose) keys this step through plan k and synthesize k-1
    start = input_pose(scene) if k == 1 else current_pose(scene, k)
    if not np.allclose(plan["trajectory"][0], start, rtol=1e-6, atol=1e-6):
        where = "the input camera" if k == 1 else f"the estimated last pose of iteration {k - 1}"
        raise ValueError(f"the trajectory of iteration {k} does not start at {where} (first position "
                         f"{np.round(plan['trajectory'][0][:3, 3], 4).tolist()}, expected "
                         f"{np.round(start[:3, 3], 4).tolist()}): the view at its first camera, which the clip "
                         f"is conditioned on, is not available; plan iteration {k} from the current pose")
    if k == 1:
        image, reference = work, {}
    else:
        image = scene.read_rows(SYNTHESIZE, k - 1, "frames", [-1])[0]
        reference = {"reference_image": work, "reference_c2w": input_pose(scene)}
    request = SynthesisRequest(image=image, trajectory=plan["trajectory"],
                               intrinsics=Intrinsics.from_matrix(plan["K"], W, H),
                               cloud_points=cloud.points, cloud_colors=cloud.colors, seed=ctx.seed, **reference)
    attrs = {}
    if ctx.backend.is_simulation:
        attrs["synthesizer_model"] = "simulation"
        clip = ctx.backend.synthesizer.simulate(request, _simulated_start(scene, k))
        frames = clip.frames
        ctx.write_all(true_c2w=clip.true_c2w, true_depth=clip.true_depth.astype(np.float32),
                      true_quality=clip.true_quality.astype(np.float32))
        attrs["simulation_true_fraction"] = float(np.mean(clip.true_quality[1:])) if len(frames) > 1 else 1.0
    else:
        frames = ctx.backend.synthesizer.synthesize(request)
        # which synthesizer made the clip: the model of the exported directory (checked against synthesis.model)
        attrs["synthesizer_model"] = str(getattr(ctx.backend.synthesizer, "model_name", ctx.config.synthesis.model))
    expected = (len(plan["trajectory"]), H, W, 3)
    if frames.shape != expected or frames.dtype != np.uint8:
        raise ValueError(f"synthesizer returned {frames.dtype} {frames.shape}, expected uint8 {expected}")
    ctx.write("frames", frames)
    return {"num_frames": int(len(frames)), **attrs}


def _simulated_start(scene, k: int):
    """Hidden truth of the conditioning image: the input camera for k = 1, else clip k-1's last frame."""

    if k == 1:
        return ClipStart(input_pose(scene))
    if not scene.has(SYNTHESIZE, k - 1, "true_c2w"):
        raise ValueError(f"iter_{k - 1}/synthesize has no simulation truth (written by an older version): "
                         "rerun the scene from iteration 1")
    return ClipStart(scene.read(SYNTHESIZE, k - 1, "true_c2w")[-1],
                     scene.read_rows(SYNTHESIZE, k - 1, "true_depth", [-1])[0],
                     float(scene.read(SYNTHESIZE, k - 1, "true_quality")[-1]))

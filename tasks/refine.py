"""Refine: diffusion refinement of rendered views as extra supervision, then more fitting (paper, Sec. III-D;
the Difix3D+ recipe).

1. **Novel cameras** (``models.gaussians.novelviews``): ``refine.views`` training cameras, evenly spread over the fit's
   training frames, each displaced sideways/up by ``refine.offset`` x the fit's scene scale and turned by up
   to ``refine.angle_deg`` (seeded; a camera never lands closer to the cloud than half its source's
   clearance). Held-out cameras are never used, so the held-out evaluation stays honest.
2. **Render** the fitted Gaussians there (the fit's resolution and intrinsics).
3. **Refine** each render with the backend's Refiner role, given the nearest training frame as reference:
   a Difix-style single-step diffusion model (``onnx`` backend, ``models/refiner``), or the simulation
   stand-in (the render moved toward the true view; ``simulation.refine_strength``).
4. **Fit again**: the fitted Gaussians train ``refine.iterations`` more iterations on the training views plus
   the refined views with the fit's loss (weight ``refine.weight``, 1; with ``refine.depth`` their monocular
   depth calibrated to the scene cloud rendered at the novel camera supervises depth), with the fit's learning rates
   except the position rate, which decays from 10 x to 1 x ``fit.lr_means_final``; density control off;
   DropGaussian as in the fit.
5. **Evaluate** on the fit's held-out frames: ``psnr`` / ``ssim`` (/ ``lpips``) after, ``psnr_before`` /
   ``ssim_before`` from the fit.

Outputs (group ``renders``): the novel cameras, renders, refined views, the refined Gaussians (which the
export step uses when refine is enabled), held-out renders and the loss history.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.gaussians.novelviews import nearest_views, novel_cameras
from navcrafter.models.gaussians.recipe import continue_training, heldout_metrics, history_array, load_lpips
from navcrafter.models.gaussians.train import TrainView, render_model
from navcrafter.models.reconstruction.depthcalib import CalibrationError, calibrate_depth
from navcrafter.models.reconstruction.pointrender import render_points
from navcrafter.models.threads import one_openmp_thread
from navcrafter.schemas.layout import FIT
from navcrafter.tasks.common import load_cloud, logger
from navcrafter.tasks.memory import PeakRSS
from navcrafter.tasks.progress import TrainingProgress
from navcrafter.tasks.readers import load_fit_views, load_gaussians
from navcrafter.tasks.steps import StepContext


class RefinerMissing(RuntimeError):
    """The backend has no Refiner role (no exported refiner model)."""


def refine(ctx: StepContext) -> dict:
    with PeakRSS() as peak, one_openmp_thread():  # torch on this scene's thread alone (models/threads.py)
        out = _refine(ctx)
    return {**out, "peak_rss_mb": peak.mb}


def _refine(ctx: StepContext) -> dict:
    rc, fc, scene, seed = ctx.config.refine, ctx.config.fit, ctx.scene, ctx.seed
    backend = ctx.backend
    if backend.refiner is None:
        raise RefinerMissing(
            f"the {backend.name} backend has no refiner model: export one with `navcrafter models "
            f"export-refiner <model_dir>/refiner ...` (see models/runtime/README.md), or turn refine.enabled off")
    # 1. novel cameras off the trajectory, next to evenly spread training cameras
    fit_attrs = scene.status(FIT).attrs
    g = scene.read_all(FIT)
    model = load_gaussians(scene)
    train_views, test_views = load_fit_views(scene)
    w, h = fit_attrs["resolution"]
    train_idx = np.nonzero(g["train"])[0]
    rng = np.random.default_rng(seed)
    pick = train_idx[np.unique(np.linspace(0, len(train_idx) - 1, min(rc.views, len(train_idx))).round()
                               .astype(int))]
    offset = rc.offset * float(fit_attrs["scene_scale"])
    c2w, source = novel_cameras(g["c2w"], pick, model.means.numpy(), offset=offset, angle_deg=rc.angle_deg,
                                rng=rng)
    if len(c2w) == 0:
        raise ValueError("no novel camera found a free position next to the training cameras; lower "
                         "refine.offset")
    # 2. render there; 3. refine each render, guided by the nearest training frame
    K = np.asarray(g["K"][int(source[0])], dtype=np.float64)
    renders = render_model(model, c2w, np.repeat(K[None], len(c2w), 0), w, h, device=fc.device,
                           renderer=fc.renderer)
    ref_frames = train_idx[nearest_views(c2w, g["c2w"][train_idx])]
    frame_pos = {int(f): j for j, f in enumerate(train_idx)}
    intr = Intrinsics.from_matrix(K, w, h)
    refined = np.empty_like(renders)
    if hasattr(backend.refiner, "observe"):  # the simulated refiner knows what the cloud observed
        backend.refiner.observe(load_cloud(scene, ctx.config.iterations).points)
    for i in range(len(c2w)):
        ref_img = np.round(train_views[frame_pos[int(ref_frames[i])]].image.numpy() * 255).astype(np.uint8)
        refined[i] = backend.refiner.refine(renders[i], ref_img, seed=seed + i, hint_c2w=c2w[i],
                                            hint_intrinsics=intr)
    depth = refined_depth(ctx, refined, c2w, K) if rc.depth and fc.lambda_depth > 0 else [None] * len(c2w)
    extra = [TrainView(torch.from_numpy(refined[i].astype(np.float32) / 255.0),
                       torch.as_tensor(c2w[i], dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32),
                       depth[i], rc.weight) for i in range(len(c2w))]
    # 4. fit again with the refined views; 5. evaluate on the fit's held-out frames
    lpips_model, _ = load_lpips(ctx.config.evaluation)
    t0 = time.perf_counter()
    trainer, result = continue_training(model, train_views + extra, fc, rc, seed, float(fit_attrs["scene_scale"]),
                                        lpips_model, TrainingProgress(ctx.scene_id, "refine", rc.iterations))
    seconds = time.perf_counter() - t0
    gt = np.stack([v.image.numpy() for v in test_views]).astype(np.float64)
    rgb, _ = trainer.evaluate(test_views)
    metrics = heldout_metrics(rgb, gt, lpips_model)
    out = result.model
    ctx.write_all(c2w=c2w, K=K, source_frame=source.astype(np.int32), reference_frame=ref_frames.astype(np.int32),
                  renders=renders, refined=refined)
    for name, t in out.tensors().items():
        ctx.write(name, t.numpy())
    ctx.write_all(holdout_renders=np.round(rgb * 255).astype(np.uint8), history=history_array(result.history))
    return {**metrics, "psnr_before": fit_attrs["psnr"], "ssim_before": fit_attrs["ssim"],
            "lpips_before": fit_attrs.get("lpips"), "n_views": len(c2w), "n_gaussians": len(out),
            "n_depth_views": sum(d is not None for d in depth),
            "refiner": backend.refiner.backend, "train_seconds": seconds}


def refined_depth(ctx: StepContext, refined: np.ndarray, c2w: np.ndarray, K: np.ndarray) -> list[torch.Tensor | None]:
    """Depth targets of the refined views, made as the fit makes those of its frames without a lift: the MonoDepth
    role's inverse depth of the refined image calibrated to the scene cloud rendered at the novel camera (None
    where the calibration finds too little to align to)."""
    fc, cloud = ctx.config.fit, ctx.cloud(ctx.config.iterations)
    h, w = refined.shape[1:3]
    out: list[torch.Tensor | None] = []
    for i in range(len(refined)):
        pr = render_points(cloud.points, c2w[i], K, h, w, point_size=fc.depth_point_size)
        # hint: the novel camera (simulation renders what the refined view shows there; real models ignore it)
        mono = ctx.backend.mono_depth.predict(refined[i], seed=ctx.seed + 7919 + i, hint_c2w=c2w[i])
        try:
            cal = calibrate_depth(mono.inv_depth, pr.depth, pr.mask, mono.sky)
        except CalibrationError as exc:
            logger().warning("scene %s: no depth supervision for refined view %d: %s", ctx.scene_id[:12], i, exc)
            out.append(None)
            continue
        out.append(torch.from_numpy(np.ascontiguousarray(cal.depth, dtype=np.float32)))
    return out

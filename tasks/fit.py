"""Fit: geometry-aware 3D Gaussian Splatting from the scene's cloud and frames (paper, Sec. III-D).

* **Frames and cameras.** Every synthesized frame of iterations 1..N at its *estimated* camera, as the paper
  fits on the geometry model's cameras (``readers.camera_path(cameras="estimated")``: the lift step's aligned
  poses, interpolated as a correction of the plan between the frames it lifted), with the planned intrinsics. A
  video model does not follow the requested cameras exactly, so the plan is not the frames' camera. Frame 0 of
  clip k >= 2 repeats the last frame of clip k-1 (same pose) and is left out, so no held-out camera also
  appears in training. Every ``fit.holdout_every``-th frame of that sequence (0, n, 2n, ...) is held out; of
  the others every ``fit.train_stride``-th is trained on (1: all).
* **Initialisation** from the final cloud (``iter_N/lift``; ``fit.max_init_points`` caps it by a seeded
  subset): one isotropic Gaussian per point (3DGS).
* **Depth supervision.** For each training frame the backend's MonoDepth role gives relative inverse depth and
  a sky mask; ``models.reconstruction.depthcalib`` aligns it (confident / valid, non-sky pixels; trimmed least
  squares) to a multi-view depth: the lift step's geometry depth on the frames it ran the geometry model on, and with
  ``fit.depth_views = "all"`` (default) the scene cloud rendered into the other frames (z-buffered points of
  size ``fit.depth_point_size``). The calibrated depth supervises the rendered expected depth
  (``lambda_depth``); the targets are stored (``depth_targets``) for the refine step.
* **Loss** L1 + ``lambda_lpips`` LPIPS + ``lambda_depth`` depth (the paper's unit weights, depth in inverse
  depth; ``fit.loss``), with DropGaussian (``models.gaussians.train``; the recipe around it:
  ``models.gaussians.recipe``).
  LPIPS needs the official weights (``evaluation.weights_dir``); without them the term is skipped, held-out
  LPIPS is not reported, and ``lpips_note`` says why. It is never computed with a random network.
* **Device and renderer** (``fit.device``, ``fit.renderer``; ``models.gaussians.renderer``): by default the fit
  trains on CUDA when torch sees a GPU, rendering with gsplat when it is installed (``pip install
  navcrafter[cuda]``) and with our PyTorch rasterizer otherwise; on the CPU with our compiled kernels
  (``fit.threads``). Results (model,
  renders, metrics) come back to the CPU; the attrs record the device and renderer used.
* **Progress**: iteration, loss terms and Gaussian count are logged about ten times per fit (the CLI and the
  task run's log), and a ``fit-<id12>`` progress artifact follows the iterations in the dashboard
  (``tasks/progress.py``).
* **Outputs** (group ``gaussians``): the Gaussians, the frames' cameras, the hold-out and training masks,
  held-out renders, depth targets and calibrations, the loss history; attrs: held-out PSNR / SSIM (/ LPIPS),
  the initial model's held-out PSNR (``init_psnr``), counts and timings, and the step's peak resident memory
  (``peak_rss_mb``, ``tasks/memory.py``: sampled while it runs; process-wide, so scenes fitted at the same time
  in one worker share it). Only one clip's frames are held at full resolution at a time.

The diffusion refinement of rendered views and the fitting again with them is the next step, ``tasks/refine.py``.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.recipe import (
    fit_size,
    heldout_metrics,
    history_array,
    init_subset,
    load_lpips,
    resize_depth,
    resize_image,
    scene_scale,
)
from navcrafter.models.gaussians.train import GaussianTrainer, TrainView
from navcrafter.models.metrics.image import psnr
from navcrafter.models.reconstruction.depthcalib import CalibrationError, calibrate_depth
from navcrafter.models.reconstruction.pointrender import render_points
from navcrafter.models.threads import one_openmp_thread
from navcrafter.schemas.layout import LIFT, SYNTHESIZE
from navcrafter.tasks.common import logger
from navcrafter.tasks.memory import PeakRSS
from navcrafter.tasks.progress import TrainingProgress
from navcrafter.tasks.readers import camera_path, frame_truth
from navcrafter.tasks.steps import StepContext


def fit(ctx: StepContext) -> dict:
    with PeakRSS() as peak, one_openmp_thread():  # torch's kernels on this scene's thread alone (models/threads.py)
        out = _fit(ctx)
    return {**out, "peak_rss_mb": peak.mb}


def _fit(ctx: StepContext) -> dict:
    cfg, N, scene, seed = ctx.config.fit, ctx.config.iterations, ctx.scene, ctx.seed
    path = camera_path(scene, ctx.config, cameras="estimated").distinct()
    refs, c2w, K_full = path.refs, path.c2w, path.K
    H, W = scene.read_rows(SYNTHESIZE, 1, "frames", [0]).shape[1:3]
    h, w = fit_size(H, W, cfg.resolution)
    K = np.stack([path.intrinsics(f).resize(w, h).K for f in range(len(path))])
    holdout = (np.arange(len(refs)) % cfg.holdout_every) == 0
    if holdout.all() or not holdout.any():
        raise ValueError(f"{len(refs)} frames cannot be split with holdout_every={cfg.holdout_every}")

    train_idx, test_idx = np.nonzero(~holdout)[0][::cfg.train_stride], np.nonzero(holdout)[0]
    cloud = ctx.cloud(N)

    # 1. per clip (one clip's frames at full resolution in memory at a time): the views at the fit's resolution
    #    and the calibrated monocular depth of the training frames, against the lift step's geometry depth where
    #    it ran on the frame, else (depth_views="all") against the scene cloud rendered into the frame
    depth_for: dict[int, np.ndarray] = {}
    calib_rows = []
    images: dict[int, np.ndarray] = {}
    is_train = np.zeros(len(refs), dtype=bool)
    is_train[train_idx] = True
    for k in range(1, N + 1):
        frames = scene.read(SYNTHESIZE, k, "frames")
        lift = scene.read_all(LIFT, k)
        lift_depth = {int(i): (lift["depth"][j], lift["confidence"][j]) for j, i in enumerate(lift["view_index"])}
        for f in np.nonzero([r[0] == k for r in refs])[0]:
            f = int(f)
            if not (is_train[f] or holdout[f]):
                continue
            img = frames[refs[f][1]]
            images[f] = resize_image(img, h, w).astype(np.float32) / 255.0
            if not is_train[f]:
                continue
            if refs[f][1] in lift_depth:
                d_v, conf = lift_depth[refs[f][1]]
                valid, source = conf >= cfg.depth_confidence, 0
            elif cfg.depth_views == "all":
                pr = render_points(cloud.points, c2w[f], K_full[f], H, W, point_size=cfg.depth_point_size)
                d_v, valid, source = pr.depth, pr.mask, 1
            else:
                continue
            true_c2w, true_depth = frame_truth(scene, k, [refs[f][1]])  # hints of the simulated role only
            mono = ctx.backend.mono_depth.predict(img, seed=seed + f, hint_c2w=true_c2w, hint_depth=true_depth[0])
            try:
                cal = calibrate_depth(mono.inv_depth, d_v, valid, mono.sky)
            except CalibrationError as exc:
                logger().warning("scene %s: no depth supervision for frame %s: %s", ctx.scene_id[:12], refs[f], exc)
                continue
            depth_for[f] = resize_depth(cal.depth, h, w)
            calib_rows.append([f, cal.scale, cal.bias, cal.inlier_fraction, cal.sigma, source])
        del frames, lift, lift_depth
    calib_rows.sort(key=lambda r: r[0])

    # 2. the views, the initial Gaussians from the cloud
    def view(f: int) -> TrainView:
        d = depth_for.get(f)
        return TrainView(torch.from_numpy(images.pop(f)), torch.as_tensor(c2w[f], dtype=torch.float32),
                         torch.as_tensor(K[f], dtype=torch.float32),
                         None if d is None else torch.from_numpy(np.ascontiguousarray(d, dtype=np.float32)))

    train_views, test_views = [view(f) for f in train_idx], [view(f) for f in test_idx]
    pts, cols = init_subset(cloud.points, cloud.colors, cfg.max_init_points, seed)
    if len(pts) == 0:
        raise ValueError("the scene cloud is empty; nothing to initialise the Gaussians from")
    init = GaussianModel.from_point_cloud(pts, cols, sh_degree=cfg.sh_degree)
    scale = scene_scale(c2w, pts)

    # 3. train, then evaluate on the held-out frames
    lpips_model, lpips_note = load_lpips(ctx.config.evaluation)  # held-out LPIPS whenever the weights exist
    lam_lpips = cfg.lambda_lpips if lpips_model is not None else 0.0
    trainer = GaussianTrainer(init, train_views, cfg, scene_scale=scale, seed=seed, lambda_lpips=lam_lpips,
                              perceptual=lpips_model if lam_lpips > 0 else None)
    gt = np.stack([v.image.numpy() for v in test_views]).astype(np.float64)
    init_rgb, _ = trainer.evaluate(test_views)
    t0 = time.perf_counter()
    result = trainer.train(TrainingProgress(ctx.scene_id, "fit", cfg.iterations))
    train_seconds = time.perf_counter() - t0
    rgb, _ = trainer.evaluate(test_views)
    model = result.model
    metrics = heldout_metrics(rgb, gt, lpips_model)

    # 4. outputs
    for name, t in model.tensors().items():
        ctx.write(name, t.numpy())
    train_mask = np.zeros(len(refs), dtype=bool)
    train_mask[train_idx] = True
    depth_targets = np.zeros((len(refs), h, w), dtype=np.float32)
    for f, d in depth_for.items():
        depth_targets[f] = d
    hist = result.history
    ctx.write_all(frame_ref=np.asarray(refs, dtype=np.int32).reshape(-1, 2), c2w=c2w, K=K.astype(np.float64),
                  holdout=holdout, train=train_mask, holdout_renders=np.round(rgb * 255).astype(np.uint8),
                  depth_targets=depth_targets,
                  depth_calibration=np.asarray(calib_rows, dtype=np.float64).reshape(-1, 6),
                  history=history_array(hist))
    return {**metrics, "lpips_note": lpips_note, "n_gaussians": len(model), "sh_degree": model.sh_degree,
            "resolution": [w, h], "holdout_every": cfg.holdout_every, "n_train": len(train_views),
            "n_holdout": len(test_views), "init_psnr": float(np.mean(psnr(init_rgb, gt))),
            "scene_scale": scale, "train_seconds": train_seconds, "final_loss": float(hist["loss"][-1]),
            "n_depth_views": len(calib_rows),
            "n_depth_views_cloud": sum(1 for r in calib_rows if r[5] == 1), "lambda_lpips_used": lam_lpips,
            "device": str(trainer.device), "renderer": trainer.renderer,
            "densify": {k: v for k, v in result.strategy_state.items() if k.startswith("n_")}}

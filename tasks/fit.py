"""Fit: geometry-aware 3D Gaussian Splatting from the scene's cloud and frames (paper, Sec. III-D).

* **Frames and cameras.** Every synthesized frame of iterations 1..N at the camera it was synthesized for:
  the planned pose (``iter_k/plan`` trajectory) and intrinsics. The synthesizer is camera-controlled, so
  these are its cameras; the lift step's poses are the geometry model's re-estimates of a subset. Frame 0 of
  clip k >= 2 repeats the last frame of clip k-1 (same pose) and is left out, so no held-out camera also
  appears in training. Every ``fit.holdout_every``-th frame of that sequence (0, n, 2n, ...) is held out; of
  the others every ``fit.train_stride``-th is trained on (1: all).
* **Initialisation** from the final cloud (``iter_N/lift``; ``fit.max_init_points`` caps it by a seeded
  subset): one isotropic Gaussian per point (3DGS).
* **Depth supervision.** For each training frame the backend's MonoDepth role gives relative inverse depth and
  a sky mask; ``models.depthcalib`` aligns it (confident / valid, non-sky pixels; trimmed least squares) to a
  multi-view depth: the lift step's geometry depth on the frames it ran the geometry model on, and with
  ``fit.depth_views = "all"`` (default) the scene cloud rendered into the other frames (z-buffered points of
  size ``fit.depth_point_size``). The calibrated depth supervises the rendered expected depth
  (``lambda_depth``); the targets are stored (``depth_targets``) for the refine step.
* **Loss** L1 + ``lambda_lpips`` LPIPS + ``lambda_depth`` depth, with DropGaussian (``models.gaussians.train``).
  LPIPS needs the official weights (``evaluation.weights_dir``); without them the term is skipped, held-out
  LPIPS is not reported, and ``lpips_note`` says why. It is never computed with a random network.
* **Device and renderer** (``fit.device``, ``fit.renderer``; ``models.gaussians.backend``): by default the fit
  trains on CUDA when torch sees a GPU, rendering with gsplat when it is installed (``pip install
  navcrafter[cuda]``) and with our PyTorch rasterizer otherwise; on the CPU always with ours. Results (model,
  renders, metrics) come back to the CPU; the attrs record the device and renderer used.
* **Progress**: iteration, loss terms and Gaussian count are logged about ten times per fit (the CLI and the
  task run's log), and a ``fit-<id12>`` progress artifact follows the iterations in the dashboard
  (``tasks/progress.py``).
* **Outputs** (group ``gaussians``): the Gaussians, the frames' cameras, the hold-out and training masks,
  held-out renders, depth targets and calibrations, the loss history; attrs: held-out PSNR / SSIM (/ LPIPS),
  the initial model's held-out PSNR (``init_psnr``), counts and timings.

The diffusion refinement of rendered views and the fitting again with them is the next step, ``tasks/refine.py``.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from PIL import Image

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.train import GaussianTrainer, TrainConfig, TrainView
from navcrafter.models.metrics.image import psnr, ssim
from navcrafter.models.reconstruction.depthcalib import CalibrationError, calibrate_depth
from navcrafter.models.reconstruction.pointrender import render_points
from navcrafter.schemas.config import FitConfig, RunConfig
from navcrafter.schemas.layout import FIT, LIFT, PLAN, SYNTHESIZE, StepSpec
from navcrafter.tasks.common import StepRef, load_backend, load_cloud, logger, open_store, run_step
from navcrafter.tasks.progress import TrainingProgress


def train_config(cfg: FitConfig, seed: int, lambda_lpips: float | None = None) -> TrainConfig:
    fields = {k: getattr(cfg, k) for k in TrainConfig.__dataclass_fields__ if k not in ("seed", "background")
              and hasattr(cfg, k)}
    if lambda_lpips is not None:
        fields["lambda_lpips"] = lambda_lpips
    return TrainConfig(**fields, seed=int(seed % (2**31)))


def fit_size(height: int, width: int, resolution: int | None) -> tuple[int, int]:
    """(h, w) of the fit: the longer side ``resolution`` (aspect kept), or the frames' own size."""
    if resolution is None or resolution >= max(height, width):
        return height, width
    s = resolution / max(height, width)
    return max(1, round(height * s)), max(1, round(width * s))


def resize_image(img: np.ndarray, h: int, w: int) -> np.ndarray:
    if img.shape[:2] == (h, w):
        return img
    return np.asarray(Image.fromarray(img).resize((w, h), Image.Resampling.BOX))


def resize_depth(depth: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resampling (no mixing of valid and invalid depth)."""
    if depth.shape == (h, w):
        return depth
    rows = np.minimum(((np.arange(h) + 0.5) * depth.shape[0] / h).astype(int), depth.shape[0] - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * depth.shape[1] / w).astype(int), depth.shape[1] - 1)
    return depth[rows[:, None], cols[None, :]]


def frame_sequence(scene, iterations: int) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray]:
    """(iteration, frame) of every distinct frame, their planned c2w [F, 4, 4] and K [F, 3, 3] (frame size)."""
    refs, c2ws, Ks = [], [], []
    for k in range(1, iterations + 1):
        traj, K = scene.read(PLAN, k, "trajectory"), scene.read(PLAN, k, "K")
        for i in range(0 if k == 1 else 1, len(traj)):
            refs.append((k, i))
            c2ws.append(traj[i])
            Ks.append(K)
    return refs, np.asarray(c2ws, dtype=np.float64), np.asarray(Ks, dtype=np.float64)


def scene_scale(c2w: np.ndarray, points: np.ndarray) -> float:
    """The scale 3DGS's learning rate and size thresholds refer to. 3DGS uses the cameras' extent, which
    assumes cameras around the scene; exploration cameras move little, so this is the median distance from
    the cameras' centroid to the cloud (the scene's radius as the cameras see it)."""
    centre = c2w[:, :3, 3].mean(axis=0)
    d = np.linalg.norm(np.asarray(points, dtype=np.float64) - centre, axis=1)
    return float(np.median(d)) if len(d) else 1.0


def load_lpips(config: RunConfig):
    """(LPIPS model or None, note)."""
    from navcrafter.models.metrics.evalnets.lpips import LPIPS
    from navcrafter.models.metrics.evalnets.weights import MetricUnavailable

    try:
        model = LPIPS.from_pretrained(config.evaluation.lpips_net, config.evaluation.weights_dir)
    except MetricUnavailable as exc:
        return None, (f"LPIPS loss term skipped and held-out LPIPS not reported: the official weights are "
                      f"missing ({exc})")
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval(), f"LPIPS-{config.evaluation.lpips_net} (official weights)"


def fit(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> StepRef:
    cfg, N = config.fit, config.iterations
    if N < 1:
        raise ValueError("the fit needs at least one synthesized clip (iterations >= 1)")

    def body(writer, seed: int, _) -> dict:
        scene = open_store(store_uri).scene(scene_id)
        refs, c2w, K_full = frame_sequence(scene, N)
        frames = {k: scene.read(SYNTHESIZE, k, "frames") for k in range(1, N + 1)}
        H, W = frames[1].shape[1:3]
        h, w = fit_size(H, W, cfg.resolution)
        K = np.stack([Intrinsics.from_matrix(k_, W, H).resize(w, h).K for k_ in K_full])
        holdout = (np.arange(len(refs)) % cfg.holdout_every) == 0
        if holdout.all() or not holdout.any():
            raise ValueError(f"{len(refs)} frames cannot be split with holdout_every={cfg.holdout_every}")

        train_idx, test_idx = np.nonzero(~holdout)[0][::cfg.train_stride], np.nonzero(holdout)[0]
        cloud = load_cloud(scene, N)

        # calibrated monocular depth of the training frames: against the lift step's geometry depth where it ran
        # on the frame, else (depth_views="all") against the scene cloud rendered into the frame
        backend = load_backend(scene, config)
        lift_depth = {}
        for k in range(1, N + 1):
            lift = scene.read_all(LIFT, k)
            for j, i in enumerate(lift["view_index"]):
                lift_depth[(k, int(i))] = (lift["depth"][j], lift["confidence"][j])
        depth_for: dict[int, np.ndarray] = {}
        calib_rows = []
        for f in train_idx:
            ref = refs[f]
            if ref in lift_depth:
                d_v, conf = lift_depth[ref]
                valid, source = conf >= cfg.depth_confidence, 0
            elif cfg.depth_views == "all":
                pr = render_points(cloud.points, c2w[f], K_full[f], H, W, point_size=cfg.depth_point_size)
                d_v, valid, source = pr.depth, pr.mask, 1
            else:
                continue
            img = frames[ref[0]][ref[1]]
            mono = backend.mono_depth.predict(img, seed=seed + int(f), hint_c2w=c2w[f][None])
            try:
                cal = calibrate_depth(mono.inv_depth, d_v, valid, mono.sky)
            except CalibrationError as exc:
                logger().warning("scene %s: no depth supervision for frame %s: %s", scene_id[:12], ref, exc)
                continue
            depth_for[int(f)] = resize_depth(cal.depth, h, w)
            calib_rows.append([f, cal.scale, cal.bias, cal.inlier_fraction, cal.sigma, source])

        def view(f: int) -> TrainView:
            img = resize_image(frames[refs[f][0]][refs[f][1]], h, w).astype(np.float32) / 255.0
            d = depth_for.get(f)
            return TrainView(torch.from_numpy(img), torch.as_tensor(c2w[f], dtype=torch.float32),
                             torch.as_tensor(K[f], dtype=torch.float32),
                             None if d is None else torch.from_numpy(np.ascontiguousarray(d, dtype=np.float32)))

        train_views, test_views = [view(f) for f in train_idx], [view(f) for f in test_idx]

        pts, cols = cloud.points, cloud.colors
        if cfg.max_init_points is not None and len(pts) > cfg.max_init_points:
            rng = np.random.default_rng(seed)
            keep = np.sort(rng.choice(len(pts), cfg.max_init_points, replace=False))
            pts, cols = pts[keep], cols[keep]
        if len(pts) == 0:
            raise ValueError("the scene cloud is empty; nothing to initialise the Gaussians from")
        init = GaussianModel.from_point_cloud(pts, cols, sh_degree=cfg.sh_degree)
        scale = scene_scale(c2w, pts)

        lpips_model, lpips_note = load_lpips(config)  # held-out LPIPS whenever the weights exist
        lam_lpips = cfg.lambda_lpips if lpips_model is not None else 0.0
        tcfg = train_config(cfg, seed, lambda_lpips=lam_lpips)
        trainer = GaussianTrainer(init, train_views, tcfg, scene_scale=scale,
                                  perceptual=lpips_model if lam_lpips > 0 else None)
        gt = np.stack([v.image.numpy() for v in test_views]).astype(np.float64)
        init_rgb, _ = trainer.evaluate(test_views)
        t0 = time.perf_counter()
        result = trainer.train(TrainingProgress(scene_id, "fit", tcfg.iterations))
        train_seconds = time.perf_counter() - t0
        rgb, _ = trainer.evaluate(test_views)
        model = result.model
        metrics = heldout_metrics(rgb, gt, lpips_model)
        for name, t in model.tensors().items():
            writer.write(name, t.numpy())
        writer.write("frame_ref", np.asarray(refs, dtype=np.int32).reshape(-1, 2))
        writer.write("c2w", c2w)
        writer.write("K", K.astype(np.float64))
        writer.write("holdout", holdout)
        train_mask = np.zeros(len(refs), dtype=bool)
        train_mask[train_idx] = True
        writer.write("train", train_mask)
        writer.write("holdout_renders", np.round(rgb * 255).astype(np.uint8))
        depth_targets = np.zeros((len(refs), h, w), dtype=np.float32)
        for f, d in depth_for.items():
            depth_targets[f] = d
        writer.write("depth_targets", depth_targets)
        writer.write("depth_calibration", np.asarray(calib_rows, dtype=np.float64).reshape(-1, 6))
        hist = result.history
        writer.write("history", history_array(hist))
        return {**metrics, "lpips_note": lpips_note, "n_gaussians": len(model), "sh_degree": model.sh_degree,
                "resolution": [w, h], "holdout_every": cfg.holdout_every, "n_train": len(train_views),
                "n_holdout": len(test_views), "init_psnr": float(np.mean(psnr(init_rgb, gt))),
                "scene_scale": scale, "train_seconds": train_seconds, "final_loss": float(hist["loss"][-1]),
                "n_depth_views": len(calib_rows),
                "n_depth_views_cloud": sum(1 for r in calib_rows if r[5] == 1), "lambda_lpips_used": lam_lpips,
                "device": str(trainer.device), "renderer": trainer.renderer,
                "densify": {k: v for k, v in result.strategy_state.items() if k.startswith("n_")}}

    return run_step(store_uri, scene_id, FIT, None, config, run_id, body)


def heldout_metrics(rgb: np.ndarray, gt: np.ndarray, lpips_model=None) -> dict:
    """Mean PSNR / SSIM (and LPIPS with its official model, else None) of renders against held-out frames."""
    metrics = {"psnr": float(np.mean(psnr(rgb, gt))), "ssim": float(np.mean(ssim(rgb, gt))), "lpips": None}
    if lpips_model is not None:
        from navcrafter.models.metrics.evalnets.lpips import lpips_distance

        metrics["lpips"] = float(np.mean(lpips_distance(rgb, gt, model=lpips_model)))
    return metrics


HISTORY_COLUMNS = ("loss", "l1", "lpips", "depth", "drop_rate", "n_gaussians")


def history_array(history: dict[str, list[float]]) -> np.ndarray:
    """A training history as the stored ``history`` array [I, 6] (``HISTORY_COLUMNS``)."""
    return np.stack([np.asarray(history[c], dtype=np.float32) for c in HISTORY_COLUMNS], axis=1)


def load_gaussians(scene, step: StepSpec = FIT) -> GaussianModel:
    """The Gaussians a step stored (the fit's ``gaussians`` group by default; the refine step's ``renders``);
    the group must be complete."""
    scene.require_complete(step)
    arrays = scene.read_all(step)
    return GaussianModel(**{k: torch.from_numpy(np.ascontiguousarray(arrays[k])) for k in
                            ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")})


def load_fit_views(scene) -> tuple[list[TrainView], list[TrainView]]:
    """The fit's training and held-out views, rebuilt from its group (frames from the synthesize steps,
    resized as the fit did; calibrated depth targets of the training views)."""
    scene.require_complete(FIT)
    g = scene.read_all(FIT)
    w, h = scene.status(FIT).attrs["resolution"]
    frames: dict[int, np.ndarray] = {}
    train, test = [], []
    for f, (k, i) in enumerate(np.asarray(g["frame_ref"])):
        if int(k) not in frames:
            frames[int(k)] = scene.read(SYNTHESIZE, int(k), "frames")
        img = resize_image(frames[int(k)][int(i)], h, w).astype(np.float32) / 255.0
        d = g["depth_targets"][f]
        view = TrainView(torch.from_numpy(img), torch.as_tensor(g["c2w"][f], dtype=torch.float32),
                         torch.as_tensor(g["K"][f], dtype=torch.float32),
                         torch.from_numpy(np.ascontiguousarray(d)) if (d > 0).any() else None)
        if g["holdout"][f]:
            test.append(view)
        elif g["train"][f]:
            train.append(view)
    return train, test

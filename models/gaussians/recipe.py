"""The fit's recipe around the trainer (paper, Sec. III-D): resolution, resampling, the scene scale 3DGS's rates
refer to, LPIPS, held-out metrics, the stored loss history, and the further training of the refine step.

The steps that use it (``tasks/fit.py``, ``tasks/refine.py``) only read and write the store.
"""

from __future__ import annotations

import numpy as np
from PIL import Image

from navcrafter.models.gaussians.config import FitConfig, RefineConfig
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.train import GaussianTrainer, TrainResult, TrainView
from navcrafter.models.metrics.config import EvaluationConfig
from navcrafter.models.metrics.evalnets.lpips import LPIPS, lpips_distance
from navcrafter.models.metrics.evalnets.weights import MetricUnavailable
from navcrafter.models.metrics.image import psnr, ssim

HISTORY_COLUMNS = ("loss", "l1", "lpips", "depth", "drop_rate", "n_gaussians")


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


def scene_scale(c2w: np.ndarray, points: np.ndarray) -> float:
    """The scale 3DGS's learning rate and size thresholds refer to. 3DGS uses the cameras' extent, which
    assumes cameras around the scene; exploration cameras move little, so this is the median distance from
    the cameras' centroid to the cloud (the scene's radius as the cameras see it)."""
    centre = c2w[:, :3, 3].mean(axis=0)
    d = np.linalg.norm(np.asarray(points, dtype=np.float64) - centre, axis=1)
    return float(np.median(d)) if len(d) else 1.0


def init_subset(points: np.ndarray, colors: np.ndarray, max_points: int | None, seed: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """The points a fit starts from: all of them, or a seeded subset of ``max_points`` (``fit.max_init_points``)."""
    if max_points is not None and len(points) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))
        return points[keep], colors[keep]
    return points, colors


def load_lpips(evaluation: EvaluationConfig):
    """(LPIPS model or None, note): the official LPIPS network, never a random one."""
    try:
        model = LPIPS.from_pretrained(evaluation.lpips_net, evaluation.weights_dir)
    except MetricUnavailable as exc:
        return None, (f"LPIPS loss term skipped and held-out LPIPS not reported: the official weights are "
                      f"missing ({exc})")
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval(), f"LPIPS-{evaluation.lpips_net} (official weights)"


def heldout_metrics(rgb: np.ndarray, gt: np.ndarray, lpips_model=None) -> dict:
    """Mean PSNR / SSIM (and LPIPS with its official model, else None) of renders against held-out frames."""
    metrics = {"psnr": float(np.mean(psnr(rgb, gt))), "ssim": float(np.mean(ssim(rgb, gt))), "lpips": None}
    if lpips_model is not None:
        metrics["lpips"] = float(np.mean(lpips_distance(rgb, gt, model=lpips_model)))
    return metrics


def history_array(history: dict[str, list[float]]) -> np.ndarray:
    """A training history as the stored ``history`` array [I, 6] (``HISTORY_COLUMNS``)."""
    return np.stack([np.asarray(history[c], dtype=np.float32) for c in HISTORY_COLUMNS], axis=1)


def continue_training(model: GaussianModel, views: list[TrainView], fit: FitConfig, refine: RefineConfig,
                      seed: int, scene_scale: float, lpips_model=None,
                      callback=None) -> tuple[GaussianTrainer, TrainResult]:
    """Train a fitted ``model`` ``refine.iterations`` more on ``views``: the fit's settings, density control off,
    the position rate decaying from 10 x to 1 x ``fit.lr_means_final``. Returns (trainer, result)."""
    trainer = continuation_trainer(model, views, fit, refine, seed, scene_scale, lpips_model)
    return trainer, trainer.train(callback)


def continuation_trainer(model: GaussianModel, views: list[TrainView], fit: FitConfig, refine: RefineConfig,
                         seed: int, scene_scale: float, lpips_model=None) -> GaussianTrainer:
    """The trainer ``continue_training`` runs (untrained: a caller may evaluate it while it trains)."""
    lam_lpips = fit.lambda_lpips if lpips_model is not None else 0.0
    settings = fit.model_copy(update={"iterations": refine.iterations, "densify": False,
                                      "lr_means": 10 * fit.lr_means_final, "sh_degree_interval": 1})
    return GaussianTrainer(model, views, settings, scene_scale=scene_scale, seed=seed, lambda_lpips=lam_lpips,
                           perceptual=lpips_model if lam_lpips > 0 else None)

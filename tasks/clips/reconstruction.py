"""Table IV on dataset clips: 3D scene reconstruction from generated frames, scored at the dataset's own frames.

As the paper measures it: a 3DGS scene is fitted on what the generator made (the conditioning image and the
generated frames, at the clip's requested cameras, with the fit settings of ``fit.*``: the paper's loss, our
renderer), then rendered at the cameras of the dataset's frames and compared with those true frames (PSNR, SSIM,
LPIPS with its official weights). The fit starts from the point cloud the generator was given
(``<generated>/<clip>/cloud.npz``, written by ``navcrafter generate-clips``); for another generator's frames,
which come without one, from ``INIT_POINTS`` random points in the conditioning camera's frustum, uniform in
inverse depth between ``NEAR`` and ``FAR`` times the camera path's extent, coloured from the conditioning image
(stated in the row's note).

The in-pipeline Table IV rows (``tasks/score.py``) score held-out *synthesized* frames, which measures how well
the fit interpolates our own video; these rows compare with the true scene.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.recipe import (
    fit_size,
    heldout_metrics,
    init_subset,
    load_lpips,
    resize_image,
    scene_scale,
)
from navcrafter.models.gaussians.train import GaussianTrainer, TrainView
from navcrafter.schemas.clips import CLOUD
from navcrafter.schemas.config import RunConfig
from navcrafter.tasks.clips.dataset import load_clip, load_generated
from navcrafter.tasks.score import row

INIT_POINTS, NEAR, FAR = 20_000, 0.5, 5.0
METRICS = ("PSNR", "SSIM", "LPIPS")


def frustum_points(image: np.ndarray, K: np.ndarray, extent: float, count: int, seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points in the frustum of the identity camera ``K`` (uniform in inverse depth between ``NEAR`` and
    ``FAR`` x ``extent``), each coloured by the pixel it projects to."""
    H, W = image.shape[:2]
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, W, count), rng.uniform(0, H, count)
    inv = rng.uniform(1.0 / (FAR * extent), 1.0 / (NEAR * extent), count)
    z = 1.0 / inv
    pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    cols = image[np.minimum(v.astype(int), H - 1), np.minimum(u.astype(int), W - 1)]
    return pts.astype(np.float32), cols.astype(np.uint8)


def initial_points(generated: Path, key: str, clip: dict[str, Any], seed: int
                   ) -> tuple[np.ndarray, np.ndarray, str]:
    path = generated / key / CLOUD
    if path.is_file():
        with np.load(path) as z:
            return z["points"], z["colors"], f"initialised from the generator's point cloud ({CLOUD})"
    extent = float(np.linalg.norm(clip["c2w"][:, :3, 3], axis=1).max()) or 1.0
    pts, cols = frustum_points(clip["condition"], clip["K"][0], extent, INIT_POINTS, seed)
    return pts, cols, (f"no {CLOUD} from the generator: initialised from {INIT_POINTS} random points in the "
                       f"conditioning frustum ({NEAR}-{FAR} x the path extent)")


def reconstruction_rows(clips: str | Path, generated: str | Path, key: str, config: RunConfig
                        ) -> list[dict[str, Any]]:
    """Table IV rows of one clip (``status`` failed, with the reason, when its frames cannot be read)."""

    clips, generated = Path(clips), Path(generated)
    try:
        clip = load_clip(clips, key)
        fake = load_generated(generated, key, clip)
    except (OSError, ValueError) as exc:
        return [row("IV", m, status="failed", note=str(exc), scene_id=key) for m in METRICS]
    cfg = config.fit
    H, W = clip["condition"].shape[:2]
    h, w = fit_size(H, W, cfg.resolution)
    K = np.stack([Intrinsics.from_matrix(k, W, H).resize(w, h).K for k in clip["K"]])
    c2w = clip["c2w"]

    def view(img: np.ndarray, i: int) -> TrainView:
        return TrainView(torch.from_numpy(resize_image(img, h, w).astype(np.float32) / 255.0),
                         torch.as_tensor(c2w[i], dtype=torch.float32), torch.as_tensor(K[i], dtype=torch.float32))

    train = [view(clip["condition"], 0)] + [view(f, i) for i, f in enumerate(fake, start=1)]
    test = [view(f, i) for i, f in enumerate(clip["reference"], start=1)]
    seed = config.seed
    pts, cols, init_note = initial_points(generated, key, clip, seed)
    pts, cols = init_subset(pts, cols, cfg.max_init_points, seed)
    model = GaussianModel.from_point_cloud(pts, cols, sh_degree=cfg.sh_degree)
    lpips_model, lpips_note = load_lpips(config.evaluation)
    lam = cfg.lambda_lpips if lpips_model is not None else 0.0
    trainer = GaussianTrainer(model, train, cfg, scene_scale=scene_scale(c2w, pts), seed=seed, lambda_lpips=lam,
                              perceptual=lpips_model if lam > 0 else None)
    trainer.train()
    rgb, _ = trainer.evaluate(test)
    gt = np.stack([v.image.numpy() for v in test]).astype(np.float64)
    m = heldout_metrics(rgb.astype(np.float64), gt, lpips_model)
    note = (f"3DGS fitted on the conditioning image + {len(fake)} generated frames at the clip's cameras "
            f"({cfg.iterations} iterations at {w}x{h}; {init_note}), rendered at the dataset's {len(test)} frames")
    rows = [row("IV", "PSNR", m["psnr"], "dB", note=note, scene_id=key),
            row("IV", "SSIM", m["ssim"], None, note=note, scene_id=key)]
    if m["lpips"] is None:
        rows.append(row("IV", "LPIPS", status="unavailable", note=lpips_note, scene_id=key))
    else:
        rows.append(row("IV", "LPIPS", m["lpips"], None, note=f"{note}; {lpips_note}", scene_id=key))
    return rows

"""Fixtures of the render tests (tests/flows/test_render_cli.py, tests/flows/tools/test_render.py): a blob of
Gaussians and a scene with a fit, written straight into a store."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from navcrafter.models.gaussians.model import GaussianModel


def blob_model(n=200, degree=3, seed=0) -> GaussianModel:
    """Opaque coloured Gaussians in a box about (0, 0, 3), world up -y."""
    g = torch.Generator().manual_seed(seed)
    return GaussianModel(
        means=torch.rand(n, 3, generator=g) * 2 - 1 + torch.tensor([0.0, 0.0, 3.0]),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.full((n, 3), -2.5),
        opacity_logits=torch.full((n,), 3.0),
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g) * 0.1,
    )


def write_scene(root: Path, scene_id: str, model: GaussianModel | None, backend="simulation") -> None:
    from navcrafter.schemas.layout import FIT, INGEST, PLAN
    from navcrafter.schemas.store import Store

    scene = Store(root).scene(scene_id)
    w = scene.begin(INGEST, None, "k", backend)
    w.write("image", np.zeros((24, 32, 3), np.uint8))
    w.write("work_image", np.zeros((24, 32, 3), np.uint8))
    w.commit(0.0, source="x.png", sha256=scene_id, original_size=[32, 24], original_mode="RGB",
             exif_orientation=1, crop_box=[0, 0, 32, 24], normalised_size=[32, 24], work_size=[32, 24])
    w = scene.begin(PLAN, 1, "k", backend)
    w.write("trajectory", np.repeat(np.eye(4)[None], 3, axis=0))
    w.write("K", np.array([[20.0, 0, 16], [0, 20, 12], [0, 0, 1]]))
    w.write("centre", np.array([0.0, 0.0, 3.0]))
    w.write("candidates", np.repeat(np.eye(4)[None], 2, axis=0))
    w.commit(0.0, strategy="orbit", chosen=0)
    if model is None:
        return
    w = scene.begin(FIT, None, "k", backend)
    for name, t in model.tensors().items():
        w.write(name, t.numpy())
    F = 2
    w.write("frame_ref", np.array([[1, 0], [1, 1]], np.int32))
    w.write("c2w", np.repeat(np.eye(4)[None], F, axis=0))
    w.write("K", np.repeat(np.eye(3)[None], F, axis=0))
    w.write("holdout", np.array([False, True]))
    w.write("holdout_renders", np.zeros((1, 8, 8, 3), np.uint8))
    w.write("train", np.array([True, False]))
    w.write("depth_targets", np.zeros((F, 8, 8), np.float32))
    w.write("depth_calibration", np.zeros((0, 6)))
    w.write("history", np.zeros((1, 6), np.float32))
    w.commit(0.0, n_gaussians=len(model), sh_degree=model.sh_degree, resolution=[8, 8], holdout_every=2, n_train=1,
             n_holdout=1, psnr=0.0, ssim=0.0, lpips=None, lpips_note="", init_psnr=0.0, scene_scale=1.0,
             train_seconds=0.0, final_loss=0.0, peak_rss_mb=None)

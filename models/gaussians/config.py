"""Settings of the 3DGS fit and the refine step's fit (composed into the run config by schemas/config.py)."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field, model_validator

from navcrafter.models.settings import Section as _Section

# The fit's named loss weightings (fit.loss): values of lambda_lpips, lambda_depth, depth_space
LOSS_WEIGHTINGS: dict[str, dict[str, Any]] = {
    "paper": {"lambda_lpips": 1.0, "lambda_depth": 1.0, "depth_space": "inverse"},
    "light": {"lambda_lpips": 0.2, "lambda_depth": 0.1, "depth_space": "median"},
}


class FitConfig(_Section):
    """Geometry-aware 3D Gaussian Splatting fit (``tasks/fit.py``; paper, Sec. III-D).

    Initialised from the final cloud, trained on every synthesized frame at its planned camera except each
    ``holdout_every``-th (held out for PSNR/SSIM/LPIPS) with L1 + ``lambda_lpips`` LPIPS (only with the
    official LPIPS weights; skipped with a note otherwise) + ``lambda_depth`` depth L1 against monocular depth
    calibrated to the lift step's geometry depth, and DropGaussian. Learning rates are 3DGS's; the loss weights are
    the paper's (unit); the size (resolution, iterations, Gaussian budget, and 3DGS's schedule scaled to it) was
    chosen by held-out quality against time on 2 CPU cores (benchmarks/fit_defaults.py,
    models/gaussians/README.md#default-size). On by default. With a GPU, longer fits are cheap: see that README.
    """

    enabled: bool = Field(True, description="Run the fit step after the last lift.")
    iterations: int = Field(500, ge=1, description="Training iterations (one view each).")
    holdout_every: int = Field(8, ge=2, description="Every n-th frame (0, n, 2n, ...) is held out for evaluation.")
    train_stride: int = Field(
        1, ge=1, description="Train on every n-th of the frames not held out (1: all of them). Sparser training "
        "sets are where the depth prior and DropGaussian matter (benchmarks/fitting.py --train-stride).")
    depth_views: Literal["lift", "all"] = Field(
        "all", description="Training frames with depth supervision: 'lift' only those the lift step ran the "
        "geometry model on (calibrated to its depth); 'all' also the others, calibrated to the scene cloud "
        "rendered into the frame (z-buffered points, ``fit.depth_point_size``).")
    depth_point_size: float = Field(
        0.02, gt=0, description="World size of a cloud point when the cloud is rendered as a frame's multi-view "
        "depth (depth_views='all'); the lift voxel size is a good value.")
    resolution: int | None = Field(
        128, ge=8, description="Longer image side for training and evaluation (frames box-downsampled, "
        "intrinsics scaled); None: the synthesis resolution.")
    max_init_points: int | None = Field(
        50_000, ge=1, description="Initialise from at most this many cloud points (a seeded random subset); "
        "None: every point (3DGS).")
    sh_degree: int = Field(3, ge=0, le=3, description="Spherical-harmonics degree (3DGS: 3).")
    sh_degree_interval: int = Field(125, ge=1, description="Iterations per increase of the active SH degree.")
    lr_means: float = Field(1.6e-4, gt=0, description="Position learning rate x scene scale, at the start (3DGS).")
    lr_means_final: float = Field(1.6e-6, gt=0, description="... at the last iteration (log-linear decay).")
    lr_quats: float = Field(1e-3, gt=0)
    lr_scales: float = Field(5e-3, gt=0, description="Learning rate of the log-scales.")
    lr_opacities: float = Field(5e-2, gt=0, description="Learning rate of the opacity logits.")
    lr_sh0: float = Field(2.5e-3, gt=0)
    lr_shN: float = Field(2.5e-3 / 20, gt=0)
    loss: Literal["paper", "light"] = Field(
        "paper", description="Named weighting of the loss; sets lambda_lpips, lambda_depth and depth_space where "
        "they are not given: 'paper' L1 + LPIPS + depth L1 with unit weights, the depth term in inverse depth (the "
        "space the calibration fits); 'light' 1 : 0.2 : 0.1 with the depth term in median-normalised depth (the "
        "earlier default; measured effect in models/gaussians/README.md#the-loss).")
    lambda_lpips: float = Field(1.0, ge=0, description="Weight of the LPIPS term (needs the official weights).")
    lambda_depth: float = Field(1.0, ge=0, description="Weight of the calibrated-depth L1 term.")
    depth_space: Literal["inverse", "median", "relative"] = Field(
        "inverse", description="The depth term's space: 'inverse' |1/ED - 1/D| (world units^-1, where the target "
        "is valid, not sky, and the render covers the pixel); 'median' |ED - D| / median(D); 'relative' "
        "|ED - D| / (ED + D) per pixel (scale-free and bounded: a pixel whose target is far nearer than the render, "
        "e.g. generated content at the lens, pulls with a vanishing gradient; same mask as 'inverse').")
    drop_gamma: float = Field(0.1, ge=0, lt=1, description="DropGaussian: drop rate r_t = gamma t / T (0: off).")
    depth_confidence: float = Field(
        0.5, ge=0, le=1, description="Geometry pixels at least this confident take part in the depth calibration.")
    densify: bool = Field(True, description="Adaptive density control (clone / split / prune / opacity reset).")
    grow_grad2d: float = Field(2e-4, gt=0, description="Mean screen-space gradient (NDC) that triggers growth.")
    grow_scale3d: float = Field(0.01, gt=0, description="Clone below, split above this size x scene scale.")
    prune_opa: float = Field(0.005, gt=0, lt=0.5, description="Prune Gaussians less opaque than this.")
    prune_scale3d: float = Field(0.1, gt=0, description="Prune Gaussians larger than this x scene scale.")
    densify_start: int = Field(50, ge=0, description="First iteration of density control (gsplat: refine_start_iter).")
    densify_stop: int = Field(375, ge=0, description="Density control stops at this iteration (refine_stop_iter).")
    densify_every: int = Field(25, ge=1, description="Iterations between density-control steps (refine_every).")
    reset_every: int = Field(0, ge=0, description="Opacity reset period (0: never).")
    max_gaussians: int = Field(50_000, ge=1, description="Densification never grows the model beyond this.")
    device: str = Field(
        "auto", pattern=r"^(auto|cpu|cuda(:\d+)?)$", description="Where to train: 'auto' (CUDA when torch sees a "
        "GPU, else the CPU), 'cpu', 'cuda' or 'cuda:N'. Results come back to the CPU either way.")
    renderer: Literal["auto", "cpu", "torch", "gsplat"] = Field(
        "auto", description="Rasterizer: 'auto' (on the CPU navcrafter's compiled kernels; on CUDA gsplat when it "
        "is installed, else the PyTorch renderer), 'cpu', 'torch' (the PyTorch renderer, any device) or 'gsplat' "
        "(CUDA only; `pip install navcrafter[cuda]`). gsplat clamps alpha at 0.999 (ours 0.99) and is not "
        "bit-reproducible; 'cpu' and 'torch' give the same images.")
    threads: int | None = Field(
        None, ge=1, description="Threads of the compiled CPU rasterizer (None: every core; results do not depend "
        "on it).")

    # the density-control fields were called refine_* (gsplat's names) when the first stores were written;
    # cache keys keep those names (schemas.keys), so that renaming them recomputes nothing
    key_names: ClassVar[dict[str, str]] = {"densify_start": "refine_start", "densify_stop": "refine_stop",
                                           "densify_every": "refine_every"}

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("loss") in LOSS_WEIGHTINGS:
            data = {**LOSS_WEIGHTINGS[data["loss"]], **data}
        if isinstance(data, dict):
            for new, old in cls.key_names.items():
                if old in data:
                    raise ValueError(f"fit.{old} was renamed fit.{new} (density control; 'refine' is the refine "
                                     f"step): write fit.{new}")
        return data


class RefineConfig(_Section):
    """Diffusion refinement of rendered views (paper, Sec. III-D; Difix3D+-style), ``tasks/refine.py``.

    After the fit, the Gaussians are rendered at ``views`` novel cameras off the explored trajectory (training
    cameras displaced sideways/up by ``offset`` x the scene scale and turned by up to ``angle_deg``; never the
    held-out cameras), the Refiner role cleans each render (guided by the nearest training frame), and the fit
    goes on for ``iterations`` with the refined views as extra training views (loss weight ``weight``).
    """

    enabled: bool = Field(False, description="Run the refine step after the fit (needs fit.enabled).")
    views: int = Field(8, ge=1, description="Novel views rendered and refined.")
    offset: float = Field(0.08, gt=0, description="Displacement of a novel camera from its training camera, "
                          "x the scene scale (the median camera-to-cloud distance).")
    angle_deg: float = Field(8.0, ge=0, description="Largest turn (yaw and pitch) of a novel camera.")
    iterations: int = Field(1000, ge=1, description="Training iterations after adding the refined views.")
    weight: float = Field(1.0, gt=0, le=1, description="Loss weight of a refined view (real views: 1; the "
                          "paper's recipe uses the refined views as training views, i.e. 1).")
    depth: bool = Field(True, description="Depth term on the refined views too (their monocular depth calibrated "
                        "to the scene cloud rendered there), i.e. the fit's loss; false: colour terms only.")

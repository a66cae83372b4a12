"""Training a 3DGS model on posed images: the geometry-aware loss of the paper with DropGaussian.

Per iteration ``t`` one training view (a seeded permutation, one epoch after another) is rendered with the
``RGB+ED`` mode; with DropGaussian's rate ``r_t = gamma * t / T`` applied to the opacities (training only)::

    L = L1(rgb, image) + lambda_lpips * LPIPS(rgb, image) + lambda_depth * L1(1 / ED, 1 / D_cal)

with unit weights by default (the paper's loss, ``fit.loss = "paper"``). ``ED`` is the rendered expected depth,
``D_cal`` the view's calibrated monocular depth (``models.reconstruction.depthcalib``), compared in inverse depth,
the space the calibration fits, over pixels where ``D_cal > 0`` (valid, not sky) and the render covers the pixel
(alpha > 0.5). ``fit.depth_space = "median"`` (the ``"light"`` weighting, 1 : 0.2 : 0.1) compares ``|ED - D_cal|``
divided by the view's median ``D_cal`` instead; ``"relative"`` compares ``|ED - D_cal| / (ED + D_cal)`` per pixel
(scale-free and bounded in [0, 1): its gradient in ED, 2 D_cal / (ED + D_cal)^2, vanishes where the target is far
nearer than the render, so a near-field outlier cannot drive the fit; same mask as inverse depth). A term with
``lambda = 0`` is neither computed nor added; the LPIPS term needs a perceptual model (the official LPIPS weights)
and is skipped otherwise. With the compiled CPU renderer the L1 and inverse-depth terms are computed in one compiled
pass each way (``cpu_rasterize.l1_inverse_depth``: the gradients of the torch expressions, bit for bit).

Optimisation is 3DGS's: one Adam (eps 1e-15) per parameter with its own learning rate; the position rate is
multiplied by the scene scale and decays exponentially from ``lr_means`` to ``lr_means_final`` over the
run; the active SH degree grows by one every ``sh_degree_interval`` iterations. Density control is a
:class:`~navcrafter.models.gaussians.densify.Strategy`. Everything random is seeded, so a run is
deterministic on the CPU.

The settings are the run config's ``fit`` section (``schemas.config.FitConfig``, the one definition of every
parameter and its default). Devices and renderers (``fit.device`` / ``fit.renderer``, ``models.gaussians.renderer``):
parameters, the training views, optimiser state and density statistics live on ``device`` (``"auto"``: CUDA
when available); views are rendered with ``rasterize(..., backend=renderer)``
(``"auto"``: gsplat on CUDA when it imports, our PyTorch renderer otherwise). Density control is our
:class:`~navcrafter.models.gaussians.densify.DefaultStrategy` with either renderer (it is device-agnostic;
gsplat's own strategy is an opt-in, ``backend.GsplatStrategy``). The trained model, evaluation renders and
histories come back on the CPU. With gsplat the alpha clamp is 0.999 instead of our 0.99, and CUDA runs are
not bit-reproducible.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from navcrafter.models.gaussians.config import FitConfig
from navcrafter.models.gaussians.densify import DefaultStrategy, NoStrategy, Strategy
from navcrafter.models.gaussians.dropgaussian import DropGaussian
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.renderer import rasterize, resolve_backend, resolve_device

PerceptualLoss = Callable[[Tensor, Tensor], Tensor]  # (rendered, target) [1, 3, H, W] in [-1, 1] -> scalar


def strategy_for(config: FitConfig, seed: int) -> Strategy:
    """The density control a fit config asks for (``fit.densify``: 3DGS's default rule, else none)."""
    if not config.densify:
        return NoStrategy()
    return DefaultStrategy(grow_grad2d=config.grow_grad2d, grow_scale3d=config.grow_scale3d,
                           prune_opa=config.prune_opa, prune_scale3d=config.prune_scale3d,
                           start=config.densify_start, stop=config.densify_stop, every=config.densify_every,
                           reset_every=config.reset_every, max_gaussians=config.max_gaussians, seed=seed + 1)


@dataclass
class TrainView:
    """One posed image: ``image`` [H, W, 3] float in [0, 1], OpenCV ``c2w`` [4, 4], ``K`` [3, 3], optional
    calibrated depth [H, W] (0 = no supervision) and the weight of the view's loss (e.g. < 1 for refined
    pseudo-views, tasks/refine.py)."""

    image: Tensor
    c2w: Tensor
    K: Tensor
    depth: Tensor | None = None
    weight: float = 1.0

    @property
    def viewmat(self) -> Tensor:
        return torch.linalg.inv(self.c2w)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[0])


@dataclass
class TrainResult:
    model: GaussianModel
    history: dict[str, list[float]] = field(default_factory=dict)  # per iteration: loss, l1, lpips, depth, ...
    seconds: float = 0.0
    strategy_state: dict = field(default_factory=dict)

    def summary(self) -> dict[str, float]:
        h = self.history
        return {"iterations": len(h.get("loss", [])), "final_loss": h["loss"][-1] if h.get("loss") else math.nan,
                "n_gaussians": len(self.model), "seconds": self.seconds}


def position_lr(step: int, total: int, lr0: float, lr1: float) -> float:
    """Log-linear decay from ``lr0`` (step 0) to ``lr1`` (step ``total``)."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return math.exp(math.log(lr0) * (1 - t) + math.log(lr1) * t)


class GaussianTrainer:
    """Holds the parameters, optimisers, DropGaussian and the strategy of one training run."""

    PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")

    def __init__(self, model: GaussianModel, views: list[TrainView], config: FitConfig, *, scene_scale: float,
                 seed: int = 0, lambda_lpips: float | None = None, perceptual: PerceptualLoss | None = None,
                 strategy: Strategy | None = None, background: tuple[float, float, float] = (0.0, 0.0, 0.0)
                 ) -> None:
        """``config``: the fit's settings (``schemas.config.FitConfig``); ``seed``: of every random choice;
        ``lambda_lpips``: overrides ``config.lambda_lpips`` (0 where the LPIPS weights are missing)."""
        if not views:
            raise ValueError("training needs at least one view")
        if model.sh_degree < config.sh_degree:
            raise ValueError(f"the model has SH degree {model.sh_degree} < config.sh_degree {config.sh_degree}")
        self.seed = int(seed % (2**31))
        self.lambda_lpips = config.lambda_lpips if lambda_lpips is None else float(lambda_lpips)
        if self.lambda_lpips > 0 and perceptual is None:
            raise ValueError("lambda_lpips > 0 needs a perceptual model (pass lambda_lpips=0 without LPIPS weights)")
        self.device = resolve_device(config.device)
        self.renderer = resolve_backend(config.renderer, self.device)  # "cpu" | "torch" | "gsplat"; raises early
        if self.renderer == "cpu":
            # deferred: numba and the compiled CPU kernels load only when the CPU renderer is chosen
            from navcrafter.models.gaussians.cpu_rasterize import set_threads

            set_threads(config.threads)
        self.config, self.scene_scale = config, float(scene_scale)
        self.views = [self._on_device(v) for v in views]
        if isinstance(perceptual, torch.nn.Module):
            perceptual.to(self.device)  # in place (LPIPS; lpips_distance follows the module's device)
        self.perceptual = perceptual
        self.params = {name: t.detach().to(device=self.device, dtype=torch.float32, copy=True).requires_grad_(True)
                       for name, t in model.tensors().items()}
        lrs = {"means": config.lr_means * self.scene_scale, "quats": config.lr_quats, "log_scales": config.lr_scales,
               "opacity_logits": config.lr_opacities, "sh_dc": config.lr_sh0, "sh_rest": config.lr_shN}
        # on the CPU the fused Adam kernel: the default single-tensor loop took ~5x its time (50k Gaussians with
        # SH degree 3: ~100 vs ~20 ms of CPU per iteration, benchmarks/fit_profile.py); CUDA keeps torch's default
        fused = True if self.device.type == "cpu" else None
        self.optimizers = {name: torch.optim.Adam([{"params": [self.params[name]], "lr": lrs[name]}], eps=1e-15,
                                                  fused=fused)
                           for name in self.PARAMS}
        self.strategy = strategy if strategy is not None else strategy_for(config, self.seed)
        self.state = self.strategy.initialize_state(self.scene_scale)
        self.drop = DropGaussian(config.drop_gamma, max(config.iterations, 1), seed=self.seed + 2)
        self.order = torch.Generator().manual_seed(self.seed)
        self._queue: list[int] = []
        self.background = torch.tensor(background, dtype=torch.float32, device=self.device)
        self.history: dict[str, list[float]] = {k: [] for k in ("loss", "l1", "lpips", "depth", "drop_rate",
                                                                "n_gaussians")}

    # ----------------------------------------------------------------------------------------------
    @property
    def model(self) -> GaussianModel:
        """A copy of the current parameters, on the CPU."""
        return GaussianModel(**{k: v.detach().to("cpu", copy=True) for k, v in self.params.items()})

    def _on_device(self, view: TrainView) -> TrainView:
        """``view`` itself when its tensors are on the training device, else a copy moved there."""
        tensors = (view.image, view.c2w, view.K) + (() if view.depth is None else (view.depth,))
        if all(t.device == self.device for t in tensors):
            return view
        return TrainView(view.image.to(self.device), view.c2w.to(self.device), view.K.to(self.device),
                         None if view.depth is None else view.depth.to(self.device), view.weight)

    def active_sh_degree(self, step: int) -> int:
        c = self.config
        return min(c.sh_degree, step // max(c.sh_degree_interval, 1))

    def render(self, view: TrainView, step: int, *, training: bool, sh_degree: int | None = None
               ) -> tuple[Tensor, Tensor, Tensor, dict]:
        """(rgb [H, W, 3], expected depth [H, W], alpha [H, W], meta) of ``view``; DropGaussian only when
        ``training``. Tensors on the training device."""
        view = self._on_device(view)
        p = self.params
        opac = self.drop(torch.sigmoid(p["opacity_logits"]), step, training=training)
        W, H = view.size
        viewmats = view.viewmat[None]
        degree = self.active_sh_degree(step) if sh_degree is None else sh_degree
        if self.renderer == "cpu":
            # the compiled SH reads sh_dc and sh_rest as they are (no [N, K, 3] copy forward, none of it back):
            # per-camera colours, bit for bit those of the concatenated coefficients
            # deferred: numba and the compiled CPU kernels load only when the CPU renderer is chosen
            from navcrafter.models.gaussians.cpu_rasterize import sh_colors

            colors, degree = sh_colors(p["means"], p["sh_dc"], p["sh_rest"], viewmats, degree), None
        else:
            colors = torch.cat([p["sh_dc"][:, None, :], p["sh_rest"]], dim=1)
        out, alpha, meta = rasterize(
            p["means"], p["quats"], torch.exp(p["log_scales"]), opac, colors, viewmats, view.K[None],
            W, H, sh_degree=degree, backgrounds=self.background[None], render_mode="RGB+ED", packed=False,
            backend=self.renderer)
        return out[0, ..., :3], out[0, ..., 3], alpha[0, ..., 0], meta

    def losses(self, view: TrainView, rgb: Tensor, depth: Tensor, alpha: Tensor | None = None) -> dict[str, Tensor]:
        """The loss terms of one rendered view (``alpha``: its rendered opacity, for the inverse-depth mask)."""
        c = self.config
        view = self._on_device(view)
        with_depth = c.lambda_depth > 0 and view.depth is not None
        fused = self.renderer == "cpu" and (not with_depth or (c.depth_space == "inverse" and alpha is not None))
        if fused:
            # deferred: numba and the compiled CPU kernels load only when the CPU renderer is chosen
            from navcrafter.models.gaussians.cpu_rasterize import fused_loss_applies, l1_inverse_depth

            fused = fused_loss_applies(rgb, depth, view.image, view.depth, alpha)
        terms = {}
        if fused:  # the L1 and inverse-depth terms below in one compiled pass (the same gradients, bit for bit)
            terms["l1"], term = l1_inverse_depth(rgb, depth, view.image, view.depth if with_depth else None, alpha)
            if term is not None:
                terms["depth"] = term
        else:
            terms["l1"] = (rgb - view.image).abs().mean()
        if self.lambda_lpips > 0:
            terms["lpips"] = self.perceptual(rgb.permute(2, 0, 1)[None] * 2 - 1,
                                             view.image.permute(2, 0, 1)[None] * 2 - 1).reshape(())
        if with_depth and not fused:
            mask = view.depth > 0  # calibrated depth: 0 = sky or invalid
            if c.depth_space in ("inverse", "relative") and alpha is not None:
                mask = mask & (alpha.detach() > 0.5)  # ED is meaningless where the render does not cover the pixel
            if c.depth_space == "inverse":
                if mask.any():
                    inv_ref = 1.0 / view.depth[mask]
                    terms["depth"] = (1.0 / depth[mask].clamp(min=1e-6) - inv_ref).abs().mean()
            elif c.depth_space == "relative":
                if mask.any():
                    ref, ed = view.depth[mask], depth[mask].clamp(min=0.0)
                    terms["depth"] = ((ed - ref).abs() / (ed + ref).clamp(min=1e-8)).mean()
            elif mask.any():
                ref = view.depth[mask]
                terms["depth"] = (depth[mask] - ref).abs().mean() / ref.median().clamp(min=1e-8)
        total = terms["l1"]
        if "lpips" in terms:
            total = total + self.lambda_lpips * terms["lpips"]
        if "depth" in terms:
            total = total + c.lambda_depth * terms["depth"]
        terms["loss"] = total if view.weight == 1.0 else view.weight * total
        return terms

    def next_view(self) -> int:
        if not self._queue:
            self._queue = torch.randperm(len(self.views), generator=self.order).tolist()
        return self._queue.pop(0)

    def step(self, step: int) -> dict[str, float]:
        c = self.config
        view = self.views[self.next_view()]
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        self.optimizers["means"].param_groups[0]["lr"] = position_lr(
            step, c.iterations, c.lr_means * self.scene_scale, c.lr_means_final * self.scene_scale)
        rgb, depth, alpha, meta = self.render(view, step, training=True)
        terms = self.losses(view, rgb, depth, alpha)
        self.strategy.step_pre_backward(self.params, self.optimizers, self.state, step, meta)
        terms["loss"].backward()
        for opt in self.optimizers.values():
            opt.step()
        self.strategy.step_post_backward(self.params, self.optimizers, self.state, step, meta)
        rec = {k: float(v.detach()) for k, v in terms.items()}
        rec.update(drop_rate=self.drop.rate(step), n_gaussians=float(self.params["means"].shape[0]))
        for k in self.history:
            self.history[k].append(rec.get(k, math.nan))
        return rec

    def train(self, callback: Callable[[int, dict[str, float]], None] | None = None) -> TrainResult:
        t0 = time.perf_counter()
        for step in range(self.config.iterations):
            rec = self.step(step)
            if callback is not None:
                callback(step, rec)
        state = {k: v for k, v in self.state.items() if isinstance(v, (int, float))}
        return TrainResult(self.model, self.history, time.perf_counter() - t0, state)

    @torch.no_grad()
    def evaluate(self, views: list[TrainView]) -> tuple[np.ndarray, np.ndarray]:
        """Renders (no DropGaussian, full SH degree) of ``views``: rgb [V, H, W, 3] in [0, 1] and depth."""
        rgbs, depths = [], []
        for v in views:
            rgb, depth, _, _ = self.render(v, self.config.iterations, training=False, sh_degree=self.config.sh_degree)
            rgbs.append(rgb.clamp(0, 1).cpu().numpy())
            depths.append(depth.cpu().numpy())
        return np.stack(rgbs), np.stack(depths)


def train_gaussians(model: GaussianModel, views: list[TrainView], config: FitConfig, *, scene_scale: float,
                    seed: int = 0, perceptual: PerceptualLoss | None = None, strategy: Strategy | None = None,
                    callback: Callable[[int, dict[str, float]], None] | None = None
                    ) -> tuple[TrainResult, GaussianTrainer]:
    """Train ``model`` on ``views``; returns the result and the trainer (for rendering held-out views)."""
    trainer = GaussianTrainer(model, views, config, scene_scale=scene_scale, seed=seed, perceptual=perceptual,
                              strategy=strategy)
    return trainer.train(callback), trainer


def render_model(model: GaussianModel, c2w: np.ndarray, K: np.ndarray, width: int, height: int,
                 background: tuple[float, float, float] = (0.0, 0.0, 0.0), *, device: str = "cpu",
                 renderer: str = "auto", batch: int = 1) -> np.ndarray:
    """Evaluation renders [V, H, W, 3] uint8 of a trained model at cameras ``c2w`` [V, 4, 4], ``K`` [V, 3, 3].

    ``device`` / ``renderer`` as ``fit.device`` / ``fit.renderer`` (default: the CPU, i.e. our renderer);
    ``batch`` cameras per rasterizer call (the covariances once per call, the cameras' tiles in one parallel
    loop; the same images as one at a time)."""
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    dev = resolve_device(device)
    backend = resolve_backend(renderer, dev)
    model = model.to(dev)
    out = np.empty((len(c2w), height, width, 3), dtype=np.uint8)
    with torch.no_grad():
        for i in range(0, len(c2w), batch):
            vm = torch.linalg.inv(torch.as_tensor(c2w[i:i + batch], dtype=torch.float32)).to(dev)
            ks = torch.as_tensor(K[i:i + batch], dtype=torch.float32, device=dev)
            bg = torch.tensor(background, dtype=torch.float32, device=dev)[None].expand(len(vm), 3)
            img, _, _ = model.render(vm, ks, width, height, backgrounds=bg, backend=backend)
            out[i:i + len(vm)] = np.round(img.clamp(0, 1).cpu().numpy() * 255).astype(np.uint8)
    return out

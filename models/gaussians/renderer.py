"""Renderer backends of the 3DGS code: our compiled CPU kernels, our pure-PyTorch rasterizer (any device) or
gsplat's CUDA kernels.

:func:`rasterize` takes the arguments of :func:`~navcrafter.models.gaussians.rasterize.rasterization` (which
has gsplat's ``rasterization`` contract) plus ``backend``:

* ``"auto"``: on CPU tensors the compiled kernels; on CUDA gsplat when ``import gsplat`` works, else the
  PyTorch renderer;
* ``"cpu"``: the compiled numba kernels (``cpu_rasterize``; CPU tensors only; same results as ``"torch"``,
  many times faster, no camera gradients);
* ``"torch"``: the PyTorch renderer, on whatever device the tensors are (it runs on CUDA too, just without
  fused kernels; the reference the compiled kernels are tested against, and the one that differentiates
  cameras);
* ``"gsplat"``: gsplat, or :class:`GsplatUnavailableError` (with the install hint) when the tensors are not
  on CUDA or gsplat does not import.

gsplat is not a dependency of CPU installs: it is the optional extra ``pip install navcrafter[cuda]``
(``gsplat>=1.5``), needs a CUDA build of torch, and JIT-compiles its kernels on first use (nvcc, i.e. the
CUDA toolkit matching torch's CUDA, must be on the PATH; the first call takes minutes). It has no CPU path.

Argument mapping to ``gsplat.rasterization`` (1.5.x; the current main branch has the same names):

* every argument of ours is passed under the same name; ``packed`` is passed as given (our default
  ``False``, gsplat's ``True``), so ``meta`` stays per (camera, Gaussian) ``[C, N, ...]`` as our density
  control expects (with ``packed=True`` the meta entries are ``[nnz, ...]`` with ``meta["gaussian_ids"]``;
  :class:`~navcrafter.models.gaussians.densify.DefaultStrategy` does not handle that).
* ``alpha_clamp`` has no gsplat equivalent: gsplat's kernels hard-code ``min(0.999, alpha)``. ``None`` (the
  default) means each backend's own value (ours :data:`~navcrafter.models.gaussians.rasterize.DEFAULT_ALPHA_CLAMP`
  = 0.99, the original 3DGS; gsplat's 0.999); any other value with gsplat is ignored with a warning.
* extra keyword arguments (``absgrad``, ``sparse_grad``, ``camera_model``, ...) go to gsplat only; the torch
  renderer refuses them (``TypeError``).

``meta`` normalisation (gsplat's ``meta`` is returned with these changes, so our strategy and trainer read the
same keys from either backend): gsplat >= 1.5 returns per-axis ``radii`` ``[C, N, 2]`` (an opacity-aware
box), older releases and our renderer ``[C, N]``. ``meta["radii"]`` becomes ``[C, N]`` (int32): the larger
of the two radii where both are positive (gsplat's visibility rule), else 0; ``meta["radii_xy"]`` keeps the
per-axis ``[C, N, 2]`` (for gsplat's own strategies; ``[C, N]`` radii are repeated). ``meta["means2d"]`` is
gsplat's tensor itself (``retain_grad()`` on it works as with ours); ``meta["backend"]`` says which renderer
ran. ``n_isects`` is added from ``isect_ids`` when missing.

Known differences of the two renderers (ours documents them in ``rasterize.py``): the alpha clamp, and which
tiles list a Gaussian's faint tail (ours: the isotropic ``3 sqrt(lambda_max)`` square; gsplat >= 1.5: the
box of the ``alpha >= 1/255`` ellipse, at most 3.33 sigma per axis). For opacities <= 0.35 the second is
immaterial (gsplat's box lies inside our square, and pixels outside its box have ``alpha < 1/255``), so with
``alpha_clamp=0.999`` the two agree to float32 rounding (``tests/models/gaussians/test_gsplat_backend.py``
checks this on a GPU); above that, pixels between 3 and 3.33 sigma may get a contribution (alpha < 0.011)
from gsplat only.

Density control with gsplat: the trainer uses our :class:`~navcrafter.models.gaussians.densify.DefaultStrategy`
(device-agnostic torch) with either renderer by default. :class:`GsplatStrategy` runs one of gsplat's
strategies on the trainer's parameters instead (opt in: ``GaussianTrainer(..., strategy=gsplat_default_strategy(
config))``); see its docstring for why it is not the default.
"""

from __future__ import annotations

import importlib
import warnings
from typing import Any, Literal

import torch
from torch import Tensor

from navcrafter.models.gaussians.rasterize import DEFAULT_ALPHA_CLAMP, RenderMode, _check_inputs, rasterization

Backend = Literal["auto", "cpu", "torch", "gsplat"]
BACKENDS = ("auto", "cpu", "torch", "gsplat")
GSPLAT_ALPHA_CLAMP = 0.999  # hard-coded in gsplat's rasterization kernels
INSTALL_HINT = (
    "install the CUDA extra with `pip install navcrafter[cuda]` (gsplat>=1.5) in an environment with a CUDA "
    "build of torch and the CUDA toolkit (nvcc) on the PATH: gsplat compiles its kernels on first use and has "
    "no CPU path. Use renderer/backend 'torch' (or 'auto') to render with navcrafter's own PyTorch rasterizer."
)

# Test hook: lets an explicit "gsplat" run on CPU tensors (with a fake ``gsplat`` module in ``sys.modules``)
# so that the glue code is exercised without CUDA. Never set outside tests; "auto" ignores it.
_ALLOW_GSPLAT_ON_CPU = False


class GsplatUnavailableError(RuntimeError):
    """The gsplat backend was asked for but cannot run here."""


def _import_gsplat() -> Any:
    return importlib.import_module("gsplat")


def gsplat_available() -> bool:
    """Whether ``import gsplat`` works. It does not check CUDA (gsplat imports without it and builds its
    kernels on first use); :func:`resolve_backend` does."""
    try:
        _import_gsplat()
    except Exception:  # ImportError, or a broken install failing at import time
        return False
    return True


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """``"auto"``: ``cuda`` when ``torch.cuda.is_available()``, else ``cpu``; otherwise ``torch.device(device)``
    (a CUDA device without CUDA is an error)."""
    if isinstance(device, str) and device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {str(dev)!r} was asked for but torch.cuda.is_available() is False "
                           f"(torch {torch.__version__}, CUDA build: {torch.version.cuda is not None})")
    return dev


def resolve_backend(backend: str, device: str | torch.device) -> Literal["cpu", "torch", "gsplat"]:
    """The renderer that ``backend`` means for tensors on ``device`` (see the module docstring)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    dev = torch.device(device)
    if backend == "torch":
        return "torch"
    if backend == "cpu":
        if dev.type != "cpu":
            raise ValueError(f"the compiled CPU rasterizer needs CPU tensors, got {str(dev)!r}; use 'auto', "
                             "'gsplat' or 'torch' on CUDA")
        return "cpu"
    if backend == "auto":
        if dev.type == "cpu":
            return "cpu"
        return "gsplat" if dev.type == "cuda" and gsplat_available() else "torch"
    if dev.type != "cuda" and not _ALLOW_GSPLAT_ON_CPU:
        raise GsplatUnavailableError(f"the gsplat renderer needs CUDA tensors, got tensors on {str(dev)!r}; "
                                     f"{INSTALL_HINT}")
    try:
        _import_gsplat()
    except Exception as exc:
        raise GsplatUnavailableError(f"the gsplat renderer was asked for but `import gsplat` failed ({exc!r}); "
                                     f"{INSTALL_HINT}") from exc
    return "gsplat"


def normalize_gsplat_meta(meta: dict) -> dict:
    """gsplat's ``meta`` with ``radii`` as ``[..., N]`` and the per-axis radii as ``radii_xy`` (module docstring)."""
    out = dict(meta)
    radii, means2d = meta["radii"], meta["means2d"]
    if radii.shape == means2d.shape:  # gsplat >= 1.5: per-axis [..., 2]
        visible = (radii > 0).all(dim=-1)
        out["radii"] = torch.where(visible, radii.amax(dim=-1), torch.zeros_like(radii[..., 0]))
        out["radii_xy"] = radii
    else:  # older gsplat: one radius per Gaussian
        out["radii_xy"] = radii[..., None].expand(*radii.shape, 2)
    if "n_isects" not in out and out.get("isect_ids") is not None:
        out["n_isects"] = int(out["isect_ids"].shape[0])
    out["backend"] = "gsplat"
    return out


def rasterize(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = False,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,
    render_mode: RenderMode = "RGB",
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    covars: Tensor | None = None,
    alpha_clamp: float | None = None,
    backend: Backend = "auto",
    **kwargs: Any,
) -> tuple[Tensor, Tensor, dict]:
    """:func:`~navcrafter.models.gaussians.rasterize.rasterization` on the backend ``backend`` chooses for the
    tensors' device; returns ``(render_colors [C, H, W, X], render_alphas [C, H, W, 1], meta)``.

    ``alpha_clamp=None`` is each backend's own clamp (0.99 ours, 0.999 gsplat's); ``kwargs`` are gsplat-only
    arguments. See the module docstring for the mapping and the ``meta`` normalisation.
    """
    which = resolve_backend(backend, means.device)
    if which in ("cpu", "torch"):
        if kwargs:
            raise TypeError(f"the {which} renderer does not take {sorted(kwargs)} (gsplat-only arguments)")
        if which == "cpu":
            # deferred: numba and the compiled CPU kernels load only when the CPU renderer is chosen
            from navcrafter.models.gaussians.cpu_rasterize import rasterization as ours
        else:
            ours = rasterization
        render, alphas, meta = ours(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=near_plane,
            far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d, sh_degree=sh_degree, packed=packed,
            tile_size=tile_size, backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
            covars=covars, alpha_clamp=DEFAULT_ALPHA_CLAMP if alpha_clamp is None else alpha_clamp)
        meta["backend"] = which
        return render, alphas, meta

    # our checks give clearer messages than gsplat's asserts; they also pin our contract (no batch dimensions)
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, render_mode, covars)
    if alpha_clamp is not None and alpha_clamp != GSPLAT_ALPHA_CLAMP:
        warnings.warn(f"alpha_clamp={alpha_clamp} ignored: gsplat hard-codes {GSPLAT_ALPHA_CLAMP}", stacklevel=2)
    gsplat = _import_gsplat()
    render, alphas, meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=near_plane,
        far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d, sh_degree=sh_degree, packed=packed,
        tile_size=tile_size, backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
        covars=covars, **kwargs)
    return render, alphas, normalize_gsplat_meta(meta)


# --------------------------------------------------------------------------------------------------
# gsplat's strategies on the trainer's parameters (opt-in)
# --------------------------------------------------------------------------------------------------
# GaussianTrainer's parameter names -> gsplat's (its strategies and examples/simple_trainer.py). The values
# are the same parameterisation: log-scales, opacity logits [N], SH DC and rest (gsplat's strategy code only
# indexes and concatenates along the first dimension, so our sh_dc [N, 3] vs its sh0 [N, 1, 3] is immaterial).
GSPLAT_PARAM_NAMES = {"means": "means", "quats": "quats", "log_scales": "scales", "opacity_logits": "opacities",
                      "sh_dc": "sh0", "sh_rest": "shN"}


class GsplatStrategy:
    """One of gsplat's strategies (e.g. ``gsplat.DefaultStrategy``) behind our
    :class:`~navcrafter.models.gaussians.densify.Strategy` interface.

    Each call hands gsplat a dict of the trainer's parameters (and one of their optimisers) under gsplat's
    names (:data:`GSPLAT_PARAM_NAMES`) and an ``info`` with gsplat's per-axis ``radii`` (``meta["radii_xy"]``,
    same ``means2d`` tensor); gsplat's ops replace entries of that dict (new ``nn.Parameter`` rows, Adam moments
    moved in the same optimiser objects), which are copied back into the trainer's dict afterwards.

    Not the trainer's default, deliberately: gsplat 1.5.x's ``DefaultStrategy`` never resets opacities (its
    condition ``step % reset_every == 0 & step > 0`` is a chained comparison that is always false; fixed on
    gsplat's main branch in Aug 2025, after 1.5.3), has no ``max_gaussians`` cap, draws its split samples from
    the global RNG, and starts refining at ``step > refine_start_iter`` (ours ``>=``). Our
    :class:`~navcrafter.models.gaussians.densify.DefaultStrategy` keeps the config's semantics on any device.
    """

    def __init__(self, strategy: Any, *, packed: bool = False) -> None:
        self.strategy, self.packed = strategy, packed

    @staticmethod
    def _views(params: dict, optimizers: dict) -> tuple[dict, dict]:
        return ({g: params[o] for o, g in GSPLAT_PARAM_NAMES.items()},
                {g: optimizers[o] for o, g in GSPLAT_PARAM_NAMES.items()})

    @staticmethod
    def _info(info: dict) -> dict:
        if info.get("radii_xy") is None:
            raise ValueError("gsplat's strategies need per-axis radii: render with models.gaussians.renderer.rasterize")
        return {**info, "radii": info["radii_xy"]}

    def initialize_state(self, scene_scale: float) -> dict[str, Any]:
        return self.strategy.initialize_state(scene_scale=scene_scale)

    def step_pre_backward(self, params, optimizers, state, step, info) -> None:
        info = self._info(info)
        gp, go = self._views(params, optimizers)
        self.strategy.step_pre_backward(gp, go, state, step, info)

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        info = self._info(info)
        gp, go = self._views(params, optimizers)
        self.strategy.step_post_backward(gp, go, state, step, info, packed=self.packed)
        for ours, theirs in GSPLAT_PARAM_NAMES.items():
            params[ours] = gp[theirs]


def gsplat_default_strategy(config: Any) -> GsplatStrategy:
    """gsplat's ``DefaultStrategy`` with a fit config's (``schemas.config.FitConfig``) density
    settings (``reset_every=0``, "never", becomes a period no run reaches: gsplat divides by it).
    ``max_gaussians`` and ``seed`` have no gsplat equivalent and are not applied."""
    try:
        gsplat = _import_gsplat()
    except Exception as exc:
        raise GsplatUnavailableError(f"gsplat's DefaultStrategy needs gsplat ({exc!r}); {INSTALL_HINT}") from exc
    return GsplatStrategy(gsplat.DefaultStrategy(
        prune_opa=config.prune_opa, grow_grad2d=config.grow_grad2d, grow_scale3d=config.grow_scale3d,
        prune_scale3d=config.prune_scale3d, refine_start_iter=config.densify_start,
        refine_stop_iter=config.densify_stop, refine_every=config.densify_every,
        reset_every=config.reset_every if config.reset_every > 0 else 2**62))

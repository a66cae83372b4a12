"""The Gaussian model: a dataclass of tensors in the parameterisation 3DGS optimises and stores.

Stored (raw) parameters, as in the 3DGS PLY: ``means`` [N, 3], ``quats`` [N, 4] (w, x, y, z; need not be
normalised), ``log_scales`` [N, 3], ``opacity_logits`` [N], ``sh_dc`` [N, 3] and ``sh_rest`` [N, K-1, 3]
with ``K = (sh_degree + 1)^2`` (coefficient-major, channel last, as gsplat takes them). Activations:
``scales = exp(log_scales)``, ``opacities = sigmoid(opacity_logits)``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from navcrafter.models.gaussians.renderer import rasterize
from navcrafter.models.gaussians.sh import num_sh_bases, rgb_to_sh_dc, sh_degree_from_bases

INIT_OPACITY = 0.1
_MIN_DIST2 = 1e-7  # floor of the mean squared neighbour distance (3DGS), for duplicate points


@dataclass
class GaussianModel:
    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacity_logits: Tensor
    sh_dc: Tensor
    sh_rest: Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
            "sh_dc": (n, 3),
        }
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(getattr(self, name).shape)}")
        rest = self.sh_rest
        if rest.dim() != 3 or rest.shape[0] != n or rest.shape[2] != 3:
            raise ValueError(f"sh_rest must be [N, K-1, 3] for N={n}, got {tuple(rest.shape)}")
        sh_degree_from_bases(rest.shape[1] + 1)  # raises on a bad K

    # ---------------------------------------------------------------------------------------------
    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh_rest.shape[1] + 1)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh_coeffs(self) -> Tensor:
        """All SH coefficients [N, K, 3] (DC first)."""
        return torch.cat([self.sh_dc[:, None, :], self.sh_rest], dim=1)

    def tensors(self) -> dict[str, Tensor]:
        """The raw parameters by name (e.g. for an optimiser's parameter groups)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def map(self, fn) -> GaussianModel:
        """A new model with ``fn`` applied to every tensor."""
        return GaussianModel(**{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> GaussianModel:
        return self.map(lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> GaussianModel:
        return self.map(lambda t: t.detach())

    def clone(self) -> GaussianModel:
        return self.map(lambda t: t.clone())

    def requires_grad_(self, requires_grad: bool = True) -> GaussianModel:
        for t in self.tensors().values():
            t.requires_grad_(requires_grad)
        return self

    # ---------------------------------------------------------------------------------------------
    @classmethod
    def from_point_cloud(
        cls,
        points: np.ndarray | Tensor,
        colors: np.ndarray | Tensor,
        *,
        sh_degree: int = 3,
        init_opacity: float = INIT_OPACITY,
        init_scale: float = 1.0,
        fallback_scale: float = 0.01,
        dtype: torch.dtype = torch.float32,
    ) -> GaussianModel:
        """One isotropic Gaussian per point (the 3DGS initialisation).

        ``colors`` are uint8 (0-255) or floats in [0, 1]; they become the SH DC term (higher bands zero).
        The scale of each Gaussian is ``init_scale`` times the root mean square distance to its 3 nearest
        neighbours (fewer when the cloud has fewer points; ``fallback_scale`` for a single point), as in
        3DGS (``distCUDA2``) and gsplat's trainer. Rotations are the identity; opacities ``init_opacity``.
        """
        if not 0.0 < init_opacity < 1.0:
            raise ValueError(f"init_opacity must be in (0, 1), got {init_opacity}")
        num_sh_bases(sh_degree)  # validates
        pts = np.asarray(points.detach().cpu() if isinstance(points, Tensor) else points, dtype=np.float64)
        pts = pts.reshape(-1, 3)
        col = colors.detach().cpu().numpy() if isinstance(colors, Tensor) else np.asarray(colors)
        col = col.reshape(-1, 3)
        if len(col) != len(pts):
            raise ValueError(f"{len(pts)} points but {len(col)} colours")
        if not np.isfinite(pts).all():
            raise ValueError("points must be finite")
        rgb = col.astype(np.float64) / 255.0 if col.dtype == np.uint8 else col.astype(np.float64)
        n = len(pts)
        if n >= 2:
            k = min(3, n - 1)
            dist, _ = cKDTree(pts).query(pts, k=k + 1)
            dist2 = np.maximum((dist[:, 1:] ** 2).mean(axis=1), _MIN_DIST2)
            scale = np.sqrt(dist2) * init_scale
        else:
            scale = np.full(n, fallback_scale)
        k_rest = num_sh_bases(sh_degree) - 1
        quats = np.zeros((n, 4))
        quats[:, 0] = 1.0
        logit = float(np.log(init_opacity / (1.0 - init_opacity)))

        def t(a: np.ndarray) -> Tensor:
            return torch.as_tensor(a, dtype=dtype)

        return cls(
            means=t(pts),
            quats=t(quats),
            log_scales=t(np.repeat(np.log(scale)[:, None], 3, axis=1)),
            opacity_logits=t(np.full(n, logit)),
            sh_dc=rgb_to_sh_dc(t(rgb)),
            sh_rest=torch.zeros(n, k_rest, 3, dtype=dtype),
        )

    # ---------------------------------------------------------------------------------------------
    def render(
        self,
        viewmats: Tensor,
        Ks: Tensor,
        width: int,
        height: int,
        *,
        sh_degree: int | None = None,
        opacities: Tensor | None = None,
        backend: str = "auto",
        **kwargs,
    ) -> tuple[Tensor, Tensor, dict]:
        """:func:`~navcrafter.models.gaussians.renderer.rasterize` of this model (``sh_degree`` defaults to the
        model's; ``opacities`` replaces the activated opacities, e.g. with DropGaussian's; ``backend``: "auto" is
        our PyTorch renderer for CPU tensors, gsplat for CUDA tensors when it is installed)."""
        return rasterize(
            self.means,
            self.quats,
            self.scales,
            self.opacities if opacities is None else opacities,
            self.sh_coeffs,
            viewmats,
            Ks,
            width,
            height,
            sh_degree=self.sh_degree if sh_degree is None else sh_degree,
            backend=backend,
            **kwargs,
        )

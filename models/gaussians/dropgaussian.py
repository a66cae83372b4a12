"""DropGaussian: random Gaussian dropout during training, a regulariser for sparse-view 3DGS.

At training step ``t`` of ``T`` each Gaussian is dropped independently with probability
``r_t = gamma * t / T`` (a progressive schedule), and the survivors' opacities are scaled by
``1 / (1 - r_t)`` so that every Gaussian's opacity is preserved in expectation. At evaluation (or when
``r_t = 0``) it is the identity: the very same tensor is returned. Only the (activated) opacities passed to
the renderer change; the model's parameters are untouched, and gradients reach the survivors (scaled by
``1 / (1 - r_t)``) and not the dropped ones.
"""

from __future__ import annotations

import torch
from torch import Tensor


def drop_rate(step: int, total_steps: int, gamma: float) -> float:
    """``r_t = gamma * t / T`` with ``t`` clamped to ``[0, T]``."""
    if total_steps <= 0:
        raise ValueError(f"total_steps must be positive, got {total_steps}")
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma must be in [0, 1), got {gamma}")
    return gamma * min(max(step, 0), total_steps) / total_steps


def drop_gaussians(
    opacities: Tensor, rate: float, *, training: bool = True, generator: torch.Generator | None = None
) -> Tensor:
    """Opacities with each entry zeroed with probability ``rate`` and the rest divided by ``1 - rate``.

    Returns ``opacities`` itself when ``training`` is false or ``rate == 0``.
    """
    if not 0.0 <= rate < 1.0:
        raise ValueError(f"drop rate must be in [0, 1), got {rate}")
    if not training or rate == 0.0:
        return opacities
    # drawn on the CPU (where the generator lives), so a seed gives the same mask on any device
    keep = torch.rand(opacities.shape, generator=generator) >= rate
    return opacities * keep.to(device=opacities.device, dtype=opacities.dtype) / (1.0 - rate)


class DropGaussian:
    """The schedule and a seeded generator: ``DropGaussian(gamma, total_steps, seed)(opacities, step)``.

    The same seed and sequence of calls give the same masks. Calls at evaluation draw nothing, so they do
    not shift the training sequence.
    """

    def __init__(self, gamma: float = 0.1, total_steps: int = 10_000, seed: int = 0) -> None:
        drop_rate(0, total_steps, gamma)  # validates
        self.gamma = float(gamma)
        self.total_steps = int(total_steps)
        self.generator = torch.Generator().manual_seed(seed)

    def rate(self, step: int) -> float:
        return drop_rate(step, self.total_steps, self.gamma)

    def __call__(self, opacities: Tensor, step: int, *, training: bool = True) -> Tensor:
        return drop_gaussians(opacities, self.rate(step), training=training, generator=self.generator)

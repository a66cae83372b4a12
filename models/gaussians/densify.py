"""Adaptive density control of 3DGS on the CPU, behind a small strategy interface shaped like gsplat's.

A strategy sees the trainable parameters (a dict of leaf tensors named as ``GaussianModel`` fields) and their
optimisers (one ``torch.optim.Adam`` per parameter) around each backward pass:

* ``step_pre_backward(params, optimizers, state, step, info)``: ``info["means2d"].retain_grad()``, so the
  2D mean gradients used for densification survive the backward pass;
* ``step_post_backward(params, optimizers, state, step, info)``: accumulate statistics and, on schedule,
  change the set of Gaussians **in place** in ``params`` and ``optimizers`` (rows added or removed from both
  the tensors and Adam's moments).

:class:`DefaultStrategy` is 3DGS's (and gsplat's ``DefaultStrategy``'s) rule: every ``every`` steps in
``[start, stop)``, Gaussians whose average screen-space mean gradient (in NDC units: pixels
times ``W/2``, ``H/2``) exceeds ``grow_grad2d`` are **cloned** when small (max scale <= ``grow_scale3d`` x
scene scale) and **split** in two when large (new means drawn from the Gaussian, scales / 1.6); then those
with opacity < ``prune_opa`` (and, after the first opacity reset, those larger than ``prune_scale3d`` x scene
scale) are **pruned**; every ``reset_every`` steps opacities are clamped to ``2 prune_opa``. The number of
Gaussians never exceeds ``max_gaussians``: growth is limited to the candidates with the largest gradients.
Seeded (the split samples), so deterministic on the CPU. Device-agnostic: statistics and row surgery stay on
the parameters' device (CUDA included, with either renderer of ``models.gaussians.renderer``); the split
samples are drawn on the CPU from the seeded generator and moved, so they do not depend on the device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from navcrafter.models.gaussians.rasterize import quat_to_rotmat

Params = dict[str, Tensor]
Optimizers = dict[str, torch.optim.Optimizer]


class Strategy(Protocol):
    def initialize_state(self, scene_scale: float) -> dict[str, Any]: ...

    def step_pre_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                          info: dict[str, Any]) -> None: ...

    def step_post_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                           info: dict[str, Any]) -> None: ...


class NoStrategy:
    """A fixed set of Gaussians (no densification, pruning or resets)."""

    def initialize_state(self, scene_scale: float) -> dict[str, Any]:
        return {}

    def step_pre_backward(self, params, optimizers, state, step, info) -> None:
        return None

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        return None


# --------------------------------------------------------------------------------------------------
# Row surgery on parameters and their Adam moments
# --------------------------------------------------------------------------------------------------
def _replace_rows(params: Params, optimizers: Optimizers, keep: Tensor, extra: Params | None = None) -> None:
    """Keep the rows ``keep`` (bool [N] or index) of every parameter and append ``extra[name]`` rows (moments
    of appended rows start at zero). Parameters stay leaf tensors requiring grad; optimisers are updated."""
    for name, p in list(params.items()):
        new_rows = None if extra is None else extra[name]
        data = p.detach()[keep]
        if new_rows is not None:
            data = torch.cat([data, new_rows.detach().to(data.dtype)])
        new_p = data.clone().requires_grad_(True)
        opt = optimizers[name]
        old_state = opt.state.pop(p, None)
        opt.param_groups[0]["params"] = [new_p]
        if old_state is not None:
            st = {}
            for k, v in old_state.items():
                if k == "step" or not torch.is_tensor(v) or v.dim() == 0:
                    st[k] = v
                    continue
                v = v[keep]
                if new_rows is not None:
                    v = torch.cat([v, torch.zeros((len(new_rows),) + v.shape[1:], dtype=v.dtype, device=v.device)])
                st[k] = v
            opt.state[new_p] = st
        params[name] = new_p


def _reset_moments(optimizer: torch.optim.Optimizer, param: Tensor) -> None:
    st = optimizer.state.get(param)
    if st:
        for k in ("exp_avg", "exp_avg_sq"):
            if k in st:
                st[k].zero_()


@dataclass
class DefaultStrategy:
    """3DGS / gsplat default density control (see the module docstring). The settings are the fit config's
    (``schemas.config.FitConfig``: gsplat's defaults, defined there once; ``models.gaussians.train.strategy_for``
    builds one); ``start`` / ``stop`` / ``every`` are in training iterations (gsplat: ``refine_start_iter`` ..)."""

    grow_grad2d: float
    grow_scale3d: float
    prune_opa: float
    prune_scale3d: float
    start: int
    stop: int
    every: int
    reset_every: int
    max_gaussians: int
    seed: int

    def initialize_state(self, scene_scale: float) -> dict[str, Any]:
        return {"scene_scale": float(scene_scale), "grad2d": None, "count": None,
                "generator": torch.Generator().manual_seed(self.seed), "n_clone": 0, "n_split": 0, "n_prune": 0}

    def step_pre_backward(self, params, optimizers, state, step, info) -> None:
        info["means2d"].retain_grad()

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        if step >= self.stop:
            return
        self._update_state(params, state, info)
        if step >= self.start and step % self.every == 0 and step > 0:
            self._grow(params, optimizers, state)
            self._prune(params, optimizers, state, step)
            state["grad2d"] = state["count"] = None
        if self.reset_every > 0 and step > 0 and step % self.reset_every == 0:
            logit = math.log(2 * self.prune_opa / (1 - 2 * self.prune_opa))
            with torch.no_grad():
                params["opacity_logits"].clamp_(max=logit)
            _reset_moments(optimizers["opacity_logits"], params["opacity_logits"])

    # ----------------------------------------------------------------------------------------------
    def _update_state(self, params: Params, state: dict[str, Any], info: dict[str, Any]) -> None:
        m2d = info["means2d"]
        if m2d.grad is None:
            return
        n = params["means"].shape[0]
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            state["grad2d"] = torch.zeros(n, dtype=torch.float64, device=m2d.device)
            state["count"] = torch.zeros(n, dtype=torch.float64, device=m2d.device)
        grads, radii = m2d.grad.detach(), info["radii"]  # [C, N, 2], [C, N]
        if grads.device.type == "cpu" and grads.dtype == torch.float32:
            # one compiled pass, the same bits as the ops below (which cost ~1 ms per iteration at 50k on 2 cores:
            # ten small ops, each waking torch's threads; issue 31, round fit33)
            # deferred: numba and the compiled CPU kernels load only where density control runs on the CPU
            from navcrafter.models.gaussians.cpu_kernels import accumulate_grad2d

            accumulate_grad2d(grads.contiguous().numpy(), radii.contiguous().numpy(), np.float32(info["width"] / 2.0),
                              np.float32(info["height"] / 2.0), state["grad2d"].numpy(), state["count"].numpy())
            return
        grads = grads.clone()
        grads[..., 0] *= info["width"] / 2.0
        grads[..., 1] *= info["height"] / 2.0
        visible = radii > 0
        norms = grads.norm(dim=-1) * visible
        state["grad2d"] += norms.sum(0).double()
        state["count"] += visible.sum(0).double()

    def _grow(self, params: Params, optimizers: Optimizers, state: dict[str, Any]) -> None:
        if state["grad2d"] is None:
            return
        n = params["means"].shape[0]
        grads = state["grad2d"] / state["count"].clamp(min=1)
        high = grads > self.grow_grad2d
        max_scale = torch.exp(params["log_scales"].detach()).max(dim=-1).values
        small = max_scale <= self.grow_scale3d * state["scene_scale"]
        clone, split = high & small, high & ~small
        room = self.max_gaussians - n  # a clone or a split adds one Gaussian each
        if room <= 0:
            return
        cand = torch.nonzero(clone | split, as_tuple=True)[0]
        if len(cand) > room:  # keep the candidates with the largest gradients (ties: lower index)
            order = torch.argsort(-grads[cand], stable=True)[:room]
            chosen = torch.zeros(n, dtype=torch.bool, device=grads.device)
            chosen[cand[order]] = True
            clone, split = clone & chosen, split & chosen
        with torch.no_grad():
            extra = {name: p.detach()[clone] for name, p in params.items()}
            if split.any():
                # the split Gaussian is replaced by two samples: one appended, one overwriting it in place
                idx = torch.nonzero(split, as_tuple=True)[0]
                scales = torch.exp(params["log_scales"][idx])
                rot = quat_to_rotmat(params["quats"][idx])
                gen = state["generator"]
                # drawn on the CPU (where the generator lives): the same samples on any device
                samples = torch.randn((2, len(idx), 3), generator=gen, dtype=scales.dtype).to(scales.device)
                offsets = torch.einsum("nij,knj->kni", rot, samples * scales[None])
                new_log_scales = torch.log(scales / 1.6)
                appended = {name: p[idx] for name, p in params.items()}
                appended["means"] = params["means"][idx] + offsets[1]
                appended["log_scales"] = new_log_scales
                params["means"][idx] = params["means"][idx] + offsets[0]
                params["log_scales"][idx] = new_log_scales
                extra = {name: torch.cat([extra[name], appended[name]]) for name in params}
        state["n_clone"] += int(clone.sum())
        state["n_split"] += int(split.sum())
        if len(extra["means"]):
            _replace_rows(params, optimizers, torch.ones(n, dtype=torch.bool, device=grads.device), extra)

    def _prune(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> None:
        with torch.no_grad():
            prune = torch.sigmoid(params["opacity_logits"]) < self.prune_opa
            if step > self.reset_every > 0:
                prune |= torch.exp(params["log_scales"]).max(dim=-1).values > self.prune_scale3d * state["scene_scale"]
        if prune.all():  # never prune everything
            prune[torch.argmax(params["opacity_logits"].detach())] = False
        if prune.any():
            state["n_prune"] += int(prune.sum())
            _replace_rows(params, optimizers, ~prune)

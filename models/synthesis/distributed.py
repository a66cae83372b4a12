"""FSDP2 (``torch.distributed.fsdp.fully_shard``) for the camera-control trainer (``config.parallel="fsdp"``).

**Sharding** (``shard_model``): one FSDP unit per base DiT block (``model.base.blocks[i]``), then the root
``CameraControlledWan``, whose group holds everything else: the base prologue/epilogue and the whole camera
control. Each block is all-gathered just before it runs and freed after (again for backward); the root group is
gathered once at the start of the forward and, as FSDP2 does for the root, stays gathered until backward ends.

**Full state** (``full_module_state`` / ``load_full_module_state``, ``full_optimizer_state`` /
``load_full_optimizer_state``): the unsharded CPU tensors on rank 0 (gathered one tensor at a time), and back:
rank 0 holds the full tensors, every rank receives its shard. ``full_optimizer_state`` has the layout of
``optimizer.state_dict()`` in a single process (integer parameter indices), so checkpoints are the same files
whatever wrote them. ``save_control_state`` / ``read_control_state`` write and read the full control in the
``camcontrol`` layout (``save_camera_control`` / ``load_camera_control`` themselves, with their checks).

**Unused parameters** (``ParameterUse``): FSDP2 reduce-scatters the gradients of the parameters whose
unsharded gradient exists, so two ranks whose clips leave different parameters unused (a dropped camera, no
extra reference frame) would run mismatched collectives. Every trainable root-group parameter the loss does not
reach gets an exact-zero gradient, and after the step's backward the gradients of parameters no rank reached are
dropped, as a single process leaves them ``None`` (AdamW then skips them: no weight decay, no moment update).

Every function here is collective (all ranks call it, in the same order) unless it says otherwise.
"""

from __future__ import annotations

import pickle
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any, TypeVar

import torch
import torch.distributed as dist
from torch import nn

from navcrafter.models.synthesis.camcontrol import (
    CameraControlConfig,
    CameraControlledWan,
    load_camera_control,
    save_camera_control,
)

R = TypeVar("R")


def _rank() -> int:
    return dist.get_rank() if dist.is_initialized() else 0


def _dtensor_type() -> type:
    from torch.distributed.tensor import DTensor

    return DTensor


# --------------------------------------------------------------------------------------------------
# Sharding
# --------------------------------------------------------------------------------------------------
def make_mesh(device: torch.device | str, world_size: int | None = None):
    """The 1-D data-parallel mesh of the default process group on ``device``'s type (cpu: gloo, cuda: NCCL)."""
    from torch.distributed.device_mesh import init_device_mesh

    world = int(world_size if world_size is not None else dist.get_world_size())
    return init_device_mesh(torch.device(device).type, (world,))


def shard_model(model: CameraControlledWan, mesh=None, *, device: torch.device | str | None = None,
                ) -> CameraControlledWan:
    """Apply ``fully_shard`` to every ``model.base.blocks[i]`` and then to ``model`` (in place; returns it).

    Set ``requires_grad`` before (FSDP2 keeps it on the sharded parameters) and build the optimizer after, over
    the parameters ``model`` then holds (sharded ``DTensor`` s).
    """
    from torch.distributed.fsdp import fully_shard

    if mesh is None:
        mesh = make_mesh(device if device is not None else next(model.parameters()).device)
    for block in model.base.blocks:
        fully_shard(block, mesh=mesh)
    # The control stays in the root group on purpose. Its submodules (control.adapter, control.lora_encoder,
    # control.ref_embedding, control.blocks[i].pre_proj, ... and, inside each base block's attention processor,
    # control.blocks[i].lora_q/k/v, attn_proj, ref_gate) are called directly by CameraControlledWan.forward and
    # by the processors, never through control.forward. FSDP2 gathers a unit's parameters in a forward pre-hook
    # of the module it was applied to, so a separate unit on model.control (or on its blocks) would never be
    # gathered: the processors would meet sharded DTensors. In the root group they are gathered when the root's
    # forward starts and stay gathered through backward (FSDP2 does not reshard the root after forward).
    fully_shard(model, mesh=mesh)
    # The root returns a view (the final unpatchify); the trainer only applies out-of-place ops to it.
    warnings.filterwarnings("ignore", message=r"FSDP2-wrapped module \(FSDPCameraControlledWan\) returned a view")
    return model


def is_sharded(model: nn.Module) -> bool:
    from torch.distributed.fsdp import FSDPModule

    return isinstance(model, FSDPModule)


# --------------------------------------------------------------------------------------------------
# Rank 0 reads, everybody learns the outcome
# --------------------------------------------------------------------------------------------------
def rank0_only(fn: Callable[[], R]) -> R:
    """Run ``fn`` on rank 0 and return its (small, picklable) result on every rank; an exception raised by
    ``fn`` is raised on every rank (instead of the other ranks waiting forever in the next collective)."""
    if not dist.is_initialized() or dist.get_world_size() == 1:
        return fn()
    box: list[Any] = [None]
    error: BaseException | None = None
    if _rank() == 0:
        try:
            box[0] = ("ok", fn())
        except Exception as exc:  # noqa: BLE001 - re-raised below, on every rank
            error = exc
            try:
                pickle.dumps(exc)
                box[0] = ("error", exc)
            except Exception:  # noqa: BLE001
                box[0] = ("error", RuntimeError(f"rank 0: {type(exc).__name__}: {exc}"))
    dist.broadcast_object_list(box, src=0)
    kind, value = box[0]
    if kind == "error":
        if error is not None:
            raise error
        raise value
    return value


# --------------------------------------------------------------------------------------------------
# Full (unsharded, CPU) state on rank 0 <-> shards on every rank
# --------------------------------------------------------------------------------------------------
def _full_options(**kw: Any):
    from torch.distributed.checkpoint.state_dict import StateDictOptions

    return StateDictOptions(full_state_dict=True, **kw)


def full_module_state(module: nn.Module) -> dict[str, torch.Tensor]:
    """``module.state_dict()`` with every sharded tensor gathered, on the CPU, on rank 0 (``{}`` elsewhere).

    ``module`` may be a submodule of the FSDP root (``model.control``, ``model.base``): the keys are relative to
    it, as ``module.state_dict()`` of the unsharded model."""
    from torch.distributed.checkpoint.state_dict import get_model_state_dict

    state = get_model_state_dict(module, options=_full_options(cpu_offload=True))
    return {k: v.detach().contiguous() for k, v in state.items()} if _rank() == 0 else {}


def load_full_module_state(module: nn.Module, state: dict[str, torch.Tensor]) -> None:
    """Load a full state dict held by rank 0 (``state`` is ignored elsewhere) into ``module``'s shards (strict:
    rank 0's keys must be exactly ``module``'s)."""
    from torch.distributed.checkpoint.state_dict import set_model_state_dict

    set_model_state_dict(module, state if _rank() == 0 else {},
                         options=_full_options(broadcast_from_rank0=True, strict=True))


def full_optimizer_state(opt: torch.optim.Optimizer) -> dict[str, Any]:
    """``opt.state_dict()`` with every sharded state tensor gathered, on the CPU, on rank 0 (``{}`` elsewhere):
    the single-process layout (``state`` keyed by parameter index, ``param_groups`` with index lists).

    (``torch.distributed.checkpoint.state_dict.get_optimizer_state_dict`` keys the state by parameter name and,
    on load, first fills every parameter with a fake zero step: a parameter that never had a gradient would come
    back with ``step=1``. Gathering the optimizer's own state dict keeps it exact.)"""
    DTensor = _dtensor_type()
    sd = opt.state_dict()
    rank0 = _rank() == 0
    state: dict[int, dict[str, Any]] = {}
    for idx in sorted(sd["state"]):
        entry = {}
        for k, v in sd["state"][idx].items():
            if isinstance(v, DTensor):
                v = v.full_tensor()
            if rank0:
                entry[k] = v.detach().cpu().contiguous() if isinstance(v, torch.Tensor) else v
        state[idx] = entry
    return {"state": state, "param_groups": sd["param_groups"]} if rank0 else {}


def load_full_optimizer_state(opt: torch.optim.Optimizer, state: dict[str, Any]) -> None:
    """Load ``full_optimizer_state``'s layout held by rank 0 (ignored elsewhere): the structure and the scalars
    are broadcast, every state tensor of a sharded parameter is scattered as that parameter is sharded."""
    from torch.distributed.tensor import distribute_tensor

    DTensor = _dtensor_type()

    def skeleton() -> dict[str, Any]:
        out: dict[int, dict[str, Any]] = {}
        for idx, entry in state["state"].items():
            out[int(idx)] = {k: (("tensor", tuple(v.shape), v.dtype) if isinstance(v, torch.Tensor) and v.ndim > 0
                                 else ("value", v)) for k, v in entry.items()}
        return {"state": out, "param_groups": state["param_groups"]}

    sk = rank0_only(skeleton)
    params = [p for g in opt.param_groups for p in g["params"]]
    loaded: dict[int, dict[str, Any]] = {}
    for idx in sorted(sk["state"]):
        if not 0 <= idx < len(params):
            raise ValueError(f"optimizer state for parameter {idx}, but the optimizer has {len(params)}")
        p = params[idx]
        entry: dict[str, Any] = {}
        for k, (kind, *info) in sk["state"][idx].items():
            if kind == "value":
                entry[k] = info[0]
                continue
            shape, dtype = info
            device = p.to_local().device if isinstance(p, DTensor) else p.device
            full = (state["state"][idx][k].to(device) if _rank() == 0
                    else torch.empty(shape, dtype=dtype, device=device))
            if isinstance(p, DTensor) and tuple(p.shape) == tuple(shape):
                entry[k] = distribute_tensor(full, p.device_mesh, p.placements, src_data_rank=0)
            else:
                dist.broadcast(full, src=0)
                entry[k] = full
        loaded[idx] = entry
    opt.load_state_dict({"state": loaded, "param_groups": sk["param_groups"]})


# --------------------------------------------------------------------------------------------------
# The control's full state in the camcontrol layout (rank 0 only: no collectives)
# --------------------------------------------------------------------------------------------------
class _StateView:
    """Stands for ``model.control`` in ``save_camera_control`` / ``load_camera_control``, which use nothing of it
    but ``state_dict()``: the full tensors, without a second (unsharded) control module."""

    def __init__(self, state: dict[str, torch.Tensor]) -> None:
        self._state = state

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self._state


def save_control_state(model: CameraControlledWan, state: dict[str, torch.Tensor], directory: str | Path) -> Path:
    """``save_camera_control(model, directory)`` with the control's weights taken from ``state`` (the full
    state of ``full_module_state(model.control)``): the same files, key names and metadata. Rank 0 only."""
    view = SimpleNamespace(base=model.base, config=model.config, control=_StateView(state))
    return save_camera_control(view, directory)  # type: ignore[arg-type]


def read_control_state(model: CameraControlledWan, directory: str | Path,
                       ) -> tuple[dict[str, torch.Tensor], CameraControlConfig]:
    """The full control weights and config of ``save_camera_control``'s files, checked against ``model`` exactly
    as ``load_camera_control`` checks them (base sizes, every key and shape). Rank 0 only; ``model`` is not
    changed (apply the result with ``load_full_module_state`` and ``apply_control_config``)."""
    expected = {k: torch.empty(tuple(v.shape), dtype=v.dtype) for k, v in model.control.state_dict().items()}
    view = SimpleNamespace(base=model.base, config=model.config, control=_StateView(expected),
                           _ref_generator=None)
    load_camera_control(view, directory)  # type: ignore[arg-type]
    return expected, view.config


def apply_control_config(model: CameraControlledWan, config: CameraControlConfig) -> None:
    """What ``load_camera_control`` does besides the weights: the saved config replaces ``model.config`` (it
    describes how the weights were trained) and the reference-frame generator is reseeded from it."""
    model.config = config
    model._ref_generator = torch.Generator().manual_seed(config.reference_seed)


# --------------------------------------------------------------------------------------------------
# Unused parameters
# --------------------------------------------------------------------------------------------------
def reached_leaves(t: torch.Tensor) -> set[int]:
    """``id`` of every leaf tensor ``t``'s autograd graph accumulates a gradient into (local; no collective).
    With non-reentrant activation checkpointing the graph is complete after the forward, so this is exact."""
    ids: set[int] = set()
    seen: set[Any] = set()
    stack = [t.grad_fn]
    while stack:
        fn = stack.pop()
        if fn is None or fn in seen:
            continue
        seen.add(fn)
        var = getattr(fn, "variable", None)
        if var is not None:
            ids.add(id(var))
        stack.extend(nxt for nxt, _ in fn.next_functions)
    return ids


class ParameterUse:
    """Which of the ``n`` trainable parameters (the optimizer's order) one step's losses reached on this rank.

    Per micro-batch: ``objective = loss_term + use.touch(loss, live)`` with ``live`` the trainable parameters as
    registered after that forward (the root group's are the gathered plain tensors; a block's are sharded again
    and count as reached: every base block parameter is used by every forward). After the step's backward:
    ``use.drop_unused(params)``.
    """

    def __init__(self, n: int, device: torch.device | str = "cpu") -> None:
        self.used = torch.zeros(n, dtype=torch.bool)
        self.device = torch.device(device)  # of the all-reduce (NCCL needs a CUDA tensor)

    def touch(self, loss: torch.Tensor, live: Sequence[torch.Tensor]) -> torch.Tensor:
        """A zero-valued term that gives every parameter ``loss`` does not reach an exact-zero gradient."""
        if len(live) != len(self.used):
            raise ValueError(f"{len(live)} live parameters for {len(self.used)} trainable ones")
        DTensor = _dtensor_type()
        reached = reached_leaves(loss)
        missed = []
        for i, p in enumerate(live):
            if isinstance(p, DTensor) or id(p) in reached:
                self.used[i] = True
            elif p.requires_grad:
                missed.append(p)
        if not missed:
            return loss.new_zeros(())
        return 0.0 * torch.stack([p.sum().to(loss.dtype) for p in missed]).sum()

    def drop_unused(self, params: Sequence[torch.Tensor]) -> int:
        """Set the gradient of every parameter no rank reached to ``None`` (collective); the number dropped."""
        used = self.used.to(device=self.device, dtype=torch.int32)
        if dist.is_initialized() and dist.get_world_size() > 1:
            dist.all_reduce(used, op=dist.ReduceOp.MAX)
        dropped = 0
        for p, u in zip(params, used.cpu().tolist()):
            if not u and p.grad is not None:
                p.grad = None
                dropped += 1
        return dropped

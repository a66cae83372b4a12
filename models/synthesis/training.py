"""Training of the camera control (Module I): the rectified-flow loss, the trainer and its checkpoints.

**Loss** (the paper's, Wan2.1's flow matching). For clean latents ``x₀`` of a clip, noise ``ε ~ N(0, I)`` and
``u ~ U(0, 1)`` shifted to ``σ = s·u / (1 + (s-1)·u)`` (``config.flow_shift``)::

    x_σ = (1 - σ)·x₀ + σ·ε,      target = ε - x₀,      loss = ‖f(x_σ, 1000σ, conditions) - target‖²  (mean)

with the I2V conditioning of the sampler (mask + latents of frame 0, ``pipeline.i2v_mask``), CLIP features of
frame 0, the text embeddings (replaced by the null prompt's with probability ``text_dropout``), the Plücker
rays of the clip's cameras in the control's recorded convention (dropped with probability ``camera_dropout``),
the render conditioning when the control has ``cond_channels``, the extra reference frame when the clip has
one, and the clean latents as ``reference_latents`` (random reference frames). The camera LoRA runs at
``TRAINING_LORA_SCALE`` (1.0).

**Determinism.** Every random draw of a sample (σ, ε, dropouts, the reference frames) comes from a generator
seeded by ``(config.seed, global sample index)``; the data order is a per-epoch permutation seeded by
``(config.seed, epoch)``. A step's global batch is ``batch_size × world_size`` consecutive samples of that
order; rank ``r`` takes its ``batch_size`` of them and runs them one at a time (gradient accumulation, one
clip per forward, the natural size of an 81-frame clip). Hence: a run restarted from a checkpoint continues
exactly as an uninterrupted one, and ``world_size`` processes with batch ``b`` compute the same update as one
process with batch ``world_size·b`` (up to float reduction order).

**Checkpoints** (``schemas/training.py``): the control weights (``save_camera_control``), the AdamW state in
``optimizer.safetensors`` and ``state.json`` (step, data position, RNG states, loss history), written to a
temporary folder and renamed, then ``latest`` is updated: a kill at any point leaves the previous complete one.

**Several processes** (``world_size > 1``): ``config.parallel="ddp"`` wraps the model in
``DistributedDataParallel``; ``"fsdp"`` shards it with FSDP2 (``distributed.shard_model``: one unit per base
block, the control in the root unit), accumulates the micro-batches without communication
(``set_requires_gradient_sync``), clips the global norm of the sharded gradients (``clip_grad_norm_`` over
``DTensor`` s) and gathers the full control and AdamW state for the checkpoints: the files are the same as a
single process writes (index-keyed optimizer state included), so either kind of run resumes the other's.
``"fsdp"`` with one process is a plain single-process run (there is nothing to shard across).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from navcrafter.models.camera.cameras import clip_relative_rays, plucker_rays
from navcrafter.models.synthesis.camcontrol import (
    TRAINING_LORA_SCALE,
    CameraControlConfig,
    CameraControlledWan,
    load_camera_control,
    make_render_condition,
    plucker_to_tensor,
    save_camera_control,
)
from navcrafter.models.synthesis.distributed import (
    ParameterUse,
    apply_control_config,
    full_module_state,
    full_optimizer_state,
    load_full_module_state,
    load_full_optimizer_state,
    rank0_only,
    read_control_state,
    save_control_state,
    shard_model,
)
from navcrafter.models.synthesis.pipeline import SamplerConfig, i2v_mask, initial_noise, make_scheduler
from navcrafter.models.synthesis.training_config import CHECKPOINT_DIR, CameraTrainingConfig

OPTIMIZER_FILE = "optimizer.safetensors"
STATE_FILE = "state.json"
LATEST = "latest"


class TrainingDataError(ValueError):
    """A clip does not fit the model being trained (the message names the clip and the fix)."""


# --------------------------------------------------------------------------------------------------
# Randomness
# --------------------------------------------------------------------------------------------------
def _seed(*parts: int) -> int:
    """A 63-bit seed from integers (stable across processes and platforms)."""
    h = 1469598103934665603
    for p in parts:
        for b in int(p).to_bytes(8, "little", signed=True):
            h = ((h ^ b) * 1099511628211) & 0xFFFFFFFFFFFFFFFF
    return h & 0x7FFFFFFFFFFFFFFF


def sample_generator(seed: int, index: int) -> torch.Generator:
    """The generator of global sample ``index`` (σ, ε, dropouts, reference frames)."""
    return torch.Generator().manual_seed(_seed(seed, 1, index))


def epoch_order(seed: int, epoch: int, n: int) -> np.ndarray:
    return np.random.default_rng(_seed(seed, 2, epoch)).permutation(n)


def shift_sigma(u: torch.Tensor | float, shift: float) -> torch.Tensor:
    """Wan's flow-matching shift ``σ = s·u / (1 + (s-1)·u)``."""
    u = torch.as_tensor(u, dtype=torch.float32)
    return shift * u / (1.0 + (shift - 1.0) * u)


# --------------------------------------------------------------------------------------------------
# Model inputs of one clip
# --------------------------------------------------------------------------------------------------
def clip_conditions(model: CameraControlledWan, clip: dict[str, Any], device: torch.device | str = "cpu",
                    ) -> dict[str, torch.Tensor | None]:
    """Everything the DiT sees of a stored clip besides the noisy latents, as batch-1 tensors.

    Keys: ``x0`` (clean latents), ``hidden_cond`` (I2V mask + frame-0 latents), ``text``, ``image``
    (CLIP features), ``plucker`` (rays in the control's recorded convention), ``cond`` (render condition or
    None), ``image_reference`` / ``image_reference_plucker`` (the extra reference frame or None).
    """
    cfg = model.config
    name = clip.get("attrs", {}).get("clip_id", "?")
    x0 = np.asarray(clip["latents"], dtype=np.float32)
    C, Fl, h, w = x0.shape
    if C != cfg.latent_channels:
        raise TrainingDataError(f"clip {name}: latents have {C} channels, the control expects "
                                f"{cfg.latent_channels}: precompute the clips with this model's encoders")
    st, sh, sw = cfg.vae_stride
    c2w, K = np.asarray(clip["c2w"], dtype=np.float64), np.asarray(clip["K"], dtype=np.float64)
    T = len(c2w)
    H, W = h * sh, w * sw
    if (T - 1) // st + 1 != Fl:
        raise TrainingDataError(f"clip {name}: {T} cameras but {Fl} latent frames (temporal stride {st})")
    mask = i2v_mask(Fl, h, w, st)
    hidden_cond = np.concatenate([mask, np.asarray(clip["image_latents"], dtype=np.float32)], axis=0)
    rays = plucker_rays(c2w, K, H, W, convention=cfg.plucker_convention)
    out: dict[str, torch.Tensor | None] = {
        "x0": torch.from_numpy(x0)[None],
        "hidden_cond": torch.from_numpy(hidden_cond)[None],
        "text": torch.as_tensor(np.asarray(clip["text_embeds"], dtype=np.float32))[None],
        "image": torch.as_tensor(np.asarray(clip["image_embeds"], dtype=np.float32))[None],
        "plucker": plucker_to_tensor(rays),
        "cond": None, "image_reference": None, "image_reference_plucker": None,
    }
    if cfg.cond_channels:
        if "render_latents" not in clip or "visibility" not in clip:
            raise TrainingDataError(f"clip {name}: the control has cond_channels={cfg.cond_channels} but the clip "
                                    "has no render conditioning: precompute with data.render_condition=true or "
                                    "train a control with cond_channels=0")
        out["cond"] = make_render_condition(torch.as_tensor(np.asarray(clip["render_latents"], np.float32))[None],
                                            torch.as_tensor(np.asarray(clip["visibility"], np.float32))[None],
                                            cfg.vae_stride)
    if "reference_latents" in clip:
        out["image_reference"] = torch.as_tensor(np.asarray(clip["reference_latents"], np.float32))[None]
        ref_rays = clip_relative_rays(c2w, np.asarray(clip["reference_c2w"], np.float64)[None], K[0], H, W,
                                      convention=cfg.plucker_convention)
        out["image_reference_plucker"] = plucker_to_tensor(ref_rays)
    return {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in out.items()}


def flow_loss(model: torch.nn.Module, inner: CameraControlledWan, c: dict[str, torch.Tensor | None],
              generator: torch.Generator, config: CameraTrainingConfig, *, null_text: torch.Tensor | None = None,
              camera: str = "true", sigma: float | None = None, autocast: bool = False) -> torch.Tensor:
    """The rectified-flow loss of one clip (see the module docstring). ``model`` is what is called (the
    ``CameraControlledWan`` or its DDP wrapper), ``inner`` the unwrapped model.

    ``camera``: ``"true"`` (the clip's rays), ``"none"`` (no camera), or ``"given"`` (``c["plucker"]`` was
    already replaced by the caller, e.g. another clip's cameras). ``sigma`` fixes σ (evaluation).
    """
    x0 = c["x0"]
    device = x0.device
    u = torch.rand((), generator=generator)
    s = torch.as_tensor(float(sigma)) if sigma is not None else shift_sigma(u, config.flow_shift)
    noise = torch.randn(x0.shape, generator=generator).to(device)
    drop_text = bool(torch.rand((), generator=generator) < config.text_dropout)
    drop_cam = bool(torch.rand((), generator=generator) < config.camera_dropout)
    ref_seed = int(torch.randint(0, 2**62, (), generator=generator))
    if sigma is not None:
        drop_text = drop_cam = False
    inner.seed_reference_frames(ref_seed)
    sd = s.to(device)
    x_t = (1.0 - sd) * x0 + sd * noise
    target = noise - x0
    text = c["text"]
    if drop_text:
        if null_text is None:
            raise TrainingDataError("text_dropout > 0 needs the null prompt's embeddings (the clip store's "
                                    "null_text_embeds): precompute the store again or set text_dropout=0")
        text = null_text
    plucker = None if (camera == "none" or drop_cam) else c["plucker"]
    kwargs: dict[str, Any] = {}
    if c.get("image_reference") is not None and plucker is not None:
        kwargs = {"image_reference": c["image_reference"], "image_reference_plucker": c["image_reference_plucker"]}
    with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=autocast):
        pred = model(torch.cat([x_t, c["hidden_cond"]], dim=1), (1000.0 * sd).reshape(1), text, c["image"],
                     plucker, c["cond"], torch.tensor(TRAINING_LORA_SCALE, device=device),
                     reference_latents=x0, **kwargs)
    return torch.mean((pred.float() - target.float()) ** 2)


# --------------------------------------------------------------------------------------------------
# Optimiser state <-> safetensors
# --------------------------------------------------------------------------------------------------
def _optimizer_tensors(sd: dict[str, Any]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """``optimizer.state_dict()`` (index-keyed) -> the tensors of ``optimizer.safetensors`` and the JSON rest."""
    tensors, scalars = {}, {}
    for idx, st in sd["state"].items():
        for k, v in st.items():
            if isinstance(v, torch.Tensor) and v.ndim > 0:
                tensors[f"state.{idx}.{k}"] = v.detach().contiguous().cpu()
            else:
                scalars[f"{idx}.{k}"] = v.item() if isinstance(v, torch.Tensor) else v
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def _load_optimizer(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    opt.load_state_dict(_optimizer_state_dict(tensors, meta))


def _optimizer_state_dict(tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> dict[str, Any]:
    """The inverse of ``_optimizer_tensors``: an ``optimizer.state_dict()``."""
    state: dict[int, dict[str, Any]] = {}
    for key, v in tensors.items():
        _, idx, k = key.split(".", 2)
        state.setdefault(int(idx), {})[k] = v
    for key, v in meta["scalars"].items():
        idx, k = key.split(".", 1)
        state.setdefault(int(idx), {})[k] = torch.tensor(v, dtype=torch.float32) if k == "step" else v
    return {"state": state, "param_groups": meta["param_groups"]}


# --------------------------------------------------------------------------------------------------
# Trainer
# --------------------------------------------------------------------------------------------------
@dataclass
class StepLog:
    step: int
    loss: float
    lr: float
    clips_per_s: float


@dataclass
class TrainState:
    step: int = 0
    position: int = 0  # global samples consumed (the data position; independent of the world size)
    history: list[dict[str, float]] = field(default_factory=list)  # one row per step: step, loss, lr
    validation: list[dict[str, float]] = field(default_factory=list)


class CameraTrainer:
    """Trains ``model``'s camera control (or everything, ``config.trainable='all'``) on ``clips``.

    ``clips``: a sequence of stored clips (``tasks.training.clips.ClipDataset``: dicts of numpy arrays).
    ``rank``/``world_size``: this process in a ``torch.distributed`` group; when ``world_size > 1`` DDP wraps the
    model (``config.parallel="ddp"``) or FSDP2 shards it in place (``"fsdp"``: ``self.model`` is then the
    sharded module, and every forward, ``save_checkpoint`` and ``load_checkpoint`` must run on all ranks).
    ``null_text``: the null prompt's embeddings ``[512, text_dim]`` (text dropout).
    """

    def __init__(self, model: CameraControlledWan, clips: Sequence[dict[str, Any]], config: CameraTrainingConfig,
                 *, device: str | torch.device = "cpu", rank: int = 0, world_size: int = 1,
                 null_text: np.ndarray | None = None) -> None:
        if len(clips) == 0:
            raise TrainingDataError("no training clips: precompute the clip store first (train-camera "
                                    "precompute) or check data.sources")
        self.config = config
        self.device = torch.device(device)
        self.model = model.to(self.device)
        self.clips = clips
        self.rank, self.world_size = int(rank), int(world_size)
        model.requires_grad_(False)
        params = trainable_parameter_list(model, config)
        for p in params:
            p.requires_grad_(True)
        self.params = params
        model.gradient_checkpointing = bool(config.gradient_checkpointing)
        model.train()
        self.sharded = config.parallel == "fsdp" and self.world_size > 1
        if self.sharded:
            shard_model(model, device=self.device)
            # fully_shard replaced every parameter by a sharded DTensor: optimise those
            params = trainable_parameter_list(model, config)
            self.params = params
        self.opt = torch.optim.AdamW(params, lr=config.optim.learning_rate, betas=tuple(config.optim.betas),
                                     weight_decay=config.optim.weight_decay)
        self.autocast = config.mixed_precision == "bf16" and self.device.type == "cuda"
        self.null_text = (None if null_text is None else
                          torch.as_tensor(np.asarray(null_text, np.float32))[None].to(self.device))
        self.state = TrainState()
        self.wrapped: torch.nn.Module = model
        if self.world_size > 1 and not self.sharded:
            from torch.nn.parallel import DistributedDataParallel

            self.wrapped = DistributedDataParallel(model, device_ids=None if self.device.type == "cpu"
                                                   else [self.device], find_unused_parameters=True)

    # ---- data order ---------------------------------------------------------------------------------
    def global_indices(self) -> list[int]:
        """Global sample indices of the next step (all ranks), in order."""
        b = self.config.optim.batch_size * self.world_size
        return list(range(self.state.position, self.state.position + b))

    def clip_of(self, index: int) -> int:
        n = len(self.clips)
        return int(epoch_order(self.config.seed, index // n, n)[index % n])

    def local_indices(self) -> list[int]:
        b = self.config.optim.batch_size
        return self.global_indices()[self.rank * b:(self.rank + 1) * b]

    def lr_at(self, step: int) -> float:
        warm = self.config.optim.warmup_steps
        base = self.config.optim.learning_rate
        return base * min(1.0, (step + 1) / warm) if warm else base

    # ---- one step -----------------------------------------------------------------------------------
    def train_step(self) -> StepLog:
        step = self.state.step
        t0 = time.perf_counter()
        lr = self.lr_at(step)
        for g in self.opt.param_groups:
            g["lr"] = lr
        self.opt.zero_grad(set_to_none=True)
        indices = self.local_indices()
        mean = self.step_loss(indices)
        if self.config.optim.grad_clip is not None:
            # over sharded DTensor gradients (fsdp) the norm is the global one, as in a single process
            torch.nn.utils.clip_grad_norm_(self.params, self.config.optim.grad_clip)
        self.opt.step()
        if self.world_size > 1:
            t = torch.tensor([mean], dtype=torch.float64, device=self.device)
            torch.distributed.all_reduce(t)
            mean = float(t) / self.world_size
        self.state.step = step + 1
        self.state.position += self.config.optim.batch_size * self.world_size
        self.state.history.append({"step": step + 1, "loss": mean, "lr": lr})
        dt = time.perf_counter() - t0
        return StepLog(step + 1, mean, lr, len(indices) * self.world_size / max(dt, 1e-9))

    def step_loss(self, indices: list[int]) -> float:
        """Forward and backward of one step's clips on this rank (gradients accumulated, each clip's loss over
        ``len(indices)``); returns the mean of their losses. ``train_step`` wraps it (lr, zero_grad, clipping,
        optimizer step, state); a subclass may compute the same loss another way (e.g. the clips in one call:
        ``benchmarks/camera_control_mini.py``)."""
        total = 0.0
        use = None
        if self.sharded:
            use = ParameterUse(len(self.params), self.device)
        for j, index in enumerate(indices):
            c = clip_conditions(self.model, self.clips[self.clip_of(index)], self.device)
            last = j == len(indices) - 1
            ctx = contextlib.nullcontext()
            if self.sharded:  # FSDP2's no_sync: keep the unsharded gradients, reduce-scatter after the last
                self.wrapped.set_requires_gradient_sync(last)
            elif self.world_size > 1 and not last:
                ctx = self.wrapped.no_sync()
            with ctx:
                loss = flow_loss(self.wrapped, self.model, c, sample_generator(self.config.seed, index),
                                 self.config, null_text=self.null_text, autocast=self.autocast)
                objective = loss / len(indices)
                if use is not None:  # same gradient set on every rank (distributed.ParameterUse)
                    objective = objective + use.touch(loss, trainable_parameter_list(self.model, self.config))
                objective.backward()
            total += float(loss.detach())
        if use is not None:
            use.drop_unused(self.params)
        return total / len(indices)

    # ---- checkpoints --------------------------------------------------------------------------------
    def save_checkpoint(self, run_dir: str | os.PathLike) -> Path:
        """Write ``run_dir/checkpoints/step-XXXXXXXX`` atomically and point ``latest`` at it (rank 0 writes; with
        fsdp every rank must call it: the full state is gathered first)."""
        from safetensors.torch import save_file

        root = Path(run_dir) / CHECKPOINT_DIR
        name = f"step-{self.state.step:08d}"
        final = root / name
        train_base = self.config.trainable in ("base", "all")
        if self.sharded:
            full_control = full_module_state(self.model.control)
            full_base = full_module_state(self.model.base) if train_base else {}
            opt_state = full_optimizer_state(self.opt)
        if self.rank != 0:
            return final
        tmp = root / (name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        if train_base:
            base_state = (full_base if self.sharded else
                          {k: v.detach().contiguous().cpu() for k, v in self.model.base.state_dict().items()})
            save_file(base_state, str(tmp / "base.safetensors"))
        if self.sharded:
            save_control_state(self.model, full_control, tmp)
        else:
            save_camera_control(self.model, tmp)
            opt_state = self.opt.state_dict()
        tensors, meta = _optimizer_tensors(opt_state)
        save_file(tensors, str(tmp / OPTIMIZER_FILE))
        state = {"step": self.state.step, "data_position": self.state.position, "world_size": self.world_size,
                 "optimizer": meta,
                 "torch_rng": torch.get_rng_state().tolist(), "history": self.state.history,
                 "validation": self.state.validation, "config": json.loads(self.config.model_dump_json())}
        (tmp / STATE_FILE).write_text(json.dumps(state))
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
        (root / (LATEST + ".tmp")).write_text(name)
        os.replace(root / (LATEST + ".tmp"), root / LATEST)
        done = sorted(p for p in root.glob("step-*") if not p.name.endswith(".tmp"))
        for old in done[:-self.config.keep_checkpoints]:
            shutil.rmtree(old, ignore_errors=True)
        return final

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Load a checkpoint written by any run (one process, DDP or FSDP). With fsdp every rank must call it:
        rank 0 reads the files and sends every rank its shards."""
        from safetensors.torch import load_file

        path = Path(path)
        if self.sharded:
            state = self._load_sharded(path)
        else:
            state = json.loads((path / STATE_FILE).read_text())
            if (path / "base.safetensors").is_file():
                base = load_file(str(path / "base.safetensors"))
                self.model.base.load_state_dict(base, strict=True)
            load_camera_control(self.model, path)
            _load_optimizer(self.opt, load_file(str(path / OPTIMIZER_FILE)), state["optimizer"])
        torch.set_rng_state(torch.tensor(state["torch_rng"], dtype=torch.uint8))
        self.state = TrainState(step=int(state["step"]), position=int(state["data_position"]),
                                history=list(state["history"]), validation=list(state.get("validation", [])))
        self.model.train()

    def _load_sharded(self, path: Path) -> dict[str, Any]:
        from safetensors.torch import load_file

        full: dict[str, Any] = {}  # rank 0's full tensors

        def read() -> tuple[dict[str, Any], bool, dict[str, Any]]:
            state = json.loads((path / STATE_FILE).read_text())
            has_base = (path / "base.safetensors").is_file()
            if has_base:
                full["base"] = load_file(str(path / "base.safetensors"))
            full["control"], control_config = read_control_state(self.model, path)
            full["optimizer"] = _optimizer_state_dict(load_file(str(path / OPTIMIZER_FILE)), state["optimizer"])
            return state, has_base, control_config.to_dict()

        state, has_base, control_config = rank0_only(read)  # a bad file raises on every rank
        if has_base:
            load_full_module_state(self.model.base, full.get("base", {}))
        load_full_module_state(self.model.control, full.get("control", {}))
        apply_control_config(self.model, CameraControlConfig.from_dict(control_config))
        load_full_optimizer_state(self.opt, full.get("optimizer", {}))
        return state

    def resume(self, run_dir: str | os.PathLike) -> bool:
        """Load the newest complete checkpoint of ``run_dir``; False when there is none."""
        if self.sharded:  # rank 0 reads the files (the other ranks need not see them)
            latest = rank0_only(lambda: latest_checkpoint(run_dir))
        else:
            latest = latest_checkpoint(run_dir)
        if latest is None:
            return False
        self.load_checkpoint(latest)
        return True

    # ---- loop ---------------------------------------------------------------------------------------
    def train(self, run_dir: str | os.PathLike | None, steps: int | None = None,
              on_step: Callable[[StepLog], None] | None = None,
              on_checkpoint: Callable[[int], None] | None = None) -> TrainState:
        """Train until ``steps`` (default ``config.steps``), checkpointing every ``checkpoint_every`` steps
        (and at the end) into ``run_dir`` when given."""
        end = int(steps if steps is not None else self.config.steps)
        while self.state.step < end:
            log = self.train_step()
            if on_step is not None:
                on_step(log)
            if run_dir is not None and (log.step % self.config.checkpoint_every == 0 or log.step == end):
                if on_checkpoint is not None:
                    on_checkpoint(log.step)
                self.save_checkpoint(run_dir)
        return self.state


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    root = Path(run_dir) / CHECKPOINT_DIR
    marker = root / LATEST
    if not marker.is_file():
        return None
    path = root / marker.read_text().strip()
    return path if (path / STATE_FILE).is_file() else None


# --------------------------------------------------------------------------------------------------
# Evaluation: the camera-conditioning gap
# --------------------------------------------------------------------------------------------------
@torch.no_grad()
def evaluation_loss(model: CameraControlledWan, clips: Sequence[dict[str, Any]], config: CameraTrainingConfig,
                    *, cameras: str = "true", sigmas: Sequence[float] = (0.2, 0.4, 0.6, 0.8), seed: int = 0,
                    device: str | torch.device = "cpu", per_clip: bool = False) -> float | list[float]:
    """Mean flow loss over ``clips`` × ``sigmas`` with fixed noise (seeded per clip and σ); ``per_clip``: the
    mean of each clip instead.

    ``cameras``: ``"true"``; ``"shuffled"`` (clip ``i`` gets the cameras of clip ``i+1 mod n``: a
    derangement, so no clip keeps its own); ``"none"``. The camera-conditioning gap is
    ``loss(shuffled) - loss(true)``: zero for a model that ignores the camera.

    With a model sharded by an fsdp trainer every rank must call it with the same clips (each forward gathers
    the shards): called on rank 0 alone it waits forever for the other ranks.
    """
    was = model.training
    model.eval()
    n = len(clips)
    if cameras == "shuffled" and n < 2:
        raise ValueError("shuffled cameras need at least 2 clips")
    conds = [clip_conditions(model, c, device) for c in clips]
    losses: list[float] = []
    for i, c in enumerate(conds):
        c = dict(c)
        mode = "true"
        if cameras == "shuffled":
            other = conds[(i + 1) % n]
            c["plucker"] = other["plucker"]
            if c.get("image_reference") is not None and other.get("image_reference_plucker") is not None:
                c["image_reference_plucker"] = other["image_reference_plucker"]
            mode = "given"
        elif cameras == "none":
            mode = "none"
        clip_total = 0.0
        for j, s in enumerate(sigmas):
            g = torch.Generator().manual_seed(_seed(seed, 3, i, j))
            model.seed_reference_frames(_seed(seed, 4, i))
            clip_total += float(flow_loss(model, model, c, g, config, camera=mode, sigma=float(s)))
        losses.append(clip_total / len(sigmas))
    model.train(was)
    if per_clip:
        return losses
    return float(np.mean(losses)) if losses else 0.0


def camera_gap(model: CameraControlledWan, clips: Sequence[dict[str, Any]], config: CameraTrainingConfig,
               **kw: Any) -> dict[str, Any]:
    """Flow loss with the clips' own cameras and with shuffled ones (``evaluation_loss``), their difference (the
    camera-conditioning gap), its per-clip values and its standard error over clips."""
    true = evaluation_loss(model, clips, config, cameras="true", per_clip=True, **kw)
    shuffled = evaluation_loss(model, clips, config, cameras="shuffled", per_clip=True, **kw)
    gaps = np.asarray(shuffled) - np.asarray(true)
    se = float(gaps.std(ddof=1) / np.sqrt(len(gaps))) if len(gaps) > 1 else float("nan")
    return {"loss_true_cameras": float(np.mean(true)), "loss_shuffled_cameras": float(np.mean(shuffled)),
            "camera_gap": float(gaps.mean()), "camera_gap_se": se, "camera_gap_per_clip": gaps.tolist()}


def trainable_parameter_list(model: CameraControlledWan, config: CameraTrainingConfig) -> list[torch.nn.Parameter]:
    """What ``config.trainable`` trains: the control, the base, or both."""
    return {"control": lambda: list(model.control.parameters()), "base": lambda: list(model.base.parameters()),
            "all": lambda: list(model.parameters())}[config.trainable]()


def trainable_parameters(model: CameraControlledWan, config: CameraTrainingConfig) -> int:
    return int(sum(p.numel() for p in trainable_parameter_list(model, config)))


# --------------------------------------------------------------------------------------------------
# Validation sampling from stored conditions
# --------------------------------------------------------------------------------------------------
def stack_conditions(cs: Sequence[dict[str, torch.Tensor | None]]) -> dict[str, torch.Tensor | None]:
    """Several clips' ``clip_conditions`` as one batch (each tensor concatenated along its batch dimension), for
    ``sample_clip`` over a batch. A key must be a tensor in every clip or None in every clip."""
    if not cs:
        raise ValueError("stack_conditions needs at least one clip's conditions")
    out: dict[str, torch.Tensor | None] = {}
    for k in cs[0]:
        vals = [c[k] for c in cs]
        if all(v is None for v in vals):
            out[k] = None
        elif any(v is None for v in vals):
            raise ValueError(f"stack_conditions: {k!r} is None in some clips and not in others: batch clips whose "
                             "conditions have the same keys (same render conditioning, same reference frames)")
        else:
            out[k] = torch.cat(vals, dim=0)
    return out


@torch.no_grad()
def sample_clip(model: CameraControlledWan, c: dict[str, torch.Tensor | None], *, seed: int | Sequence[int],
                steps: int, guidance_scale: float, lora_scale: float, flow_shift: float,
                null_text: torch.Tensor | None = None) -> torch.Tensor:
    """Denoised latents ``[B, C, F, h, w]`` for the stored conditions ``c`` (``clip_conditions``, or a batch of
    them from ``stack_conditions`` with one seed per clip), with the product's scheduler (``pipeline.make_scheduler``:
    DPM-solver on flow sigmas) and noise (``pipeline.initial_noise``, per clip: a clip's noise does not depend on
    its batch). CFG over the text (``null_text``; with ``guidance_scale == 1`` one branch)."""
    was = model.training
    model.eval()
    x0 = c["x0"]
    B, C, Fl, h, w = x0.shape
    seeds = [int(seed)] if isinstance(seed, int) else [int(s) for s in seed]
    if len(seeds) != B:
        raise ValueError(f"sample_clip: {len(seeds)} seeds for a batch of {B} clips: give one seed per clip")
    cfg = SamplerConfig(steps=steps, guidance_scale=guidance_scale, lora_scale=lora_scale, flow_shift=flow_shift,
                        seed=seeds[0])
    scheduler = make_scheduler(cfg)
    scheduler.set_timesteps(steps, device="cpu")
    dev = x0.device  # the noise is drawn on the CPU (initial_noise: the same on every device), then moved
    latents = torch.from_numpy(np.concatenate([initial_noise(s, C, Fl, h, w) for s in seeds])).to(dev)
    kwargs: dict[str, Any] = {}
    if c.get("image_reference") is not None and c.get("plucker") is not None:
        kwargs = {"image_reference": c["image_reference"], "image_reference_plucker": c["image_reference_plucker"]}
    lora = torch.tensor(float(lora_scale), device=dev)
    for t in scheduler.timesteps:
        hidden = torch.cat([latents.to(x0.dtype), c["hidden_cond"]], dim=1)
        ts = torch.full((B,), float(t), device=dev)
        pred = model(hidden, ts, c["text"], c["image"], c["plucker"], c["cond"], lora, **kwargs)
        if guidance_scale != 1.0:
            if null_text is None:
                raise ValueError("guidance_scale != 1 needs null_text (the null prompt's embeddings)")
            null = null_text.expand(B, *null_text.shape[1:])
            un = model(hidden, ts, null, c["image"], c["plucker"], c["cond"], lora, **kwargs)
            pred = un + guidance_scale * (pred - un)
        latents = scheduler.step(pred.float(), t, latents, return_dict=False)[0].float()
    model.train(was)
    return latents

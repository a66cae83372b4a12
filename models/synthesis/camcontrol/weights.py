"""Weights I/O: the diffusers-format Wan base (``load_wan_transformer``) and the camera-control weights
(``save_camera_control`` / ``load_camera_control``: safetensors + JSON, never pickles)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from diffusers.models.transformers.transformer_wan import WanTransformer3DModel

from navcrafter.models.checkpoints import check_layout, safetensors_files
from navcrafter.models.synthesis.camcontrol.config import (
    _V1_DEFAULTS,
    CONTROL_CONFIG,
    CONTROL_FORMAT,
    CONTROL_FORMAT_VERSION,
    CONTROL_WEIGHTS,
    READABLE_FORMAT_VERSIONS,
    CameraControlConfig,
    CameraControlWeightsError,
)

if TYPE_CHECKING:
    from navcrafter.models.synthesis.camcontrol.model import CameraControlledWan


def load_wan_transformer(directory: str | os.PathLike, torch_dtype: torch.dtype | None = None
                         ) -> WanTransformer3DModel:
    """``WanTransformer3DModel`` from a diffusers-format directory (``<dir>/transformer`` or ``<dir>`` itself).

    Uses ``WanTransformer3DModel.from_pretrained`` when ``accelerate`` is installed. Without it diffusers 0.42
    refuses Wan outright (``low_cpu_mem_usage`` falls back to False, which ``_keep_in_fp32_modules``
    forbids), so the same files are read here: config + (sharded) safetensors, names checked, no pickles.
    """
    from diffusers.utils import is_accelerate_available

    directory = Path(directory)
    if (directory / "transformer" / "config.json").is_file():
        directory = directory / "transformer"
    elif not (directory / "config.json").is_file():
        raise FileNotFoundError(f"{directory}: no diffusers Wan transformer (expected "
                                f"{directory / 'transformer' / 'config.json'} or {directory / 'config.json'})")
    if is_accelerate_available():
        kwargs = {"torch_dtype": torch_dtype} if torch_dtype is not None else {}
        return WanTransformer3DModel.from_pretrained(directory, **kwargs)

    from diffusers.models.modeling_utils import no_init_weights
    from safetensors.torch import load_file

    files = safetensors_files(directory)
    with no_init_weights():
        model = WanTransformer3DModel.from_config(WanTransformer3DModel.load_config(directory))
    state: dict[str, torch.Tensor] = {}
    for f in files:
        state.update(load_file(str(f)))
    ignore = WanTransformer3DModel._keys_to_ignore_on_load_unexpected or []
    expected = model.state_dict()
    check_layout({k: v for k, v in state.items() if k in expected or not any(p in k for p in ignore)}, expected,
                 CameraControlWeightsError, f"{directory}: Wan weights do not fit its config.json")
    model.load_state_dict({k: state[k] for k in expected}, strict=True)
    if torch_dtype is not None:
        model.to(torch_dtype)
        keep = WanTransformer3DModel._keep_in_fp32_modules or []
        for name, tensor in [*model.named_parameters(), *model.named_buffers()]:
            if any(k in name.split(".") for k in keep):
                tensor.data = tensor.data.float()
    return model.eval()


def _base_summary(base: WanTransformer3DModel) -> dict[str, Any]:
    c = base.config
    return {"num_layers": c.num_layers, "num_attention_heads": c.num_attention_heads,
            "attention_head_dim": c.attention_head_dim, "patch_size": list(c.patch_size),
            "in_channels": c.in_channels, "out_channels": c.out_channels}


def _dict_diff(a: dict, b: dict) -> str:
    keys = sorted(set(a) | set(b))
    return ", ".join(f"{k}: {a.get(k)!r} vs {b.get(k)!r}" for k in keys if a.get(k) != b.get(k))


def save_camera_control(model: CameraControlledWan, directory: str | os.PathLike) -> Path:
    """Write ``camera_control.safetensors`` + ``camera_control.json`` (config, base sizes, tensor shapes).

    The JSON is written last (temp file + rename): a directory with it holds a complete save.
    """
    from safetensors.torch import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().contiguous().cpu() for k, v in model.control.state_dict().items()}
    weights = directory / CONTROL_WEIGHTS
    tmp = directory / (CONTROL_WEIGHTS + ".tmp")
    save_file(state, str(tmp), metadata={"format": CONTROL_FORMAT})
    os.replace(tmp, weights)
    meta = {"format": CONTROL_FORMAT, "format_version": CONTROL_FORMAT_VERSION, "config": model.config.to_dict(),
            "base": _base_summary(model.base), "weights": CONTROL_WEIGHTS,
            "tensors": {k: list(v.shape) for k, v in state.items()}}
    tmp = directory / (CONTROL_CONFIG + ".tmp")
    tmp.write_text(json.dumps(meta, indent=2, sort_keys=True))
    os.replace(tmp, directory / CONTROL_CONFIG)
    return directory


def _read_meta(directory: str | os.PathLike) -> dict[str, Any]:
    path = Path(directory) / CONTROL_CONFIG
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no camera-control config (write one with save_camera_control)")
    meta = json.loads(path.read_text())
    version = meta.get("format_version")
    if meta.get("format") != CONTROL_FORMAT or version not in READABLE_FORMAT_VERSIONS:
        raise CameraControlWeightsError(f"{path}: not a {CONTROL_FORMAT} config of a readable version "
                                        f"{list(READABLE_FORMAT_VERSIONS)} (format {meta.get('format')!r}, "
                                        f"version {version!r})")
    if version == 1:  # full D x D projections; the convention it records (v1's default when absent)
        meta["config"] = {**_V1_DEFAULTS, **meta.get("config", {})}
    return meta


def read_camera_control_config(directory: str | os.PathLike) -> CameraControlConfig:
    return CameraControlConfig.from_dict(_read_meta(directory)["config"])


def load_camera_control(model: CameraControlledWan, directory: str | os.PathLike) -> CameraControlledWan:
    """Load ``save_camera_control``'s files into ``model`` (in place; also returns it).

    Checks the base sizes, then every tensor name and shape, and raises ``CameraControlWeightsError``
    naming the file and the offending keys. The saved config (Plücker convention, default α, reference
    frames) replaces ``model.config``: it describes how the weights were trained.
    """
    from safetensors import safe_open

    directory = Path(directory)
    meta = _read_meta(directory)
    saved_cfg = CameraControlConfig.from_dict(meta["config"])
    base_now = _base_summary(model.base)
    if meta.get("base") != base_now:
        raise CameraControlWeightsError(f"{directory / CONTROL_CONFIG}: saved for a different base DiT "
                                        f"({_dict_diff(meta.get('base') or {}, base_now)})")
    path = directory / meta.get("weights", CONTROL_WEIGHTS)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: camera-control weights missing")
    expected = model.control.state_dict()
    with safe_open(str(path), framework="pt") as f:
        keys = set(f.keys())
        check_layout({k: f.get_slice(k).get_shape() for k in keys}, expected, CameraControlWeightsError,
                     f"{path}: camera-control weights do not fit the model")
        state = {k: f.get_tensor(k) for k in keys}
    with torch.no_grad():
        for k, v in expected.items():
            v.copy_(state[k].to(dtype=v.dtype, device=v.device))
    model.config = saved_cfg
    model._ref_generator = torch.Generator().manual_seed(saved_cfg.reference_seed)
    return model

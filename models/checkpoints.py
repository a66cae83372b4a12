"""Reading official checkpoints and checking their layout: one helper for every learned model.

The model packages (``synthesis.camcontrol``, ``synthesis.funcamera``, ``geometry.vggt``, ``geometry.moge``,
``refiner.difix``) read official weight files and refuse any that do not hold exactly the tensors their config
describes. What they share lives here; each passes its own error class and says which model it is, so a message
still names the model, the file and what is missing, unexpected or mis-shaped:

- ``listing``: a shortened list of names for an error message;
- ``layout_problems`` / ``check_layout``: the strict name-and-shape comparison of a file against a model;
- ``load_safetensors``, ``load_tensor_only``, ``read_state_dict``: tensors from ``.safetensors`` or a tensor-only
  torch file (``torch.load(weights_only=True)``: pickled code is refused, never loaded);
- ``safetensors_files``: the files of a single or sharded diffusers-style safetensors checkpoint;
- ``DINOV2_BLOCK_NAMES``: the official DINOv2 block names -> transformers' (VGGT's and MoGe-2's encoders).

A leaf module (torch and safetensors only, both imported on use) so that no model package imports another, or
``models.runtime``, to share it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

LISTED = 10  # names shown before "... (+N more)"

# A DINOv2 ViT block (facebookresearch/dinov2, the backbone of VGGT and MoGe-2) under its official parameter names
# -> transformers' Dinov2 modules (the ones built here), in the official order. ``None``: the fused ``attn.qkv``,
# which each loader splits into ``attention.{q,k,v}_proj``.
DINOV2_BLOCK_NAMES: tuple[tuple[str, str | None], ...] = (
    ("norm1.weight", "norm1.weight"), ("norm1.bias", "norm1.bias"),
    ("attn.qkv.weight", None), ("attn.qkv.bias", None),
    ("attn.proj.weight", "attention.o_proj.weight"), ("attn.proj.bias", "attention.o_proj.bias"),
    ("ls1.gamma", "layer_scale1.lambda1"),
    ("norm2.weight", "norm2.weight"), ("norm2.bias", "norm2.bias"),
    ("mlp.fc1.weight", "mlp.fc1.weight"), ("mlp.fc1.bias", "mlp.fc1.bias"),
    ("mlp.fc2.weight", "mlp.fc2.weight"), ("mlp.fc2.bias", "mlp.fc2.bias"),
    ("ls2.gamma", "layer_scale2.lambda1"),
)


def listing(names: Iterable[str], limit: int = LISTED) -> str:
    """``"a, b, c ... (+N more)"``: the first ``limit`` names and how many more there are."""
    names = list(names)
    more = f" ... (+{len(names) - limit} more)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _shape(value: Any) -> tuple[int, ...]:
    return tuple(int(s) for s in (value.shape if hasattr(value, "shape") else value))


def layout_problems(found: Mapping[str, Any], expected: Mapping[str, Any], *, optional: Iterable[str] = ()
                    ) -> list[str]:
    """What keeps ``found`` from being exactly ``expected``: ``[]`` when every name is there with its shape.

    Both map names to shapes (tensors or sequences of ints); names in ``optional`` may be absent. The problems read
    ``missing keys [...]``, ``unexpected keys [...]`` and ``shape mismatch [name: file [...] vs model [...]]``,
    names sorted and shortened by ``listing``.
    """
    optional = set(optional)
    missing = sorted(set(expected) - set(found) - optional)
    unexpected = sorted(set(found) - set(expected))
    mismatched = [f"{k}: file {list(_shape(found[k]))} vs model {list(_shape(expected[k]))}"
                  for k in sorted(set(found) & set(expected)) if _shape(found[k]) != _shape(expected[k])]
    problems = []
    if missing:
        problems.append(f"missing keys [{listing(missing)}]")
    if unexpected:
        problems.append(f"unexpected keys [{listing(unexpected)}]")
    if mismatched:
        problems.append(f"shape mismatch [{listing(mismatched)}]")
    return problems


def check_layout(found: Mapping[str, Any], expected: Mapping[str, Any], error: type[Exception], what: str, *,
                 optional: Iterable[str] = (), hint: str = "") -> None:
    """Raise ``error("<what>: <problems><hint>")`` unless ``found`` has exactly the names and shapes of
    ``expected`` (``layout_problems``). ``what`` names the file and the model's layout, ``hint`` the fix."""
    problems = layout_problems(found, expected, optional=optional)
    if problems:
        raise error(f"{what}: " + "; ".join(problems) + hint)


def load_safetensors(path: str | Path, error: type[Exception]) -> dict[str, Any]:
    """All tensors of a ``.safetensors`` file (on the CPU); ``error`` when it cannot be read as one."""
    from safetensors.torch import load_file

    try:
        return load_file(str(path), device="cpu")
    except Exception as exc:  # safetensors raises its own error types (SafetensorError, OSError, ...)
        raise error(f"{path}: not a readable safetensors file ({exc})") from exc


def load_tensor_only(path: str | Path, error: type[Exception]) -> Any:
    """What a torch file holds, read with ``torch.load(weights_only=True)``: tensors and plain containers only.
    A file holding pickled code raises ``error``; there is never a fall-back to a full unpickling."""
    import torch

    try:
        return torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:
        raise error(f"{path}: not a tensor-only torch checkpoint (torch.load(weights_only=True) refused it: "
                    f"{exc})") from exc


def read_state_dict(path: str | Path, error: type[Exception], model: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(state dict, the file's other entries)`` from one checkpoint file of ``model`` (its name, for messages).

    ``.safetensors``: its tensors (no other entries). Anything else: a tensor-only torch file holding either a
    state dict (name -> tensor) or a dict with one under ``"model"`` (the official training format; its other
    entries, e.g. ``"model_config"``, are returned beside it). ``error`` names the file otherwise.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise error(f"{model} checkpoint {path} does not exist")
    if path.suffix == ".safetensors":
        return load_safetensors(path, error), {}
    data = load_tensor_only(path, error)
    extra: dict[str, Any] = {}
    if isinstance(data, dict) and isinstance(data.get("model"), dict):
        data, extra = data["model"], {k: v for k, v in data.items() if k != "model"}
    if not isinstance(data, dict) or not all(isinstance(v, torch.Tensor) for v in data.values()):
        raise error(f"{path}: expected a {model} state dict (name -> tensor) or a dict with one under 'model', "
                    f"got {type(data).__name__}")
    return data, extra


def safetensors_files(directory: str | Path, stem: str = "diffusion_pytorch_model") -> list[Path]:
    """The files of a diffusers-style safetensors checkpoint in ``directory``: the shards its
    ``<stem>.safetensors.index.json`` lists, else ``<stem>.safetensors``, else every ``<stem>*.safetensors``.
    Pickled weights (``.bin``, ``.pth``) are named in the error, never read."""
    directory = Path(directory)
    index = directory / f"{stem}.safetensors.index.json"
    if index.is_file():
        return [directory / s for s in sorted(set(json.loads(index.read_text())["weight_map"].values()))]
    single = directory / f"{stem}.safetensors"
    if single.is_file():
        return [single]
    found = sorted(directory.glob(f"{stem}*.safetensors"))
    if found:
        return found
    pickles = sorted(p.name for p in directory.glob("*.pth")) + sorted(p.name for p in directory.glob("*.bin"))
    extra = f" (found {pickles}: only safetensors are read)" if pickles else ""
    raise FileNotFoundError(f"{directory}: no {single.name} or {index.name}{extra}")


def safetensors_layout(files: Sequence[Path], error: type[Exception]) -> dict[str, tuple[int, ...]]:
    """Name -> shape over the ``files`` of one (sharded) checkpoint, read from the headers only (no tensor is
    loaded); a listed file that is absent raises ``FileNotFoundError``, a name in two files ``error``."""
    from safetensors import safe_open

    found: dict[str, tuple[int, ...]] = {}
    where: dict[str, Path] = {}
    for f in files:
        if not Path(f).is_file():
            raise FileNotFoundError(f"{f}: listed in the checkpoint's index but missing")
        with safe_open(str(f), framework="pt") as sf:
            for k in sf.keys():
                if k in found:
                    raise error(f"{f}: key {k} also in {where[k]}")
                found[k], where[k] = tuple(sf.get_slice(k).get_shape()), Path(f)
    return found

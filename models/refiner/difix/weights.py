"""The official Difix checkpoint layouts (diffusers ``unet/`` + ``vae/`` folders, the training ``.pkl`` with an
SD-Turbo base), the committed key list, the strict loader and the writer; reading and checking files is
``models.checkpoints``'s."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from navcrafter.models import checkpoints
from navcrafter.models.refiner.difix.config import OFFICIAL_KEYS_SD_TURBO, UNET_FILE, VAE_FILE, DifixWeightsError
from navcrafter.models.refiner.difix.modules import lora_target_modules
from navcrafter.models.runtime.onnxio import sha256_file

if TYPE_CHECKING:
    from navcrafter.models.refiner.difix.model import DifixRefinerModel


def official_state_dicts(model: DifixRefinerModel) -> dict[str, dict[str, torch.Tensor]]:
    """``{"unet": ..., "vae": ...}``: the tensors of ``unet/`` and ``vae/diffusion_pytorch_model.safetensors``."""
    vae = model.vae.state_dict()
    if not any(".lora_A." in k for k in vae) and lora_target_modules(model.vae):
        raise ValueError("the model's LoRA adapters were merged (merge_lora_); it has no official layout any more")
    return {"unet": dict(model.unet.state_dict()), "vae": dict(vae)}


def official_key_shapes(model: DifixRefinerModel) -> dict[str, dict[str, tuple[int, ...]]]:
    return {part: {k: tuple(v.shape) for k, v in sd.items()} for part, sd in official_state_dicts(model).items()}


def read_official_key_list(path: Path = OFFICIAL_KEYS_SD_TURBO) -> dict[str, dict[str, tuple[int, ...]]]:
    """A committed ``part name shape`` list (part ``unet`` or ``vae``, dims joined by 'x'); ``#`` comments."""
    out: dict[str, dict[str, tuple[int, ...]]] = {"unet": {}, "vae": {}}
    for line in Path(path).read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            part, name, shape = line.split()
            out[part][name] = tuple(int(s) for s in shape.split("x")) if shape != "scalar" else ()
    return out


def write_official_key_list(model: DifixRefinerModel, path: Path, header: str = "") -> Path:
    lines = [f"# {h}" for h in header.splitlines()] if header else []
    for part, shapes in official_key_shapes(model).items():
        lines += [f"{part} {k} {'x'.join(map(str, s)) or 'scalar'}" for k, s in shapes.items()]
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


def save_difix_weights(model: DifixRefinerModel, directory: Path) -> Path:
    """Write the model in the official diffusers layout: ``unet/`` and ``vae/`` each with
    ``diffusion_pytorch_model.safetensors`` (fp32, metadata ``{"format": "pt"}``) and diffusers' ``config.json``."""
    from safetensors.torch import save_file

    directory = Path(directory)
    parts = official_state_dicts(model)
    for part, module in (("unet", model.unet), ("vae", model.vae)):
        (directory / part).mkdir(parents=True, exist_ok=True)
        save_file({k: v.contiguous() for k, v in parts[part].items()},
                  str(directory / part / "diffusion_pytorch_model.safetensors"), metadata={"format": "pt"})
        module.to_json_file(str(directory / part / "config.json"))
    return directory


def _load_safetensors(path: Path) -> dict[str, torch.Tensor]:
    return checkpoints.load_safetensors(path, DifixWeightsError)


def _read_checkpoint(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor], dict[str, Any]]:
    """(unet, vae, info) from a diffusers directory or a training ``.pkl``; info has "files" (name -> sha256)
    and, for ``.pkl``, "rank_vae" and "vae_lora_target_modules"."""
    if path.is_dir():
        unet_file, vae_file = path / UNET_FILE, path / VAE_FILE
        if not unet_file.is_file() or not vae_file.is_file():
            raise DifixWeightsError(
                f"{path} is not a Difix diffusers directory: it needs {UNET_FILE} and {VAE_FILE} (download "
                f"nvidia/difix_ref or nvidia/difix with all its folders, or pass a training checkpoint .pkl)")
        files = {UNET_FILE: sha256_file(unet_file), VAE_FILE: sha256_file(vae_file)}
        return _load_safetensors(unet_file), _load_safetensors(vae_file), {"files": files}
    if not path.is_file():
        raise DifixWeightsError(f"Difix checkpoint {path} does not exist")
    if path.suffix == ".safetensors":
        raise DifixWeightsError(
            f"{path}: a single .safetensors file is not a Difix layout; pass the model directory holding "
            f"{UNET_FILE} and {VAE_FILE} (nvidia/difix_ref), or the training checkpoint model_*.pkl")
    data = checkpoints.load_tensor_only(path, DifixWeightsError)
    if not isinstance(data, dict) or not isinstance(data.get("state_dict_unet"), dict):
        raise DifixWeightsError(f"{path}: expected the official training checkpoint (a dict with "
                                f"'state_dict_unet', 'state_dict_vae', 'rank_vae', 'vae_lora_target_modules')")
    info = {"files": {path.name: sha256_file(path)}, "rank_vae": data.get("rank_vae"),
            "vae_lora_target_modules": data.get("vae_lora_target_modules")}
    return dict(data["state_dict_unet"]), dict(data.get("state_dict_vae") or {}), info


def _base_weights(base: Path, model: DifixRefinerModel) -> tuple[dict, dict, dict[str, str]]:
    """SD-Turbo's UNet and VAE (plain diffusers names) with the VAE renamed to the LoRA layout
    (``X.weight`` -> ``X.base_layer.weight`` for adapted modules)."""
    base = Path(base)
    unet_file, vae_file = base / UNET_FILE, base / VAE_FILE
    if not unet_file.is_file() or not vae_file.is_file():
        raise DifixWeightsError(f"base {base} is not an SD-Turbo diffusers directory (needs {UNET_FILE} and "
                                f"{VAE_FILE}; download stabilityai/sd-turbo)")
    targets = set(model.lora_layers())
    vae = {}
    for k, v in _load_safetensors(vae_file).items():
        module, _, leaf = k.rpartition(".")
        vae[f"{module}.base_layer.{leaf}" if module in targets else k] = v
    files = {f"base/{UNET_FILE}": sha256_file(unet_file), f"base/{VAE_FILE}": sha256_file(vae_file)}
    return _load_safetensors(unet_file), vae, files


def load_difix_weights(model: DifixRefinerModel, path: Path, *, base: Path | None = None) -> dict[str, Any]:
    """Load an official Difix checkpoint into ``model`` (see the module docstring for the layouts):

    - a diffusers directory (``nvidia/difix_ref`` / ``nvidia/difix``) with ``unet/`` and ``vae/`` safetensors;
    - the training checkpoint ``model_*.pkl`` (``torch.load(weights_only=True)``); its rank and LoRA targets
      must match the model's config. Entries it lacks (the base VAE) come from ``base``, an SD-Turbo diffusers
      directory, as in the official loader.

    Every name and shape is checked against the model first; a mismatch raises ``DifixWeightsError`` naming
    the file, the missing, unexpected and wrong-shape entries and the fix. Tensors are converted to float32.
    Returns ``{"path", "files": {name: sha256}}``."""
    path = Path(path)
    unet_sd, vae_sd, info = _read_checkpoint(path)
    cfg = model.config
    rank = info.get("rank_vae")
    if rank is not None and int(rank) != cfg.lora_rank:
        raise DifixWeightsError(f"{path}: rank_vae is {rank}, the model's lora_rank is {cfg.lora_rank}; build "
                                f"the model with DifixConfig(lora_rank={rank})")
    targets = info.get("vae_lora_target_modules")
    if targets is not None and set(targets) != set(model.lora_layers()):
        ours = set(model.lora_layers())
        extra, lacking = sorted(set(targets) - ours), sorted(ours - set(targets))
        raise DifixWeightsError(f"{path}: vae_lora_target_modules differ from the model's LoRA modules (only in the "
                                f"file: {checkpoints.listing(extra)}; only in the model: "
                                f"{checkpoints.listing(lacking)})")
    files = dict(info["files"])
    if base is not None:
        base_unet, base_vae, base_files = _base_weights(base, model)
        unet_sd = {**base_unet, **unet_sd}
        vae_sd = {**base_vae, **vae_sd}
        files.update(base_files)
    expected = official_key_shapes(model)
    problems = []
    for part, state in (("unet", unet_sd), ("vae", vae_sd)):
        problems += [f"{part}: {p}" for p in checkpoints.layout_problems(state, expected[part])]
    if problems:
        hint = ("; a training checkpoint holds only the LoRA and skip weights of the VAE: pass base=<SD-Turbo "
                "diffusers directory>" if not path.is_dir() and base is None else
                "; check that the checkpoint and DifixConfig describe the same model (sd_turbo() for nvidia/difix*)")
        raise DifixWeightsError(f"{path} does not match the Difix layout of this config: " + "; ".join(problems)
                                + hint)
    model.unet.load_state_dict({k: v.to(torch.float32) for k, v in unet_sd.items()}, strict=True)
    model.vae.load_state_dict({k: v.to(torch.float32) for k, v in vae_sd.items()}, strict=True)
    return {"path": str(path.resolve()), "files": files}

"""``navcrafter models pull``: download the official checkpoints with ``huggingface_hub``, verify, export.

One table (``SOURCES``) says, per role, which official repository holds its weights and exactly which files
of it the role's loader in this repository reads (``patterns``, as ``snapshot_download(allow_patterns=...)``;
``required``: files that must be there). ``pull`` then

1. downloads them into a Hugging Face hub cache (``cache_dir``; the real cache layout
   ``models--org--name/{refs,snapshots/<commit>,blobs}``; resumable, with the library's progress bars), or with
   ``local_files_only=True`` only looks them up there (no network; ``HF_HUB_OFFLINE=1`` does the same);
2. verifies every file: online against the hub's metadata (``HfApi.model_info(files_metadata=True)``: the size of
   every file, the sha256 of LFS files, the git blob sha1 of the others), then writes what it verified (size and
   sha256 of every file, by commit) to ``models--org--name/navcrafter-manifest.json`` in the cache; offline
   against that record (a cache not filled by ``pull`` has none and is refused, naming the fix);
3. runs the role's exporter (``models/zoo/exporters.py``) into ``model_dir/<role dir>``.

Evaluation networks (LPIPS, FID Inception, FVD I3D) are not published on the Hugging Face hub: role ``eval``
downloads them from their official URLs (``huggingface_hub.file_download.http_get``, resumable) into
``cache_dir/navcrafter-urls/`` with the same record, and "exports" them by copying into ``model_dir/eval``
(pass it as ``--eval-weights`` or ``$NAVCRAFTER_EVAL_WEIGHTS``). I3D's official file is on Google Drive only:
it is listed as manual.

How the repository ids were checked (no hub access from where this was written; ``search`` tool over public
pages and code, 2026-12-02):

- ``Wan-AI/Wan2.1-I2V-14B-480P-Diffusers``: the id used in diffusers' own ``WanImageToVideoPipeline`` example
  (``diffusers/pipelines/wan/pipeline_wan_i2v.py`` of the installed diffusers); its folders (transformer/, vae/,
  image_encoder/ with model.safetensors + config.json, text_encoder/ with 5 safetensors shards + index,
  tokenizer/, image_processor/preprocessor_config.json) were seen on the hub pages of the sibling
  ``Wan-AI/Wan2.1-I2V-14B-720P-Diffusers``; the 480P tree itself was not seen.
- ``alibaba-pai/Wan2.1-Fun-V1.1-1.3B-Control-Camera``: listed with its hub link in aigc-apps/VideoX-Fun's
  ``comfyui/wan2_1_fun/README.md`` (19.0 GB). Its file list was not seen; the files fetched are the ones
  ``models/synthesis/funcamera/weights.py`` ``load_fun_camera`` reads (``config.json`` + ``diffusion_pytorch_model*
  .safetensors`` at the root, per VideoX-Fun's ``transformer_subpath: ./``); its export also needs the diffusers
  Wan2.1 I2V encoders, pulled from the repository above without its 14B transformer.
- ``facebook/VGGT-1B``: ``model.safetensors`` + ``config.json`` (PyTorchModelHubMixin) seen in public download
  logs (``HEAD .../facebook/VGGT-1B/resolve/main/model.safetensors``); ``model.pt`` (the same state dict) in
  many public loaders. The safetensors file is taken: our loader reads the official names from either.
- ``Ruicheng/moge-2-vitl-normal``: the MoGe-2 default model id of microsoft/MoGe (its infer script and docs);
  the file ``model.pt`` (``{"model_config", "model"}``) is what MoGe's ``from_pretrained`` downloads. Not seen
  in a hub listing.
- ``nvidia/difix_ref`` (and ``nvidia/difix``): loaded as ``DifixPipeline.from_pretrained("nvidia/difix_ref")``
  in public code (street_crafter, Difix3D forks); its layout (unet/, vae/, text_encoder/, tokenizer/) is the one
  ``models/refiner/difix/weights.py`` documents from nvidia/difix's pinned download manifest.
- Evaluation URLs: the sources the networks' ``WeightFile`` entries name (``models/metrics/evalnets``); the LPIPS
  heads' raw-file URL assumes the repository's default branch is ``master`` (not checked) and the folder layout
  ``lpips/weights/v0.x/`` (seen in the repository index).
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from navcrafter.models.runtime import onnxio
from navcrafter.models.runtime.onnxio import sha256_file

MANIFEST_NAME = "navcrafter-manifest.json"
URL_CACHE = "navcrafter-urls"
EVAL_DIR = "eval"


class HubError(RuntimeError):
    """A pull failed: names the repository/file and the fix."""


@dataclass(frozen=True)
class UrlFile:
    filename: str
    url: str | None  # None: no direct download exists (manual)
    sha256_prefix: str | None = None  # torchvision's file names carry the first 8 hex digits of the sha256
    note: str = ""


@dataclass(frozen=True)
class Source:
    role: str
    repo_id: str | None  # Hugging Face model repository, or None for URL sources
    patterns: tuple[str, ...] | None  # allow_patterns (None: the whole repository)
    required: tuple[str, ...]  # files the loader cannot do without
    target: str | None  # role directory under model_dir (models.zoo.modeldir.ROLE_DIRS), "eval", or None
    summary: str
    urls: tuple[UrlFile, ...] = field(default_factory=tuple)
    needs: tuple[str, ...] = ()  # other sources (keys of SOURCES / HELPERS) pulled with this one, for its export


_WAN_PARTS = ("transformer", "vae", "image_encoder", "text_encoder")
_WAN_ENCODERS = ("vae", "image_encoder", "text_encoder")
WAN_I2V = "Wan-AI/Wan2.1-I2V-14B-480P-Diffusers"

SOURCES: dict[str, Source] = {s.role: s for s in (
    # models/synthesis/onnx_export.py load_components: transformer/, vae/, image_encoder/, text_encoder/ (safetensors
    # only, use_safetensors=True), tokenizer/, optional image_processor/preprocessor_config.json.
    Source("synthesizer", WAN_I2V,
           ("model_index.json", *(f"{p}/*.json" for p in _WAN_PARTS), *(f"{p}/*.safetensors" for p in _WAN_PARTS),
            "tokenizer/*", "image_processor/*"),
           tuple(f"{p}/config.json" for p in _WAN_PARTS) + ("tokenizer/tokenizer_config.json",),
           "synthesizer", "Wan2.1 I2V 14B base (diffusers layout); no camera control: CAMERA CONTROL UNTRAINED"),
    # models/synthesis/funcamera/weights.py load_fun_camera: config.json + diffusion_pytorch_model*.safetensors
    # (single or sharded with its index) at the folder's root; the VAE, CLIP and UMT5 .pth pickles of that
    # repository are not read (safetensors only): onnx_export.load_fun_camera_components takes them from the
    # diffusers Wan2.1 I2V directory instead (HELPERS["wan-i2v-encoders"], without the 14B transformer).
    Source("fun-camera", "alibaba-pai/Wan2.1-Fun-V1.1-1.3B-Control-Camera",
           ("config.json", "diffusion_pytorch_model*.safetensors", "diffusion_pytorch_model.safetensors.index.json"),
           ("config.json",), "synthesizer",
           "Wan2.1-Fun V1.1 1.3B Control-Camera DiT + the Wan2.1 I2V encoders (VAE, CLIP, UMT5)",
           needs=("wan-i2v-encoders",)),
    # models/geometry/vggt/weights.py load_vggt_weights: one official-layout state dict (.safetensors or
    # tensor-only .pt).
    Source("geometry", "facebook/VGGT-1B", ("model.safetensors", "config.json"), ("model.safetensors",),
           "geometry", "VGGT-1B multi-view geometry"),
    # models/geometry/moge/weights.py load_moge2_weights: the official model.pt ({"model_config", "model"},
    # weights_only).
    Source("monodepth", "Ruicheng/moge-2-vitl-normal", ("model.pt",), ("model.pt",), "monodepth",
           "MoGe-2 ViT-L (normal) monocular geometry"),
    # models/refiner/difix/ load_difix_weights + encode_prompt: unet/ and vae/ safetensors, text_encoder/ and
    # tokenizer/ for the fixed prompt "remove degradation".
    Source("refiner", "nvidia/difix_ref",
           ("model_index.json", "unet/config.json", "unet/diffusion_pytorch_model.safetensors", "vae/config.json",
            "vae/diffusion_pytorch_model.safetensors", "text_encoder/*.json", "text_encoder/*.safetensors",
            "tokenizer/*"),
           ("unet/diffusion_pytorch_model.safetensors", "vae/diffusion_pytorch_model.safetensors",
            "text_encoder/config.json", "tokenizer/tokenizer_config.json"),
           "refiner", "Difix (reference-view variant), SD-Turbo based"),
    # models/metrics/evalnets: find_weights looks these file names up in one folder (the URLs are the sources
    # the networks' WeightFile entries name).
    Source("eval", None, None, (), EVAL_DIR, "evaluation networks (LPIPS alex/vgg, FID Inception, FVD I3D)", urls=(
        UrlFile("alexnet-owt-7be5be79.pth", "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
                "7be5be79"),
        UrlFile("vgg16-397923af.pth", "https://download.pytorch.org/models/vgg16-397923af.pth", "397923af"),
        UrlFile("alex.pth", "https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/"
                "weights/v0.1/alex.pth"),
        UrlFile("vgg.pth", "https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/"
                "weights/v0.1/vgg.pth"),
        UrlFile("pt_inception-2015-12-05-6726825d.pth", "https://github.com/mseitzer/pytorch-fid/releases/"
                "download/fid_weights/pt_inception-2015-12-05-6726825d.pth"),
        UrlFile("i3d_pretrained_400.pt", None, note="Google Drive only (VideoGPT's download.py, id "
                "1mQK8KD8G6UWRa5t87SRMm5PVXtlpneJT): download it by hand into the eval folder"),
    )),
)}

# sources pulled only as another role's dependency (Source.needs), never exported on their own
HELPERS: dict[str, Source] = {s.role: s for s in (
    Source("wan-i2v-encoders", WAN_I2V,
           ("model_index.json", *(f"{p}/*.json" for p in _WAN_ENCODERS), *(f"{p}/*.safetensors" for p in _WAN_ENCODERS),
            "tokenizer/*", "image_processor/*"),
           tuple(f"{p}/config.json" for p in _WAN_ENCODERS) + ("tokenizer/tokenizer_config.json",), None,
           "Wan2.1 I2V VAE, CLIP image encoder, UMT5 text encoder and tokenizer (no transformer)"),
)}

# what `models pull` fetches without --role: what `explore --backend onnx` needs (refine.enabled off by default),
# with the one public camera-controlled synthesizer (the Wan base alone ignores the cameras)
DEFAULT_ROLES = ("geometry", "monodepth", "fun-camera")


@dataclass
class PullResult:
    role: str
    source: str  # repo id (@commit) or "urls"
    snapshot: Path | None
    files: int
    bytes: int
    exported: Path | None = None
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------------------
# Cache paths and the verification record
# --------------------------------------------------------------------------------------------------
def repo_folder(cache_dir: Path, repo_id: str) -> Path:
    """``cache_dir/models--org--name`` (huggingface_hub's layout)."""
    return Path(cache_dir) / ("models--" + repo_id.replace("/", "--"))


def _record_path(folder: Path) -> Path:
    return Path(folder) / MANIFEST_NAME


def _read_record(folder: Path) -> dict:
    path = _record_path(folder)
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise HubError(f"{path}: unreadable ({exc}); delete it and rerun `navcrafter models pull` online") from exc
    return data if isinstance(data, dict) else {}


def _write_record(folder: Path, key: str, source: str, files: dict[str, dict]) -> None:
    data = _read_record(folder)
    data.setdefault("source", source)
    data.setdefault("snapshots", {}).setdefault(key, {"files": {}})["files"].update(files)
    folder.mkdir(parents=True, exist_ok=True)
    tmp = _record_path(folder).with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, _record_path(folder))


def record_snapshot(cache_dir: Path, repo_id: str, commit: str, files: dict[str, dict] | None = None) -> dict:
    """Write the verification record of ``repo_id@commit`` (``files``: name → {"size", "sha256"}; computed from
    the snapshot when not given). ``pull`` calls it after verifying a download against the hub."""
    folder = repo_folder(cache_dir, repo_id)
    snap = folder / "snapshots" / commit
    if files is None:
        files = {}
        for p in sorted(snap.rglob("*")):
            if p.is_file():
                files[p.relative_to(snap).as_posix()] = {"size": p.stat().st_size, "sha256": _sha256(p),
                                                         "sha256_from": "computed"}
    _write_record(folder, commit, repo_id, files)
    return files


def _sha256(path: Path) -> str:
    return sha256_file(path)


class _Hasher:
    """sha256 of files, remembered across processes as ``load_manifest`` does (path, size, mtime)."""

    def __init__(self) -> None:
        self._onnxio = onnxio
        self.cache = onnxio._read_checksum_cache()
        self.fresh: dict = {}

    def __call__(self, path: Path) -> str:
        return self._onnxio.cached_sha256(Path(path), self.cache, self.fresh)

    def save(self) -> None:
        if self.fresh:
            self._onnxio._write_checksum_cache(self.fresh)


def _git_blob_sha1(path: Path) -> str:
    h = hashlib.sha1(usedforsecurity=False)
    h.update(b"blob %d\0" % path.stat().st_size)
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            h.update(block)
    return h.hexdigest()


def _matches(name: str, patterns: Sequence[str] | None) -> bool:
    return patterns is None or any(fnmatch.fnmatch(name, p) for p in patterns)


def _bad_file_fix(path: Path) -> str:
    real = Path(os.path.realpath(path))
    return (f"delete {real}" + (f" and {path}" if real != path else "") +
            " and rerun `navcrafter models pull` online to download it again")


# --------------------------------------------------------------------------------------------------
# Hub roles
# --------------------------------------------------------------------------------------------------
def _hub_snapshot(src: Source, cache_dir: Path, *, local_files_only: bool, revision: str | None,
                  hasher: _Hasher) -> tuple[Path, dict[str, dict]]:
    import huggingface_hub as hf
    from huggingface_hub.utils import HfHubHTTPError, LocalEntryNotFoundError

    offline = local_files_only or os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")
    what = f"{src.repo_id}" + (f"@{revision}" if revision else "")
    if offline:
        try:
            snap = Path(hf.snapshot_download(src.repo_id, revision=revision, cache_dir=cache_dir,
                                             local_files_only=True, allow_patterns=list(src.patterns or ["*"])))
        except (LocalEntryNotFoundError, OSError, ValueError) as exc:
            raise HubError(f"{what} is not in the cache {cache_dir} ({type(exc).__name__}: {exc}); run "
                           f"`navcrafter models pull --role {src.role} --cache {cache_dir}` with network access "
                           f"first") from exc
        return snap, _verify_offline(src, cache_dir, snap, hasher)

    try:
        info = hf.HfApi().model_info(src.repo_id, revision=revision, files_metadata=True)
    except (HfHubHTTPError, OSError, ValueError) as exc:
        raise HubError(f"{what}: could not read its file list from the hub ({type(exc).__name__}: {exc}); check "
                       f"the network and, for gated repositories, `hf auth login`; or use --offline with a "
                       f"filled cache") from exc
    siblings = {s.rfilename: s for s in info.siblings or [] if _matches(s.rfilename, src.patterns)}
    missing = [f for f in src.required if f not in siblings]
    if missing:
        raise HubError(f"{src.repo_id}@{info.sha}: the hub lists no {', '.join(missing)}, which the {src.role} "
                       f"loader reads; the repository layout changed: fix SOURCES in models/zoo/hub.py")
    try:
        snap = Path(hf.snapshot_download(src.repo_id, revision=info.sha, cache_dir=cache_dir,
                                         allow_patterns=list(src.patterns) if src.patterns else None))
    except (HfHubHTTPError, OSError, ValueError) as exc:
        raise HubError(f"{src.repo_id}@{info.sha}: download failed ({type(exc).__name__}: {exc}); rerun the same "
                       f"command to resume") from exc
    files: dict[str, dict] = {}
    for name, sib in sorted(siblings.items()):
        path = snap / name
        if not path.is_file():
            raise HubError(f"{src.repo_id}@{info.sha}: {name} is missing from {snap} after the download; rerun "
                           f"`navcrafter models pull --role {src.role}`")
        size = path.stat().st_size
        expected = sib.lfs.size if sib.lfs is not None else sib.size
        if expected is not None and size != expected:
            raise HubError(f"{src.repo_id}@{info.sha}: {name} has {size} bytes, the hub says {expected}; "
                           + _bad_file_fix(path))
        digest = hasher(path)
        if sib.lfs is not None and sib.lfs.sha256 and digest != sib.lfs.sha256:
            raise HubError(f"{src.repo_id}@{info.sha}: {name} sha256 {digest} differs from the hub's "
                           f"{sib.lfs.sha256}; " + _bad_file_fix(path))
        if sib.lfs is None and sib.blob_id and _git_blob_sha1(path) != sib.blob_id:
            raise HubError(f"{src.repo_id}@{info.sha}: {name} does not match the hub's git blob {sib.blob_id}; "
                           + _bad_file_fix(path))
        files[name] = {"size": size, "sha256": digest, "sha256_from": "hub-lfs" if sib.lfs is not None else
                       "computed (git blob sha1 verified)"}
    record_snapshot(cache_dir, src.repo_id, info.sha, files)
    return snap, files


def _verify_offline(src: Source, cache_dir: Path, snap: Path, hasher: _Hasher) -> dict[str, dict]:
    folder = repo_folder(cache_dir, src.repo_id)
    commit = snap.name
    record = _read_record(folder).get("snapshots", {}).get(commit)
    if record is None:
        raise HubError(f"{src.repo_id}@{commit}: no verification record ({_record_path(folder)} lacks this "
                       f"snapshot): the cache was not filled by `navcrafter models pull`; run it once with network "
                       f"access (it verifies the files against the hub and writes the record)")
    files = {k: v for k, v in record.get("files", {}).items() if _matches(k, src.patterns)}
    missing = [f for f in src.required if f not in files or not (snap / f).is_file()]
    missing += [f for f in files if f not in missing and not (snap / f).is_file()]
    if missing:
        raise HubError(f"{src.repo_id}@{commit}: missing from the offline cache {snap}: {', '.join(missing)}; "
                       f"run `navcrafter models pull --role {src.role} --cache {cache_dir}` with network access "
                       f"to download it")
    for name, meta in sorted(files.items()):
        path = snap / name
        size = path.stat().st_size
        if size != meta["size"]:
            raise HubError(f"{src.repo_id}@{commit}: {name} has {size} bytes, {meta['size']} were verified at "
                           f"download; " + _bad_file_fix(path))
        digest = hasher(path)
        if digest != meta["sha256"]:
            raise HubError(f"{src.repo_id}@{commit}: {name} sha256 {digest} differs from the verified "
                           f"{meta['sha256']} ({_record_path(folder)}); " + _bad_file_fix(path))
    return files


# --------------------------------------------------------------------------------------------------
# URL role (evaluation networks)
# --------------------------------------------------------------------------------------------------
def _url_files(src: Source, cache_dir: Path, *, offline: bool, hasher: _Hasher) -> tuple[Path, dict[str, dict],
                                                                                        list[str]]:
    folder = Path(cache_dir) / URL_CACHE / src.role
    folder.mkdir(parents=True, exist_ok=True)
    record = _read_record(folder).get("snapshots", {}).get("urls", {}).get("files", {})
    files: dict[str, dict] = {}
    notes = []
    for uf in src.urls:
        path = folder / uf.filename
        if uf.url is None:
            notes.append(f"{uf.filename}: not downloaded ({uf.note})")
            continue
        if not path.is_file():
            if offline:
                raise HubError(f"{uf.filename} ({uf.url}) is missing from the offline cache {folder}; run "
                               f"`navcrafter models pull --role {src.role} --cache {cache_dir}` with network access")
            _http_download(uf, path)
        size = path.stat().st_size
        digest = hasher(path)
        if uf.sha256_prefix and not digest.startswith(uf.sha256_prefix):
            raise HubError(f"{uf.filename}: sha256 {digest} does not start with {uf.sha256_prefix} (the hash in "
                           f"its official name); " + _bad_file_fix(path))
        known = record.get(uf.filename)
        if known is not None and (known["size"] != size or known["sha256"] != digest):
            raise HubError(f"{uf.filename}: differs from the copy verified at download (size {known['size']}, "
                           f"sha256 {known['sha256']}); " + _bad_file_fix(path))
        if known is None and offline:
            raise HubError(f"{uf.filename}: no verification record in {_record_path(folder)}; rerun `navcrafter "
                           f"models pull --role {src.role}` with network access")
        files[uf.filename] = {"size": size, "sha256": digest, "url": uf.url}
    if not offline:
        _write_record(folder, "urls", "urls", {**record, **files})
    return folder, files, notes


def _http_download(uf: UrlFile, path: Path) -> None:
    from huggingface_hub.file_download import http_get

    part = path.with_name(path.name + ".incomplete")
    try:
        with open(part, "ab") as f:
            http_get(uf.url, f, resume_size=f.tell(), displayed_filename=uf.filename)
    except Exception as exc:  # network errors of the HTTP client; the partial file stays for resuming
        raise HubError(f"{uf.filename}: download from {uf.url} failed ({type(exc).__name__}: {exc}); rerun the same "
                       f"command to resume") from exc
    os.replace(part, path)


# --------------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------------
def _export_monodepth(out: Path, snap: Path) -> Path:
    """MoGe-2 exported at the config its checkpoint declares (``model_config``), else ViT-L (normal)."""
    # deferred: torch loads with MoGe only when its checkpoint is read and exported
    from navcrafter.models.geometry.moge import MoGe2Config, _read_checkpoint
    from navcrafter.models.geometry.moge import export_monodepth as _export

    ckpt = snap / "model.pt"
    _state, file_config = _read_checkpoint(ckpt)
    del _state
    config = MoGe2Config.from_official(file_config) if file_config is not None else MoGe2Config.vitl_normal()
    return _export(out, config, weights=ckpt)


def _export_fun_camera(out: Path, snap: Path, base: Path, sizes: dict[str, int]) -> Path:
    """``exporters.export_fun_camera`` when it exists (its parameters matched by name), else
    ``onnx_export.export_fun_camera_synthesizer(out, checkpoint_dir=, base_dir=, num_frames=, height=, width=)``."""
    import inspect

    # deferred: torch loads with the exporters only when a downloaded checkpoint is exported
    from navcrafter.models.zoo import exporters

    fn = getattr(exporters, "export_fun_camera", None)
    if fn is None:
        # deferred: torch loads with the exporters only when a downloaded checkpoint is exported
        from navcrafter.models.synthesis.onnx_export import export_fun_camera_synthesizer as fn
    params = inspect.signature(fn).parameters
    values = {"checkpoint_dir": snap, "checkpoint": snap, "base_dir": base, "base": base, **sizes}
    kwargs: dict[str, Any] = {k: v for k, v in values.items() if k in params}
    if not ({"checkpoint_dir", "checkpoint"} & set(kwargs) and {"base_dir", "base"} & set(kwargs)):
        raise HubError(f"{fn.__module__}.{fn.__name__}{inspect.signature(fn)}: no parameters for the checkpoint and "
                       f"base directories; export {snap} (with base {base}) by its own command")
    return Path(fn(out, **kwargs))


def _export(src: Source, snap: Path, model_dir: Path, sizes: dict[str, int], needed: dict[str, Path]) -> Path:
    # deferred: torch loads with the exporters and modeldir only when a downloaded checkpoint is exported
    from navcrafter.models.zoo import exporters
    from navcrafter.models.zoo.modeldir import role_dir

    if src.role == "eval":
        out = Path(model_dir) / EVAL_DIR
        out.mkdir(parents=True, exist_ok=True)
        for f in snap.iterdir():
            if f.is_file() and f.name != MANIFEST_NAME and not f.name.endswith((".incomplete", ".tmp")):
                shutil.copy2(f, out / f.name)
        return out
    out = role_dir(model_dir, src.target)
    try:
        if src.role == "geometry":
            return exporters.export_geometry(out, checkpoint=snap / "model.safetensors")
        if src.role == "monodepth":
            return _export_monodepth(out, snap)
        if src.role == "refiner":
            return exporters.export_refiner(out, checkpoint=snap, reference=True)
        if src.role == "synthesizer":
            return exporters.export_synthesizer(out, base_dir=snap, **sizes)
        if src.role == "fun-camera":
            return _export_fun_camera(out, snap, needed["wan-i2v-encoders"], sizes)
    except HubError:
        raise
    except (ValueError, FileNotFoundError, NotImplementedError, RuntimeError) as exc:
        raise HubError(f"role {src.role}: export of {snap} into {out} failed: {exc}") from exc
    raise HubError(f"role {src.role}: no exporter")


# --------------------------------------------------------------------------------------------------
# pull
# --------------------------------------------------------------------------------------------------
def default_cache_dir() -> Path:
    from huggingface_hub import constants

    return Path(constants.HF_HUB_CACHE)


def pull(roles: Sequence[str] | None, cache_dir: Path | None, model_dir: Path | None, *,
         local_files_only: bool = False, export: bool = True, revision: str | None = None,
         num_frames: int = 81, height: int = 256, width: int = 256,
         log: Callable[[str], None] | None = None) -> list[PullResult]:
    """Download (or, ``local_files_only``, look up), verify and export the official checkpoints of ``roles``
    (default ``DEFAULT_ROLES``) into ``model_dir``. ``cache_dir``: a hub cache (default huggingface_hub's).
    ``revision``: a branch, tag or commit of every repository pulled (default ``main``). ``num_frames``,
    ``height``, ``width``: the clip size the synthesizer is exported for (the runs' ``synthesis.*``).
    Raises ``HubError`` naming the repository/file and the fix."""
    roles = list(roles or DEFAULT_ROLES)
    unknown = [r for r in roles if r not in SOURCES]
    if unknown:
        raise HubError(f"unknown role(s) {', '.join(unknown)}; known: {', '.join(SOURCES)}")
    if export and model_dir is None:
        raise HubError("give the model directory to export into (--out MODEL_DIR), or --no-export")
    if export and {"synthesizer", "fun-camera"} <= set(roles):
        raise HubError("roles synthesizer and fun-camera both export MODEL_DIR/synthesizer: pull one of them (or "
                       "use --no-export)")
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    say = log or (lambda _msg: None)
    hasher = _Hasher()
    results = []
    sizes = {"num_frames": num_frames, "height": height, "width": width}
    offline = local_files_only or os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")

    def fetch(src: Source) -> PullResult:
        if src.repo_id is None:
            snap, files, notes = _url_files(src, cache_dir, offline=offline, hasher=hasher)
            result = PullResult(src.role, "urls", snap, len(files), sum(f["size"] for f in files.values()),
                                notes=notes)
        else:
            snap, files = _hub_snapshot(src, cache_dir, local_files_only=offline, revision=revision, hasher=hasher)
            result = PullResult(src.role, f"{src.repo_id}@{snap.name}", snap, len(files),
                                sum(f["size"] for f in files.values()))
        say(f"{src.role}: {result.source}: {result.files} files, {result.bytes / 2**30:.2f} GiB verified in {snap}")
        return result

    try:
        for role in roles:
            src = SOURCES[role]
            needed = {}
            for key in src.needs:
                dep = fetch(HELPERS[key])
                needed[key] = dep.snapshot
                results.append(dep)
            result = fetch(src)
            if export:
                say(f"{role}: exporting into {model_dir} ...")
                result.exported = _export(src, result.snapshot, Path(model_dir), sizes, needed)
                if role == "fun-camera":
                    result.notes.append("runs use this synthesizer with --set synthesis.model=fun-camera")
            results.append(result)
    finally:
        hasher.save()
    return results

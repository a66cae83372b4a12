"""Ingest: validate and normalise one input photo into a new scene.

Accepted: anything Pillow decodes (PNG, JPEG, WebP, TIFF, BMP, GIF, ...). Normalisation: EXIF
orientation applied; greyscale, palette, CMYK, 16-bit and float images converted to RGB8; alpha
composited onto ``ingest.alpha_background``; multi-frame files use their first frame; the stored input
is downscaled to ``ingest.max_side``; the working image is its centre crop to the synthesis aspect,
resized to the synthesis resolution.

Rejected with an ``IngestError`` naming the file and the fix: missing, empty, too large (bytes or
pixels), not an image, corrupt or truncated, too small.
"""

from __future__ import annotations

import hashlib
import io
import json
import posixpath
import warnings
from dataclasses import dataclass
from pathlib import Path

import fsspec
import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.simulation import GROUNDTRUTH_DIR
from navcrafter.schemas.config import IngestConfig, RunConfig
from navcrafter.schemas.layout import INGEST
from navcrafter.schemas.store import storage_options_for
from navcrafter.tasks import steps
from navcrafter.tasks.common import StepRef
from navcrafter.tasks.steps import StepContext


class IngestError(ValueError):
    """An input file cannot be used; the message says which and what to do."""


class CollectionError(ValueError):
    """A collection URL cannot be listed (no such bucket or prefix, no credentials, ...); the message
    names the URL and the fix."""


@dataclass(frozen=True)
class IngestResult:
    source: str
    scene_id: str | None
    ok: bool
    error: str | None = None
    step: StepRef | None = None


@dataclass
class LoadedImage:
    image: np.ndarray  # [H0, W0, 3] uint8, normalised
    original_size: tuple[int, int]  # (width, height) as stored in the file
    original_mode: str
    exif_orientation: int


# --------------------------------------------------------------------------------------------------
# Collections
# --------------------------------------------------------------------------------------------------
def is_url(location: str | Path) -> bool:
    return "://" in str(location)


def source_fs(url: str):
    """``(filesystem, path)`` of an fsspec URL, with the store's endpoint and credential handling
    (``schemas.store.storage_options_for``: ``AWS_ENDPOINT_URL`` etc. for ``s3://``)."""
    return fsspec.core.url_to_fs(url, **storage_options_for(url))


def access_problem(url: str, exc: BaseException) -> str | None:
    """What to tell the user when reading ``url`` failed for lack of access, else ``None``."""
    if type(exc).__name__ in ("NoCredentialsError", "PartialCredentialsError"):  # botocore's
        return (f"{url}: no credentials for the object store ({exc}); set AWS_ACCESS_KEY_ID and "
                f"AWS_SECRET_ACCESS_KEY (or AWS_PROFILE), and AWS_ENDPOINT_URL for MinIO/Ceph/other S3 servers")
    if isinstance(exc, PermissionError):
        return (f"{url}: access denied ({exc}); check that the credentials (AWS_ACCESS_KEY_ID, AWS_PROFILE, ...) "
                f"may read it and that AWS_ENDPOINT_URL points at the right server")
    if isinstance(exc, FileNotFoundError) and "bucket" in str(exc).lower():
        return f"{url}: the bucket does not exist ({exc}); check the bucket name in the URL (or create the bucket)"
    return None


def _list_url(url: str) -> list[str]:
    """Every visible object under a URL prefix (sorted, as URLs), or the single object named."""
    try:
        fs, root = source_fs(url)
        if fs.isfile(root):
            return [url]
        found = fs.find(root)
    except (ImportError, ValueError) as exc:  # no fsspec implementation for the protocol (e.g. gcsfs)
        raise CollectionError(f"{url}: cannot open this URL ({exc}); install the fsspec package of its "
                              f"protocol or fix the URL") from exc
    except Exception as exc:
        problem = access_problem(url, exc)
        if problem is None and isinstance(exc, FileNotFoundError):
            problem = f"{url} does not exist ({exc}); check the URL"
        if problem is None:
            raise
        raise CollectionError(problem) from exc
    root = root.rstrip("/")
    keys = [k for k in sorted(found) if not k.endswith("/") and k.startswith(f"{root}/")]
    if not keys:
        raise CollectionError(f"no objects under {url}: check the prefix (and the endpoint, AWS_ENDPOINT_URL), "
                              f"or upload the images there first")
    visible = [k for k in keys if not any(part.startswith(".") for part in k[len(root) + 1:].split("/"))]
    return [fs.unstrip_protocol(k) for k in visible]


def list_collection(photos: str | Path) -> list[str]:
    """Every visible file under a folder (recursively, sorted), or the single file given; for an fsspec
    URL (``s3://bucket/photos/``, ...) every visible object under that prefix, as URLs.

    Non-image files are listed too: ingest records them as failed instead of silently skipping them.
    Hidden files and folders (names starting with '.') are skipped; that is where demo ground truth
    lives.
    """
    if is_url(photos):
        return _list_url(str(photos))
    p = Path(photos).expanduser()
    if not p.exists():
        raise FileNotFoundError(f"photo collection {p} does not exist; pass a folder of images "
                                f"(or make a demo one with `navcrafter demo-data {p}`)")
    if p.is_file():
        return [str(p.resolve())]
    files = [f for f in sorted(p.rglob("*"))
             if f.is_file() and not any(part.startswith(".") for part in f.relative_to(p).parts)]
    return [str(f.resolve()) for f in files]


# --------------------------------------------------------------------------------------------------
# Decoding and normalisation
# --------------------------------------------------------------------------------------------------
def read_source(source: str, cfg: IngestConfig) -> bytes:
    try:
        return _read_source(source, cfg)
    except IngestError:
        raise
    except Exception as exc:  # no credentials, access denied, no bucket: the fix is the user's
        problem = access_problem(source, exc)
        if problem is None:
            raise
        raise IngestError(problem) from exc


def _read_source(source: str, cfg: IngestConfig) -> bytes:
    fs, path = source_fs(source)
    if not fs.exists(path):
        raise IngestError(f"{source}: file not found; check the path")
    size = fs.size(path)
    if size == 0:
        raise IngestError(f"{source}: the file is empty (0 bytes); remove it or replace it with the image")
    if size > cfg.max_file_bytes:
        raise IngestError(f"{source}: the file is {size / 2**20:.1f} MiB, above the "
                          f"{cfg.max_file_bytes / 2**20:.0f} MiB limit; downscale or recompress it, or "
                          f"raise ingest.max_file_bytes")
    return fs.cat_file(path)


_MAGIC = {b"\xff\xd8\xff": "JPEG", b"\x89PNG": "PNG", b"GIF8": "GIF", b"BM": "BMP",
          b"II*\x00": "TIFF", b"MM\x00*": "TIFF"}


def _image_format(data: bytes) -> str | None:
    """The image format named by the file's magic bytes, if any."""
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP"
    return next((fmt for magic, fmt in _MAGIC.items() if data.startswith(magic)), None)


def _describe(data: bytes) -> str:
    head = data[:64]
    if head.startswith(b"%PDF"):
        return "a PDF document"
    if head[:2] == b"PK":
        return "a ZIP archive"
    try:
        head.decode("utf-8")
        return "text"
    except UnicodeDecodeError:
        return "binary data of an unknown format"


def decode_image(data: bytes, source: str, cfg: IngestConfig) -> LoadedImage:
    """Bytes of an image file to a normalised RGB8 array (see module docstring)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data))
            w, h = im.size
            if w * h > cfg.max_pixels:
                raise IngestError(f"{source}: {w}x{h} = {w * h / 1e6:.0f} megapixels, above the "
                                  f"{cfg.max_pixels / 1e6:.0f} MP limit; downscale it or raise ingest.max_pixels")
            im.seek(0)
            im.load()
    except IngestError:
        raise
    except Image.DecompressionBombError as exc:
        raise IngestError(f"{source}: the image is absurdly large ({exc}); downscale it") from exc
    except UnidentifiedImageError as exc:
        fmt = _image_format(data)
        if fmt is not None:
            raise IngestError(f"{source}: the {fmt} image is corrupt or truncated (it cannot be decoded); "
                              f"re-export or re-download it") from exc
        raise IngestError(f"{source}: not an image file (it looks like {_describe(data)}); remove it "
                          f"from the collection or convert it to PNG/JPEG") from exc
    except (OSError, SyntaxError, ValueError) as exc:
        raise IngestError(f"{source}: the image is corrupt or truncated ({exc}); re-export or "
                          f"re-download it") from exc
    mode = im.mode
    orientation = int(im.getexif().get(0x0112, 1) or 1)
    im = ImageOps.exif_transpose(im)
    arr = _to_rgb8(im, cfg.alpha_background)
    H, W = arr.shape[:2]
    if min(H, W) < cfg.min_side:
        raise IngestError(f"{source}: {W}x{H} pixels is too small (shorter side below {cfg.min_side}); "
                          f"use a larger image")
    if max(H, W) > cfg.max_side:
        s = cfg.max_side / max(H, W)
        size = (max(1, round(W * s)), max(1, round(H * s)))
        arr = np.asarray(Image.fromarray(arr).resize(size, Image.Resampling.LANCZOS))
    return LoadedImage(np.ascontiguousarray(arr), (w, h), mode, orientation)


def _to_rgb8(im: Image.Image, background: tuple[int, int, int]) -> np.ndarray:
    if im.mode in ("I", "I;16", "I;16L", "I;16B", "I;16N", "F"):
        a = np.asarray(im).astype(np.float64)
        if im.mode == "F":
            lo, hi = float(np.nanmin(a)), float(np.nanmax(a))
            a = (a - lo) / (hi - lo) * 255 if hi > lo else np.zeros_like(a)
        elif a.max() > 255:
            a = a / 257.0  # 16-bit range to 8-bit
        g = np.clip(np.rint(np.nan_to_num(a)), 0, 255).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)
    has_alpha = im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or (
        im.mode == "P" and "transparency" in im.info)
    if has_alpha:
        rgba = im.convert("RGBA")
        bg = Image.new("RGBA", rgba.size, (*background, 255))
        return np.asarray(Image.alpha_composite(bg, rgba).convert("RGB"))
    return np.asarray(im.convert("RGB"))


def make_work_image(image: np.ndarray, height: int, width: int) -> tuple[np.ndarray, tuple[float, float, int, int]]:
    """Centre crop to the working aspect, then resize. Returns the image and the crop box
    ``(x0, y0, w, h)`` in the normalised image's pixels."""
    H0, W0 = image.shape[:2]
    aspect = width / height
    if W0 / H0 > aspect:
        cw, ch = round(H0 * aspect), H0
    else:
        cw, ch = W0, round(W0 / aspect)
    x0, y0 = (W0 - cw) // 2, (H0 - ch) // 2
    crop = Image.fromarray(image).crop((x0, y0, x0 + cw, y0 + ch))
    work = np.asarray(crop.resize((width, height), Image.Resampling.LANCZOS))
    return np.ascontiguousarray(work), (float(x0), float(y0), int(cw), int(ch))


# --------------------------------------------------------------------------------------------------
# Simulation ground truth of demo images
# --------------------------------------------------------------------------------------------------
def groundtruth_record(source: str, sha256: str) -> dict | None:
    """The ground-truth record beside a demo photo (``<dir>/.groundtruth/<stem>/scene.json``, also
    beside an object of an object store) if it exists and was written for exactly these image bytes;
    ``None`` otherwise."""
    if is_url(source):
        fs, path = source_fs(source)
        parent, name = posixpath.split(path)
        sidecar = f"{parent}/{GROUNDTRUTH_DIR}/{posixpath.splitext(name)[0]}/scene.json"
        try:
            text = fs.cat_file(sidecar).decode()
        except FileNotFoundError:
            return None
        folder = fs.unstrip_protocol(posixpath.dirname(sidecar))
    else:
        p = Path(source)
        local = p.parent / GROUNDTRUTH_DIR / p.stem / "scene.json"
        if not local.is_file():
            return None
        text, folder = local.read_text(), str(local.parent)
    record = json.loads(text)
    if record.get("photo", {}).get("sha256") != sha256:
        return None  # the photo was changed since the ground truth was written
    record["groundtruth"] = folder
    return record


def find_simulation_truth(source: str, sha256: str, loaded: LoadedImage,
                          crop_box: tuple[float, float, int, int], work_size: tuple[int, int]) -> dict | None:
    """The simulation truth of a demo photo, with the true intrinsics of the working image."""
    record = groundtruth_record(source, sha256)
    if record is None:
        return None
    photo = record["photo"]
    if loaded.exif_orientation != 1:
        raise IngestError(f"{source}: a demo photo with an EXIF rotation has no valid ground truth")
    K = Intrinsics.from_dict(photo["intrinsics"])
    H0, W0 = loaded.image.shape[:2]
    K = K.resize(W0, H0).crop(crop_box[0], crop_box[1], crop_box[2], crop_box[3])
    K = K.resize(work_size[0], work_size[1])
    return {"scene": record["scene"], "photo_c2w": photo["c2w"], "work_intrinsics": K.to_dict(),
            "groundtruth": record["groundtruth"]}


# --------------------------------------------------------------------------------------------------
# The tasks
# --------------------------------------------------------------------------------------------------
def ingest_body(ctx: StepContext) -> dict:
    """The ingest step's body: writes the decoded photo and its working image. ``ctx.prepared`` (made by
    ``ingest`` before anything is written): the file's source and sha256, the decoded image, the working image,
    its crop box and the demo ground truth."""
    source, sha, loaded, work, crop, truth = ctx.prepared
    ctx.write_all(image=loaded.image, work_image=work)
    attrs = {"source": source, "sha256": sha, "original_size": list(loaded.original_size),
             "original_mode": loaded.original_mode, "exif_orientation": loaded.exif_orientation,
             "crop_box": list(crop), "normalised_size": [loaded.image.shape[1], loaded.image.shape[0]],
             "work_size": [work.shape[1], work.shape[0]]}
    if truth is not None:
        attrs["simulation_truth"] = truth
    return attrs


def identify(source: str, config: RunConfig) -> IngestResult:
    """Read and hash one file, writing nothing: its scene id, or why it cannot be used.

    Hashing first lets a collection ingest each distinct image once, however many files hold it.
    """
    try:
        data = read_source(source, config.ingest)
    except IngestError as exc:
        return IngestResult(source, None, False, str(exc))
    return IngestResult(source, hashlib.sha256(data).hexdigest(), True)


def primary_source(sources: list[str], scene_id: str) -> str:
    """Of several files with the same bytes, the one to ingest: one with ground truth, if any."""
    return next((s for s in sources if groundtruth_record(s, scene_id) is not None), sources[0])


def ingest(store_uri: str, source: str, config: RunConfig, run_id: str) -> IngestResult:
    """Validate ``source`` and write the scene's ``input`` group. Never raises for a bad image:
    the failure is returned (and recorded in the manifest by the flow)."""
    cfg = config.ingest
    try:
        data = read_source(source, cfg)
    except IngestError as exc:
        return IngestResult(source, None, False, str(exc))
    sha = hashlib.sha256(data).hexdigest()
    H, W = config.synthesis.height, config.synthesis.width

    def prepare() -> tuple[str, str, LoadedImage, np.ndarray, tuple, dict | None]:
        loaded = decode_image(data, source, cfg)
        work, crop = make_work_image(loaded.image, H, W)
        truth = find_simulation_truth(source, sha, loaded, crop, (W, H))
        return source, sha, loaded, work, crop, truth

    try:
        ref = steps.execute(store_uri, sha, INGEST, None, config, run_id, ingest_body, prepare=prepare)
    except Exception as exc:
        cause = getattr(exc, "cause", exc)
        if isinstance(cause, IngestError):
            return IngestResult(source, sha, False, str(cause))
        raise
    return IngestResult(source, sha, True, None, ref)

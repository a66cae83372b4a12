"""The clip store of camera-control training: which clips (``plan_clips``), their precompute
(``init_clip_store``, ``precompute_clip``) and reading them back (``ClipDataset``). Plain functions; the
``train-camera`` flow maps ``precompute_clip`` over the planned clips.

Plan. Every ``config.data.sources`` dataset is read with ``schemas.datasets.open_dataset`` (RealEstate10K with
``split=source.split``; DL3DV from ``root/split`` when a split is given) with the reader's protocol:
clips of ``T = data.num_frames`` frames (the reader's ``num_frames = T - 1``) every ``data.frame_stride``
frames, frames resized/centre-cropped to ``data.resolution`` squared, ``data.clips_per_source`` clips drawn
from ``config.seed`` (``None``: one per sequence). Sequences are ordered by source (config order), then by
name (natural order); the **last sequences are held out for validation**: walking back from the last one,
each sequence's clips go to ``"validation"`` until ``data.validation_clips`` are held out. No sequence is in
both splits: clips of the sequence that completes the quota beyond it are left out of the plan. The rest is
``"train"``. A clip's id, its Zarr group name, is ``<source index>-<kind>-<sequence>-<start>`` (start zero
padded to 6 digits; characters other than ``A-Za-z0-9._-`` in the sequence become ``_``, and then the name's
crc32 is appended so that ids stay distinct).

Store (``RUN/clips.zarr``, Zarr v3; arrays and attrs in ``schemas/training.py``). The root holds
``format``/``version`` (``CLIP_STORE_FORMAT``/``CLIP_STORE_VERSION``), ``encoders`` (the ``ClipEncoders.name``
it was made with; a store made with other encoders is refused) and ``null_text_embeds`` (float32
``[512, text_dim]``, the empty prompt's text embeddings, for text dropout), written once by
``init_clip_store`` (the flow calls it before precomputing clips in parallel; ``precompute_clip`` calls it
when the store is not initialised). One group per clip ``clips/<clip_id>``, written by one task:

* ``latents`` = ``encode_video`` of the clip's frames (``[-1, 1]``, ``pipeline._to_video``); ``image_latents``
  = ``encode_video`` of the I2V condition video exactly as the sampler builds it (frame 0, then zeros in
  [-1, 1] space, i.e. mid-grey: ``pipeline.prepare_conditions``); ``image_embeds`` = ``image_features`` of
  frame 0; ``text_embeds`` = ``text_embeddings(data.prompt)``; ``c2w`` = the reader's cameras relative to
  frame 0 (``Sample.relative_c2w``, OpenCV, dataset units); ``K`` = the reader's pixel intrinsics.
* ``data.render_condition``: frame 0's depth ``<frame 0 stem>.depth.npy`` beside its image (the simulation
  engine's extension, ``models/simulation/datasets.py``; z-depth in dataset units, 0 = none, of the image's
  native size) is cropped and resized exactly like the image (the reader's ``resize_center_crop`` box) by
  nearest-neighbour sampling (output pixel centre ``(j + 1/2, i + 1/2)`` reads source pixel
  ``floor(x0 + (j + 1/2) / s), floor(y0 + (i + 1/2) / s)``; depths are never blended across edges), lifted
  with ``K[0]`` to frame 0's camera frame (``unproject_depth``), coloured with frame 0's pixels, and rendered
  along the clip with ``render_points`` (point size ``onnx_synthesizer.default_point_size``, as at
  inference): ``render_latents`` = ``encode_video`` of the renders (black where empty), ``visibility`` = their
  masks. A missing depth file raises ``FileNotFoundError`` naming it (real datasets have no depth and no
  geometry model is run here: set ``data.render_condition=false`` for them).
* ``data.extra_reference`` and a clip that does not start at the sequence's frame 0: a frame ``k`` frames
  before the clip start, ``k`` drawn in ``1 .. min(2T, start)`` from ``default_rng([seed, crc32(clip_id)])``,
  resized like the clip: ``reference_latents`` (``encode_video`` of that single frame) and ``reference_c2w``
  (its camera relative to the clip's frame 0). Otherwise neither array is written.
* attrs: ``CLIP_ATTRS`` (``source`` is the dataset kind; ``num_frames`` is ``T``), plus ``clip_id``,
  ``source_index``, ``source_root``, ``frame_indices``, ``reference_index`` (or ``None``), ``encoders``,
  ``prompt``, ``render_condition``, ``point_size``.

Resume: arrays are computed first, then the group is created with ``done = false``, the arrays written, and
``done = true`` set last in one write of the group's ``zarr.json``. A ``done`` group is skipped (after checking
that it was made for the same clip and settings: otherwise ``ClipStoreError``, since a store must not mix two
configurations); any other group is deleted and rewritten.
"""

from __future__ import annotations

import logging
import os
import re
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from navcrafter.models.camera.cameras import unproject_depth
from navcrafter.models.synthesis.onnx_synthesizer import default_point_size
from navcrafter.models.synthesis.pipeline import _to_video
from navcrafter.schemas.datasets import DatasetError, open_dataset
from navcrafter.schemas.training import (
    CLIP_ARRAYS,
    CLIP_REQUIRED,
    CLIP_STORE_FORMAT,
    CLIP_STORE_VERSION,
    CameraTrainingConfig,
    DataSource,
)

if TYPE_CHECKING:
    from navcrafter.models.synthesis.encoders import ClipEncoders

log = logging.getLogger(__name__)

CLIPS_GROUP = "clips"
NULL_TEXT = "null_text_embeds"
SPLITS = ("train", "validation")
# attrs a complete group must agree on with the clip asked for (else the store mixes two configurations)
_IDENTITY_ATTRS = ("source", "sequence", "start", "stride", "split", "height", "width", "num_frames", "encoders",
                   "prompt", "render_condition", "extra_reference")


class ClipStoreError(ValueError):
    """The clip store does not fit the request (the message names the store or group and the fix)."""


@dataclass(frozen=True)
class ClipRef:
    """One planned clip: where it is read from and where it is stored (plain values: picklable, JSON-able)."""

    clip_id: str            # the Zarr group name under clips/
    source_index: int       # index into config.data.sources
    kind: str               # "re10k" | "dl3dv"
    root: str               # the dataset folder
    dataset_split: str | None  # DataSource.split (RealEstate10K split folder)
    sequence: str
    start: int              # sequence index of frame 0
    stride: int
    num_frames: int         # T, frame 0 included
    resolution: int         # square frame size
    split: str              # "train" | "validation"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# --------------------------------------------------------------------------------------------------
# Plan
# --------------------------------------------------------------------------------------------------
def _natural_key(s: str) -> list:
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", s)]


def clip_id(source_index: int, kind: str, sequence: str, start: int) -> str:
    """The stable group name of a clip (see the module docstring)."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", sequence)
    if safe != sequence:
        safe = f"{safe}-{zlib.crc32(sequence.encode()):08x}"
    return f"{int(source_index)}-{kind}-{safe}-{int(start):06d}"


def _open_reader(kind: str, root: str, dataset_split: str | None, *, num_frames: int, stride: int,
                 resolution: int, seed: int, clips: int | None = None):
    options: dict[str, Any] = {"num_frames": num_frames, "stride": stride, "resolution": resolution, "seed": seed,
                               "clips_per_dataset": clips}
    if kind == "re10k":
        options["split"] = dataset_split
    elif dataset_split is not None:
        root = str(Path(root) / dataset_split)
    return open_dataset(kind, root, **options)


def _source_reader(src: DataSource, config: CameraTrainingConfig):
    d = config.data
    return _open_reader(src.kind, src.root, src.split, num_frames=d.num_frames - 1, stride=d.frame_stride,
                        resolution=d.resolution, seed=config.seed, clips=d.clips_per_source)


def plan_clips(config: CameraTrainingConfig) -> list[ClipRef]:
    """The clips of a run, in the readers' draw order (source by source), with their split assigned."""
    d = config.data
    if not d.sources:
        raise ValueError("data.sources is empty: add at least one dataset (kind 're10k' or 'dl3dv', root folder)")
    drawn: list[tuple[int, int, DataSource, str, int]] = []  # (source, sequence rank, source, sequence, start)
    for si, src in enumerate(d.sources):
        reader = _source_reader(src, config)
        pairs = reader.plan()
        for name, why in reader.skipped.items():
            log.warning("%s source %d (%s): sequence %s left out: %s", src.kind, si, src.root, name, why)
        if not pairs:
            reasons = "; ".join(f"{k}: {v}" for k, v in reader.skipped.items()) or "no sequences"
            raise DatasetError(f"data.sources[{si}] ({src.kind} {src.root}) gives no clip of {d.num_frames} frames "
                               f"(stride {d.frame_stride}): {reasons}")
        rank = {name: i for i, name in enumerate(sorted({n for n, _ in pairs}, key=_natural_key))}
        drawn += [(si, rank[name], src, name, start) for name, start in pairs]

    sequences = sorted({(si, r) for si, r, *_ in drawn})
    held: set[tuple[int, str, int]] = set()
    dropped: set[tuple[int, str, int]] = set()
    for si, r in reversed(sequences):
        if len(held) >= d.validation_clips:
            break
        mine = [(si, name, start) for s2, r2, _, name, start in drawn if (s2, r2) == (si, r)]
        room = d.validation_clips - len(held)
        held.update(mine[:room])
        dropped.update(mine[room:])
    refs = []
    for si, _, src, name, start in drawn:
        key = (si, name, start)
        if key in dropped:
            continue
        refs.append(ClipRef(clip_id=clip_id(si, src.kind, name, start), source_index=si, kind=src.kind,
                            root=str(src.root), dataset_split=src.split, sequence=name, start=int(start),
                            stride=d.frame_stride, num_frames=d.num_frames, resolution=d.resolution,
                            split="validation" if key in held else "train"))
    if not any(r.split == "train" for r in refs):
        raise ValueError(f"data.validation_clips={d.validation_clips} holds out every clip ({len(drawn)} clips from "
                         f"{len(sequences)} sequences): lower validation_clips or add sequences / clips_per_source")
    if dropped:
        log.info("left out %d clips of the last validation sequence (no sequence is in both splits)", len(dropped))
    return refs


# --------------------------------------------------------------------------------------------------
# Store
# --------------------------------------------------------------------------------------------------
def _zstore(store_path: str | os.PathLike):
    import zarr

    uri = str(store_path)
    if "://" in uri and not uri.startswith("file://"):
        return zarr.storage.FsspecStore.from_url(uri)
    return zarr.storage.LocalStore(uri.removeprefix("file://"))


def _open_root(store_path: str | os.PathLike, mode: str):
    import zarr

    return zarr.open_group(store=_zstore(store_path), mode=mode, zarr_format=3)


def _check_root(root, store_path, encoders_name: str | None) -> None:
    a = root.attrs.asdict()
    if a.get("format") != CLIP_STORE_FORMAT or a.get("version") != CLIP_STORE_VERSION:
        raise ClipStoreError(f"{store_path} is not a navcrafter clip store of version {CLIP_STORE_VERSION} (format "
                             f"{a.get('format')!r}, version {a.get('version')!r}); use a new run folder")
    if encoders_name is not None and a.get("encoders") != encoders_name:
        raise ClipStoreError(f"{store_path} was precomputed with encoders {a.get('encoders')!r}, not "
                             f"{encoders_name!r}; use a new run folder (a store must not mix encoders)")


def init_clip_store(store_path: str | os.PathLike, encoders: ClipEncoders, config: CameraTrainingConfig) -> str:
    """Create the store's root (format, version, encoders) and ``null_text_embeds``; idempotent.

    The null prompt's embeddings are needed for ``config.text_dropout > 0``; encoders that cannot embed the
    empty prompt raise then (and the array is left out when dropout is off)."""
    import zarr

    try:
        root = _open_root(store_path, "r+")
    except (FileNotFoundError, zarr.errors.GroupNotFoundError):
        root = None
    if root is None or "format" not in root.attrs:
        root = _open_root(store_path, "a")
        root.update_attributes({"format": CLIP_STORE_FORMAT, "version": CLIP_STORE_VERSION,
                                "encoders": encoders.name})
    _check_root(root, store_path, encoders.name)
    root.require_group(CLIPS_GROUP)
    if NULL_TEXT not in root:
        try:
            null = np.asarray(encoders.text_embeddings(""), dtype=np.float32)
        except ValueError as e:
            if config.text_dropout > 0:
                raise ValueError(f"text_dropout={config.text_dropout} needs the empty prompt's text embeddings, but "
                                 f"the encoders cannot give them: {e}; or set text_dropout=0") from e
            null = None
        if null is not None:
            _write_array(root, NULL_TEXT, null, "float32")
    return str(store_path)


def _write_array(group, name: str, data: np.ndarray, dtype: str) -> None:
    data = np.ascontiguousarray(np.asarray(data, dtype=dtype))
    arr = group.create_array(name, shape=data.shape, dtype=dtype, chunks=data.shape or None, fill_value=0,
                             overwrite=True)
    if data.size:
        arr[...] = data


# --------------------------------------------------------------------------------------------------
# Precompute
# --------------------------------------------------------------------------------------------------
def _depth_for(image_path: Path, clip: str) -> np.ndarray:
    from PIL import Image

    # deferred: open3d (models.simulation) loads only for a simulated source's depth maps
    from navcrafter.models.simulation.datasets import depth_path

    path = depth_path(image_path)
    if not path.is_file():
        raise FileNotFoundError(
            f"clip {clip}: data.render_condition needs the depth of frame 0, {path} does not exist (real datasets "
            f"have no depth; the simulation engine writes <stem>.depth.npy beside each image, and no geometry "
            f"model is run here): set data.render_condition=false for this dataset")
    depth = np.load(path)
    with Image.open(image_path) as im:
        w, h = im.size
    if depth.ndim != 2 or depth.shape != (h, w):
        raise ValueError(f"clip {clip}: {path} holds a {depth.shape} array but its image {image_path.name} is "
                         f"{w}x{h}: the depth must be [H, W] of the image's own size; rewrite it")
    depth = depth.astype(np.float32)
    if not np.all(np.isfinite(depth)) or (depth < 0).any():
        raise ValueError(f"clip {clip}: {path} has non-finite or negative depths (0 marks no surface); rewrite it")
    return depth


def resize_center_crop_depth(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """A depth map ``[h, w]`` cropped/resized to ``height x width`` by the same box as the images'
    ``resize_center_crop``, nearest-neighbour (module docstring); the identity at the same size."""
    h, w = depth.shape
    s = max(width / w, height / h)
    x0, y0 = (w - width / s) / 2, (h - height / s) / 2
    cols = np.clip(np.floor(x0 + (np.arange(width) + 0.5) / s).astype(np.int64), 0, w - 1)
    rows = np.clip(np.floor(y0 + (np.arange(height) + 0.5) / s).astype(np.int64), 0, h - 1)
    return depth[rows[:, None], cols[None, :]]


def _check_latents(z: np.ndarray, encoders, T: int, H: int, W: int, what: str) -> np.ndarray:
    st, sh, sw = encoders.vae_stride
    want = (encoders.latent_channels, (T - 1) // st + 1, H // sh, W // sw)
    z = np.asarray(z, dtype=np.float32)
    if z.shape != want:
        raise ValueError(f"{encoders.name}.encode_video gave {what} of shape {z.shape}, expected {want} "
                         f"(latent_channels, vae_stride {encoders.vae_stride})")
    return z


def render_condition(image: np.ndarray, depth: np.ndarray, c2w: np.ndarray, K: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """Frame 0's coloured points (``depth [H, W]`` lifted with ``K[0]``, camera frame of ``c2w[0]``) rendered
    along ``c2w [T, 4, 4]`` / ``K [T, 3, 3]``: renders uint8 ``[T, H, W, 3]``, visibility uint8 ``[T, H, W]``
    and the point size used."""
    # deferred: torch loads only when a clip's point-cloud condition is rendered
    from navcrafter.models.reconstruction.pointrender import render_points

    T = len(c2w)
    H, W = depth.shape
    pts, idx = unproject_depth(depth, c2w[0], K[0])
    renders = np.zeros((T, H, W, 3), dtype=np.uint8)
    vis = np.zeros((T, H, W), dtype=np.uint8)
    if not len(pts):
        return renders, vis, 0.0
    cols = np.asarray(image, dtype=np.uint8).reshape(-1, 3)[idx]
    size = default_point_size(pts)
    for t in range(T):
        r = render_points(pts, c2w[t], K[t], H, W, size, colors=cols)
        renders[t], vis[t] = r.color, r.mask
    return renders, vis, float(size)


def _clip_arrays(ref: ClipRef, encoders: ClipEncoders, config: CameraTrainingConfig
                 ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    d = config.data
    reader = _open_reader(ref.kind, ref.root, ref.dataset_split, num_frames=ref.num_frames - 1, stride=ref.stride,
                          resolution=ref.resolution, seed=config.seed)
    sample = reader.clip(ref.sequence, ref.start)
    images = sample.images
    T, H, W = images.shape[:3]
    video = _to_video(images)
    condition = np.zeros_like(video)
    condition[:, 0] = video[:, 0]
    c2w = sample.relative_c2w()
    out: dict[str, np.ndarray] = {
        "latents": _check_latents(encoders.encode_video(video), encoders, T, H, W, "latents"),
        "image_latents": _check_latents(encoders.encode_video(condition), encoders, T, H, W, "image_latents"),
        "image_embeds": np.asarray(encoders.image_features(images[0]), dtype=np.float32),
        "text_embeds": np.asarray(encoders.text_embeddings(d.prompt), dtype=np.float32),
        "c2w": c2w, "K": np.asarray(sample.K, dtype=np.float64),
    }
    if out["image_embeds"].ndim != 2 or out["image_embeds"].shape[1] != encoders.image_dim:
        raise ValueError(f"{encoders.name}.image_features gave {out['image_embeds'].shape}, expected "
                         f"[L_img, {encoders.image_dim}]")
    if out["text_embeds"].shape != (512, encoders.text_dim):
        raise ValueError(f"{encoders.name}.text_embeddings gave {out['text_embeds'].shape}, expected "
                         f"[512, {encoders.text_dim}]")
    extra: dict[str, Any] = {"frame_indices": [int(i) for i in sample.indices], "reference_index": None,
                             "point_size": None}
    if d.render_condition:
        depth = resize_center_crop_depth(_depth_for(Path(sample.paths[0]), ref.clip_id), H, W)
        renders, vis, size = render_condition(images[0], depth, c2w, sample.K)
        out["render_latents"] = _check_latents(encoders.encode_video(_to_video(renders)), encoders, T, H, W,
                                               "render_latents")
        out["visibility"] = vis
        extra["point_size"] = size
    if d.extra_reference and ref.start > 0:
        rng = np.random.default_rng([int(config.seed), zlib.crc32(ref.clip_id.encode())])
        back = int(rng.integers(1, min(2 * T, ref.start) + 1))
        index = ref.start - back
        one = _open_reader(ref.kind, ref.root, ref.dataset_split, num_frames=1, stride=1,
                           resolution=ref.resolution, seed=config.seed).clip(ref.sequence, index)
        out["reference_latents"] = _check_latents(encoders.encode_video(_to_video(one.image[None])), encoders,
                                                  1, H, W, "reference_latents")
        out["reference_c2w"] = np.linalg.inv(sample.c2w[0]) @ one.c2w[0]
        extra["reference_index"] = index
    return out, extra


def _attrs(ref: ClipRef, encoders, config: CameraTrainingConfig) -> dict[str, Any]:
    d = config.data
    return {"source": ref.kind, "sequence": ref.sequence, "start": ref.start, "stride": ref.stride,
            "split": ref.split, "height": ref.resolution, "width": ref.resolution, "num_frames": ref.num_frames,
            "clip_id": ref.clip_id, "source_index": ref.source_index, "source_root": ref.root,
            "encoders": encoders.name, "prompt": d.prompt, "render_condition": d.render_condition,
            "extra_reference": d.extra_reference}


def _ready_root(store_path: str | os.PathLike, encoders: ClipEncoders, config: CameraTrainingConfig):
    """The store's root, initialised (``init_clip_store``) when it is not yet."""
    import zarr

    try:
        root = _open_root(store_path, "r+")
    except (FileNotFoundError, zarr.errors.GroupNotFoundError):
        root = None
    if (root is None or "format" not in root.attrs or CLIPS_GROUP not in root
            or (NULL_TEXT not in root and config.text_dropout > 0)):
        init_clip_store(store_path, encoders, config)
        root = _open_root(store_path, "r+")
    _check_root(root, store_path, encoders.name)
    return root


def precompute_clip(store_path: str | os.PathLike, ref: ClipRef, encoders: ClipEncoders,
                    config: CameraTrainingConfig) -> str:
    """Write the group ``clips/<ref.clip_id>`` (module docstring) unless it is complete; returns the clip id."""
    root = _ready_root(store_path, encoders, config)
    clips = root[CLIPS_GROUP]
    attrs = _attrs(ref, encoders, config)
    name = ref.clip_id
    if name in clips:
        have = clips[name].attrs.asdict()
        if have.get("done") is True:
            diff = [k for k in _IDENTITY_ATTRS if have.get(k) != attrs[k]]
            if diff:
                raise ClipStoreError(
                    f"{store_path}: clip {name} was precomputed with other settings ("
                    + ", ".join(f"{k}: {have.get(k)!r} vs {attrs[k]!r}" for k in diff)
                    + "); use a new run folder (a store must not mix configurations)")
            return name
    arrays, extra = _clip_arrays(ref, encoders, config)
    if name in clips:
        del clips[name]  # a partial group from a killed run
    group = clips.create_group(name, attributes={**attrs, **extra, "done": False})
    for key, value in arrays.items():
        _write_array(group, key, value, CLIP_ARRAYS[key][0])
    group.update_attributes({"done": True})  # the complete marker, last, in one write
    return name


# --------------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------------
class ClipDataset:
    """The complete clips of a store (``split``: ``"train"``, ``"validation"`` or ``None`` for all), sorted by id.

    ``ds[i]`` is a dict of numpy arrays by ``CLIP_ARRAYS`` name (optional ones only when stored) plus
    ``"attrs"`` (the group's attributes). Incomplete groups (a precompute in progress or killed) are not listed.
    """

    def __init__(self, store_path: str | os.PathLike, split: str | None = None) -> None:
        import zarr

        if split is not None and split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS} or None, got {split!r}")
        self.store_path = str(store_path)
        self.split = split
        try:
            root = _open_root(store_path, "r")
        except (FileNotFoundError, zarr.errors.GroupNotFoundError):
            raise FileNotFoundError(f"no clip store at {store_path}: precompute the clips first "
                                    f"(navcrafter train-camera, or tasks.training.clips.precompute_clip)") from None
        _check_root(root, store_path, None)
        clips = root[CLIPS_GROUP] if CLIPS_GROUP in root else None
        ids = []
        if clips is not None:
            for name, g in clips.groups():
                a = g.attrs.asdict()
                if a.get("done") is True and (split is None or a.get("split") == split):
                    ids.append(name)
        self._ids = sorted(ids)
        self._clips = clips

    @property
    def ids(self) -> list[str]:
        return list(self._ids)

    def __len__(self) -> int:
        return len(self._ids)

    def __getitem__(self, i: int) -> dict[str, Any]:
        n = len(self._ids)
        if not -n <= i < n:
            raise IndexError(f"clip index {i} out of range for {n} clips of {self.store_path}")
        g = self._clips[self._ids[i]]
        out: dict[str, Any] = {}
        for key in CLIP_ARRAYS:
            if key in g:
                out[key] = np.asarray(g[key][...])
            elif key in CLIP_REQUIRED:
                raise ClipStoreError(f"{self.store_path}: clip {self._ids[i]} is marked done but has no {key}; "
                                     f"delete the group clips/{self._ids[i]} and precompute it again")
        out["attrs"] = g.attrs.asdict()
        return out

    def __repr__(self) -> str:
        return f"ClipDataset({self.store_path!r}, split={self.split!r}, clips={len(self)})"

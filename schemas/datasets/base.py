"""What the dataset readers share: records, ``DatasetError``, image and camera helpers, the sampling protocol.

``DatasetReader`` implements the protocol below once for all formats; a format module only says which
sequences there are (``_discover``) and reads one sequence's cameras and frame paths into a ``SequenceInfo``
(``_load``), with poses already OpenCV camera-to-world and intrinsics in pixels of ``SequenceInfo.sizes``.

Sampling protocol (the paper's)
===============================
A clip is a conditioning frame and the ``num_frames`` (14) frames after it, every ``stride`` (1) frames:
``T = num_frames + 1`` frames at sequence indices ``start + stride * k``, ``k = 0..num_frames``. Frames are
resized (aspect ratio kept) to cover ``resolution`` = ``(height, width)`` and centre-cropped, with the
intrinsics adjusted exactly (``resize_center_crop``); ``resolution=None`` keeps the native frames.

``clips_per_dataset`` clips (``None``: one per sequence) are drawn deterministically from ``seed``: the
sequences are visited in a seeded permutation of their sorted names, each gives one clip per round (a
start drawn without replacement from its valid starts by a generator seeded with ``(seed, crc32(name))``,
so a sequence's clips do not depend on the other sequences), and rounds repeat until enough clips are
drawn or every sequence is exhausted (fewer clips are then yielded). ``start="first"`` conditions on each
sequence's first frame (one clip per sequence). The first ``n`` clips of a draw do not depend on
``clips_per_dataset`` beyond ``n``.

Errors: a bad file raises ``DatasetError`` naming the file (and line) and the fix when read directly
(``reader.sequence(name)``, ``reader.clip(name, start)``). Iterating a reader skips a bad sequence and
records why in ``reader.skipped`` (``{sequence: reason}``) unless ``strict=True``; if nothing at all can be
read, iteration raises with the reasons. Iteration is lazy: a sequence's metadata is parsed when first
visited and each ``Sample`` holds its decoded frames (uint8 arrays) only once it is yielded.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from PIL import Image

from navcrafter.models.camera.camerafiles import DatasetError, _check_rigid, _floats, _natural_key, _read_lines
from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.camera.trajectories import GL_CV_FLIP

__all__ = ["GL_CV_FLIP", "DatasetError", "_check_rigid", "_floats", "_natural_key", "_read_lines"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
StartMode = Literal["random", "first"]



# --------------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------------
@dataclass(eq=False)
class Sample:
    """One evaluation clip: a conditioning frame and the ground-truth frames after it.

    ``T = len(c2w)`` frames in all; index 0 is the conditioning frame.
    """

    dataset: str                      # "re10k" | "dl3dv" | "tnt"
    sequence: str                     # video id / scene name
    image: np.ndarray                 # [H, W, 3] uint8, the conditioning frame
    frames: np.ndarray                # [T-1, H, W, 3] uint8, the frames after it (decoded, not lazy)
    c2w: np.ndarray                   # [T, 4, 4] float64, OpenCV camera-to-world, dataset world frame
    K: np.ndarray                     # [T, 3, 3] float64, pixels of the returned frames
    frame_ids: list[str]              # [T] file stems (RE10K: the timestamps)
    indices: np.ndarray               # [T] int, positions of the frames in the sequence
    timestamps_us: np.ndarray | None  # [T] int64 video time in microseconds (RE10K), else None
    paths: list[Path]                 # [T] source image files
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        """All frames, conditioning frame included (``T``)."""
        return int(self.c2w.shape[0])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def start(self) -> int:
        return int(self.indices[0])

    @property
    def clip_id(self) -> str:
        """A stable name for the clip: ``<dataset>/<sequence>@<start>``."""
        return f"{self.dataset}/{self.sequence}@{self.start}"

    @property
    def images(self) -> np.ndarray:
        """All ``T`` frames ``[T, H, W, 3]``, the conditioning frame first."""
        return np.concatenate([self.image[None], self.frames], axis=0)

    def intrinsics(self, i: int = 0) -> Intrinsics:
        return Intrinsics.from_matrix(self.K[i], self.width, self.height)

    def relative_c2w(self) -> np.ndarray:
        """Poses in the conditioning camera's frame (``c2w[0]`` becomes the identity), navcrafter's
        scene convention. Units stay the dataset's (arbitrary scale for SfM-posed datasets)."""
        return np.linalg.inv(self.c2w[0]) @ self.c2w


@dataclass(eq=False)
class SequenceInfo:
    """Metadata of a whole sequence, frames not loaded. ``K`` is in pixels of an image of ``sizes[i]``
    (``(width, height)``); it is rescaled to the size of the image actually read."""

    name: str
    c2w: np.ndarray                   # [N, 4, 4] OpenCV camera-to-world
    K: np.ndarray                     # [N, 3, 3]
    sizes: np.ndarray                 # [N, 2] int (width, height) the intrinsics refer to
    paths: list[Path]                 # [N]
    frame_ids: list[str]              # [N]
    timestamps_us: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.paths)


# --------------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------------
def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """OpenGL/nerfstudio camera-to-world (x right, y up, z back) -> OpenCV (x right, y down, z forward).

    Flips the camera's y and z axes: ``c2w @ diag(1, -1, -1, 1)`` (its own inverse). Batched.
    """
    return np.asarray(c2w, dtype=np.float64) @ GL_CV_FLIP


def _image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` from the image header."""
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except FileNotFoundError:
        raise DatasetError(f"image {path} does not exist") from None
    except Exception as e:  # PIL raises many types for bad files
        raise DatasetError(f"cannot read image {path} (corrupt or truncated?): {e}; re-extract or remove it") from None


def _read_image(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except FileNotFoundError:
        raise DatasetError(f"image {path} does not exist") from None
    except Exception as e:
        raise DatasetError(f"cannot read image {path} (corrupt or truncated?): {e}; re-extract or remove it") from None


def _rescale_K(K: np.ndarray, size_from: tuple[int, int], size_to: tuple[int, int], where: str) -> np.ndarray:
    """Intrinsics of an image of ``size_from`` resampled (whole extent) to ``size_to`` (width, height)."""
    (w0, h0), (w1, h1) = size_from, size_to
    if (w0, h0) == (w1, h1):
        return np.asarray(K, dtype=np.float64).copy()
    # a downscaled copy keeps the aspect ratio up to rounding of its size
    if abs(h1 - h0 * w1 / w0) > 1.0 + 1e-6 and abs(w1 - w0 * h1 / h0) > 1.0 + 1e-6:
        raise DatasetError(f"{where}: the image is {w1}x{h1} but its intrinsics are for {w0}x{h0} (a different "
                           "aspect ratio); check that the image belongs to this camera file, or give intrinsics "
                           "for this image size")
    return Intrinsics.from_matrix(K, w0, h0).resize(w1, h1).K


def resize_center_crop(image: np.ndarray, K: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Scale ``image`` uniformly to cover ``height x width``, keep the centred part, adjust ``K``.

    With ``s = max(width / w, height / h)`` the kept source region is the centred box of
    ``(width / s) x (height / s)`` pixels, starting at pixel edge ``(x0, y0) = ((w - width/s) / 2,
    (h - height/s) / 2)`` (fractional in general); it is resampled (Lanczos) to ``width x height``. Hence
    ``fx' = s fx``, ``fy' = s fy``, ``cx' = s (cx - x0)``, ``cy' = s (cy - y0)``: a 3D point projects with the
    new ``K`` onto the same image content as before, and the image centre stays the centre.
    """
    h, w = image.shape[:2]
    s = max(width / w, height / h)
    bw, bh = width / s, height / s
    x0, y0 = (w - bw) / 2, (h - bh) / 2
    K = np.asarray(K, dtype=np.float64)
    K2 = np.array([[s * K[0, 0], s * K[0, 1], s * (K[0, 2] - x0)],
                   [0.0, s * K[1, 1], s * (K[1, 2] - y0)],
                   [0.0, 0.0, 1.0]])
    if (w, h) == (width, height):
        return np.ascontiguousarray(image, dtype=np.uint8), K2
    pil = Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8))
    pil = pil.resize((width, height), Image.Resampling.LANCZOS, box=(x0, y0, x0 + bw, y0 + bh))
    return np.asarray(pil, dtype=np.uint8), K2


# --------------------------------------------------------------------------------------------------
# Reader base: the sampling protocol
# --------------------------------------------------------------------------------------------------
class DatasetReader:
    """Base of the readers: sequence discovery and metadata are per format, the protocol is shared.

    Protocol options (all readers): ``num_frames`` frames after the conditioning frame (T = num_frames+1),
    ``stride`` between frames, ``clips_per_dataset`` (``None``: one clip per sequence), ``seed``,
    ``resolution`` (``int`` -> square, ``(height, width)``, or ``None`` for native frames), ``start``
    (``"random"`` or ``"first"``), ``sequences`` (only these names), ``strict`` (raise instead of skipping).
    """

    kind: ClassVar[str] = ""

    def __init__(self, root: str | Path, *, num_frames: int = 14, stride: int = 1,
                 clips_per_dataset: int | None = None, seed: int = 0,
                 resolution: int | tuple[int, int] | None = (256, 256), start: StartMode = "random",
                 sequences: Sequence[str] | None = None, strict: bool = False) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.kind} root {self.root} is not a folder")
        if num_frames < 1 or stride < 1:
            raise ValueError(f"num_frames and stride must be >= 1, got {num_frames}, {stride}")
        if clips_per_dataset is not None and clips_per_dataset < 1:
            raise ValueError(f"clips_per_dataset must be >= 1 or None, got {clips_per_dataset}")
        if start not in ("random", "first"):
            raise ValueError(f"start must be 'random' or 'first', got {start!r}")
        if isinstance(resolution, int):
            resolution = (resolution, resolution)
        if resolution is not None and (len(resolution) != 2 or min(resolution) < 1):
            raise ValueError(f"resolution must be (height, width) of positive ints or None, got {resolution}")
        self.num_frames = int(num_frames)
        self.stride = int(stride)
        self.clips_per_dataset = clips_per_dataset
        self.seed = int(seed)
        self.resolution = None if resolution is None else (int(resolution[0]), int(resolution[1]))
        self.start = start
        self.only = None if sequences is None else [str(s) for s in sequences]
        self.strict = strict
        self.skipped: dict[str, str] = {}
        self._cache: dict[str, SequenceInfo] = {}

    # ---- per format -------------------------------------------------------------------------------
    def _discover(self) -> list[str]:
        raise NotImplementedError

    def _load(self, name: str) -> SequenceInfo:
        raise NotImplementedError

    # ---- public -----------------------------------------------------------------------------------
    @property
    def clip_length(self) -> int:
        """Frames a clip spans in its sequence: ``1 + num_frames * stride``."""
        return 1 + self.num_frames * self.stride

    def sequence_names(self) -> list[str]:
        """All sequence names, sorted (natural order)."""
        names = sorted(self._discover(), key=_natural_key)
        if self.only is not None:
            missing = [s for s in self.only if s not in names]
            if missing:
                raise DatasetError(f"{self.kind} sequences not found under {self.root}: {', '.join(missing)}")
            names = [s for s in names if s in set(self.only)]
        return names

    def sequence(self, name: str) -> SequenceInfo:
        """Metadata of one sequence (cached); raises ``DatasetError`` for a bad one."""
        if name not in self._cache:
            self._cache[name] = self._load(name)
        return self._cache[name]

    def valid_starts(self, info: SequenceInfo) -> np.ndarray:
        n = len(info)
        if n < self.clip_length:
            raise DatasetError(f"{self.kind} sequence {info.name!r} has {n} frames but a clip needs "
                               f"{self.clip_length} (1 + num_frames={self.num_frames} x stride={self.stride}); "
                               "lower num_frames/stride or leave the sequence out")
        return np.arange(n - self.clip_length + 1)

    def starts_for(self, info: SequenceInfo) -> list[int]:
        """The sequence's clip starts in draw order (deterministic in ``seed`` and the name)."""
        valid = self.valid_starts(info)
        if self.start == "first":
            return [0]
        rng = np.random.default_rng([self.seed, zlib.crc32(info.name.encode())])
        return [int(s) for s in rng.permutation(valid)]

    def clip(self, sequence: str | SequenceInfo, start: int) -> Sample:
        """Load the clip of ``sequence`` conditioned on its frame ``start``."""
        info = self.sequence(sequence) if isinstance(sequence, str) else sequence
        idx = start + self.stride * np.arange(self.num_frames + 1)
        if start < 0 or idx[-1] >= len(info):
            raise DatasetError(f"{self.kind} sequence {info.name!r}: a clip from frame {start} needs frames "
                               f"{start}..{idx[-1]} but the sequence has {len(info)}")
        images, Ks = [], []
        for i in idx:
            img = _read_image(info.paths[i])
            size = (img.shape[1], img.shape[0])
            K = _rescale_K(info.K[i], tuple(info.sizes[i]), size, str(info.paths[i]))
            if self.resolution is not None:
                img, K = resize_center_crop(img, K, *self.resolution)
            images.append(img)
            Ks.append(K)
        shapes = {im.shape for im in images}
        if len(shapes) > 1:
            raise DatasetError(f"{self.kind} sequence {info.name!r}: frames of one clip differ in size {shapes}; "
                               "set a resolution to resize them")
        stack = np.stack(images)
        return Sample(
            dataset=self.kind, sequence=info.name, image=stack[0], frames=stack[1:],
            c2w=info.c2w[idx].copy(), K=np.stack(Ks), frame_ids=[info.frame_ids[i] for i in idx],
            indices=idx.astype(np.int64),
            timestamps_us=None if info.timestamps_us is None else info.timestamps_us[idx].copy(),
            paths=[info.paths[i] for i in idx],
            meta={**info.meta, "start": int(start), "stride": self.stride, "num_frames": self.num_frames},
        )

    def _order(self) -> list[str]:
        names = self.sequence_names()
        if not names:
            raise DatasetError(f"no {self.kind} sequences found under {self.root}; see the expected folder layout "
                               "in navcrafter.schemas.datasets")
        rng = np.random.default_rng(self.seed)
        return [names[i] for i in rng.permutation(len(names))]

    def _skip(self, name: str, err: DatasetError) -> None:
        if self.strict:
            raise err
        self.skipped[name] = str(err)

    def _candidates(self, bad: set[str]) -> Iterator[tuple[SequenceInfo, int]]:
        """(sequence, start) in draw order: round r takes each good sequence's r-th start."""
        good: list[tuple[SequenceInfo, list[int]]] = []
        for name in self._order():
            try:
                info = self.sequence(name)
                starts = self.starts_for(info)
            except DatasetError as e:
                self._skip(name, e)
                continue
            good.append((info, starts))
            yield info, starts[0]
        r = 1
        while True:
            more = [(info, s[r]) for info, s in good if len(s) > r and info.name not in bad]
            if not more:
                return
            for info, start in more:
                if info.name not in bad:
                    yield info, start
            r += 1

    def plan(self) -> list[tuple[str, int]]:
        """The ``(sequence, start)`` pairs iteration would load, without loading frames (a sequence whose
        frames turn out unreadable is skipped by iteration, which then draws further clips)."""
        self.skipped = {}
        limit = self.clips_per_dataset
        out: list[tuple[str, int]] = []
        for info, start in self._candidates(set()):
            if limit is not None and len(out) >= limit:
                break
            if limit is None and any(n == info.name for n, _ in out):
                break
            out.append((info.name, start))
        return out

    def __iter__(self) -> Iterator[Sample]:
        self.skipped = {}
        bad: set[str] = set()
        limit = self.clips_per_dataset
        done: set[str] = set()
        count = 0
        for info, start in self._candidates(bad):
            if limit is not None and count >= limit:
                return
            if limit is None and info.name in done:
                return  # one clip per sequence: the second round begins
            try:
                sample = self.clip(info, start)
            except DatasetError as e:
                bad.add(info.name)
                self._skip(info.name, e)
                continue
            done.add(info.name)
            count += 1
            yield sample
        if count == 0 and self.skipped:
            reasons = "\n  ".join(f"{k}: {v}" for k, v in self.skipped.items())
            raise DatasetError(f"no usable {self.kind} clip under {self.root}; every sequence was skipped:\n  "
                               f"{reasons}")

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.root)!r}, num_frames={self.num_frames}, stride={self.stride}, "
                f"clips_per_dataset={self.clips_per_dataset}, seed={self.seed}, resolution={self.resolution})")


def _list_images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS),
                  key=lambda p: _natural_key(p.name))


def _subfolders(root: Path) -> list[str]:
    return [p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith((".", "_"))]

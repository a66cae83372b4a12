"""Where evaluation weights are looked up, and which files are expected."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

ENV_VAR = "NAVCRAFTER_EVAL_WEIGHTS"
DEFAULT_DIR = Path("~/.cache/navcrafter/eval")


class MetricUnavailable(RuntimeError):
    """A metric cannot be computed here (its pretrained weights are missing); it is reported as
    unavailable with this message, which names the file and where to put it."""


@dataclass(frozen=True)
class WeightFile:
    key: str  # our name for it, e.g. "lpips-alex"
    filename: str  # the official file name
    source: str  # where users get it (official release)
    used_by: str  # the metric


# The official files (names as their projects publish them).
WEIGHT_FILES: dict[str, WeightFile] = {}


def register(w: WeightFile) -> WeightFile:
    WEIGHT_FILES[w.key] = w
    return w


def weights_dir(explicit: str | os.PathLike | None = None) -> Path:
    """The folder searched for weight files: ``explicit``, else ``$NAVCRAFTER_EVAL_WEIGHTS``, else
    ``~/.cache/navcrafter/eval``."""
    raw = explicit if explicit is not None else os.environ.get(ENV_VAR) or DEFAULT_DIR
    return Path(raw).expanduser()


def find_weights(key: str, explicit: str | os.PathLike | None = None) -> Path:
    """Path of a registered weight file; ``explicit`` may be the file itself or a folder holding it.

    Raises ``MetricUnavailable`` naming the file, the folder searched and the official source.
    """
    if key not in WEIGHT_FILES:
        raise KeyError(f"unknown weight file {key!r}; known: {sorted(WEIGHT_FILES)}")
    w = WEIGHT_FILES[key]
    if explicit is not None and Path(explicit).expanduser().is_file():
        return Path(explicit).expanduser()
    folder = weights_dir(explicit)
    path = folder / w.filename
    if path.is_file():
        return path
    raise MetricUnavailable(
        f"{w.used_by} is unavailable: weight file {w.filename} not found in {folder}. "
        f"Download it from {w.source} and put it there (or pass --eval-weights DIR / set {ENV_VAR}); "
        "navcrafter never computes this metric with random weights.")

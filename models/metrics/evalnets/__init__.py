"""Pretrained feature networks used only for evaluation (LPIPS, FID, FVD).

Architectures are written here (no torchvision); weights are the official files, which cannot be
downloaded by navcrafter: the user puts them in a folder (``--eval-weights DIR`` or the
``NAVCRAFTER_EVAL_WEIGHTS`` environment variable, default ``~/.cache/navcrafter/eval``). A metric whose
weights are missing is reported as *unavailable* (``MetricUnavailable``), never computed with random
weights.
"""

from navcrafter.models.metrics.evalnets.weights import (
    WEIGHT_FILES,
    MetricUnavailable,
    WeightFile,
    find_weights,
    known_weight_files,
    weights_dir,
)

__all__ = ["WEIGHT_FILES", "MetricUnavailable", "WeightFile", "find_weights", "known_weight_files", "weights_dir"]

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
    weights_dir,
)

__all__ = ["WEIGHT_FILES", "MetricUnavailable", "WeightFile", "find_weights", "known_weight_files", "weights_dir"]


def known_weight_files() -> dict[str, WeightFile]:
    """Every weight file any evaluation network can use (imports the networks, which register them)."""
    # deferred: the networks import torch; only asking for the list of weight files loads them
    from navcrafter.models.metrics.evalnets import fidfvd, lpips  # noqa: F401  (registration on import)

    return dict(WEIGHT_FILES)

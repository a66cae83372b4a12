"""Scene-seed ranges of the simulation benchmarks: ``--seeds A-B`` (inclusive) or ``N`` (0..N-1).

Seeds 0-9 are the DEVELOPMENT range (the project's rule): anything (planners, recipes) may be tuned there and only
there; results are judged on other ranges (e.g. 40-45), which are not looked at while tuning.
"""

from __future__ import annotations

import argparse

DEV_SEEDS = (0, 9)  # the development range (inclusive)


def parse_seeds(text: str) -> tuple[int, int]:
    """``"A-B"``: seeds A..B inclusive; ``"N"``: seeds 0..N-1 (an ``argparse`` type)."""
    try:
        if "-" in text:
            a, b = (int(x) for x in text.split("-", 1))
        else:
            a, b = 0, int(text) - 1
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seeds must be A-B or N, got {text!r}") from None
    if a < 0 or b < a:
        raise argparse.ArgumentTypeError(f"--seeds {text!r} is an empty or negative range")
    return a, b


def is_development(seeds: tuple[int, int]) -> bool:
    """Whether a seed range overlaps the development range."""
    return seeds[0] <= DEV_SEEDS[1] and seeds[1] >= DEV_SEEDS[0]

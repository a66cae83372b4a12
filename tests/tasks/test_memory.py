"""The peak-memory sampler the fit and refine steps report (tasks/memory.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from navcrafter.tasks.memory import PeakRSS, current_rss_bytes


@pytest.mark.skipif(current_rss_bytes() is None, reason="needs /proc/self/statm (Linux)")
def test_peak_rss_sees_a_short_lived_allocation():
    with PeakRSS() as quiet:
        time.sleep(0.05)
    with PeakRSS() as peak:
        block = np.ones(200 * 2**20 // 8)  # 200 MB, touched
        time.sleep(0.1)
        del block
    assert peak.mb is not None and quiet.mb is not None
    assert peak.mb - quiet.mb > 150  # the block was resident while sampled, and is gone at the end
    assert current_rss_bytes() / 2**20 < peak.mb - 100

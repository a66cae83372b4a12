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


@pytest.mark.skipif(current_rss_bytes() is None, reason="needs /proc/self/statm (Linux)")
def test_step_peaks_measure_the_block_and_say_when_there_is_no_gpu(monkeypatch):
    from navcrafter.tasks import memory

    with memory.StepPeaks() as quiet:
        time.sleep(0.05)
    with memory.StepPeaks() as peaks:
        block = np.ones(150 * 2**20 // 8)
        time.sleep(0.1)
        del block
    assert peaks.attrs()["peak_rss_mb"] - quiet.attrs()["peak_rss_mb"] > 100
    assert peaks.attrs()["peak_gpu_mb"] is None  # no CUDA here: no figure, never a guess

    class FakeCuda:  # the allocator's peak over the block, summed over devices, reset at its start
        resets: list[int] = []

        @staticmethod
        def device_count():
            return 2

        @staticmethod
        def reset_peak_memory_stats(d):
            FakeCuda.resets.append(d)

        @staticmethod
        def max_memory_allocated(d):
            return (d + 1) * 2**20

    monkeypatch.setattr(memory.StepPeaks, "_torch_cuda", staticmethod(lambda: FakeCuda))
    with memory.StepPeaks() as gpu:
        pass
    assert FakeCuda.resets == [0, 1] and gpu.attrs()["peak_gpu_mb"] == 3.0

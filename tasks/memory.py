"""Peak resident memory of a block of work: a sampling thread reading the process's RSS (Linux ``/proc``).

``ru_maxrss`` is the whole process's peak since it started (a worker that synthesized video before fitting would
report the synthesis), so a step measures its own peak by sampling while it runs: ``with PeakRSS() as peak: ...``,
then ``peak.mb``. Sampling every 20 ms can miss a spike shorter than that; it never over-reports. Elsewhere than
Linux the figure is ``None`` (and says so), never a guess.
"""

from __future__ import annotations

import os
import threading

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def current_rss_bytes() -> int | None:
    """This process's resident set size now, or None where ``/proc/self/statm`` does not exist."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return None


class PeakRSS:
    """Context manager: the largest RSS sampled while the block ran (``bytes``, ``mb``), at least the RSS at
    its start and end."""

    def __init__(self, interval_s: float = 0.02) -> None:
        self.interval_s = interval_s
        self.bytes: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        rss = current_rss_bytes()
        if rss is not None:
            self.bytes = rss if self.bytes is None else max(self.bytes, rss)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def __enter__(self) -> PeakRSS:
        self._sample()
        self._thread = threading.Thread(target=self._run, name="peak-rss", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._sample()

    @property
    def mb(self) -> float | None:
        return None if self.bytes is None else round(self.bytes / 2**20, 1)


class StepPeaks:
    """Context manager: a step's peak memory, stored with its timings (``peak_rss_mb``, ``peak_gpu_mb``).

    ``peak_rss_mb``: :class:`PeakRSS` over the block (process-wide: steps running at the same time in one process
    share it). ``peak_gpu_mb``: ``torch.cuda.max_memory_allocated`` over the block (the allocator's peak, reset at
    the start; all devices summed) when torch is loaded and CUDA is available, else ``None`` (no GPU, or the step
    never imported torch); onnxruntime's CUDA arena is not torch's and is not counted."""

    def __init__(self, interval_s: float = 0.02) -> None:
        self.rss = PeakRSS(interval_s)
        self.gpu_bytes: int | None = None
        self._cuda = None

    @staticmethod
    def _torch_cuda():
        import sys

        torch = sys.modules.get("torch")  # never import torch for a step that does not use it
        try:
            return torch.cuda if torch is not None and torch.cuda.is_available() else None
        except Exception:  # a broken CUDA install: no figure, not a failed step
            return None

    def __enter__(self) -> StepPeaks:
        self._cuda = self._torch_cuda()
        if self._cuda is not None:
            for d in range(self._cuda.device_count()):
                self._cuda.reset_peak_memory_stats(d)
        self.rss.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.rss.__exit__(*exc)
        cuda = self._cuda or self._torch_cuda()  # torch may have been imported by the step itself
        if cuda is not None:
            self.gpu_bytes = sum(int(cuda.max_memory_allocated(d)) for d in range(cuda.device_count()))

    def attrs(self) -> dict[str, float | None]:
        gpu = None if self.gpu_bytes is None else round(self.gpu_bytes / 2**20, 1)
        return {"peak_rss_mb": self.rss.mb, "peak_gpu_mb": gpu}

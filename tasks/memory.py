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

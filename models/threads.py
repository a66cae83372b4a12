"""One OpenMP thread for the calling thread: torch's CPU kernels while scenes run side by side.

torch runs its CPU kernels on OpenMP threads (two here). When several scenes run in threads of one process (the
collection flows) the cores are already busy, and each kernel's two threads spin waiting for each other: the
point renderer's projection took ~10x the CPU time of one thread (``models/reconstruction/pointrender.py``), the
fit's small elementwise kernels alike. ``one_openmp_thread`` sets the calling thread's OpenMP limit to 1 with
``threadpoolctl`` (the OpenMP thread count is a per-thread setting: other threads keep theirs) and restores it.
(``torch.set_num_threads`` would not do: it also sets MKL's thread count, process-wide.)
numba's parallel kernels (the CPU rasterizer) pass their own thread count and keep it.
"""

from __future__ import annotations

import functools

import torch
from threadpoolctl import ThreadpoolController


@functools.cache
def _controller() -> ThreadpoolController:
    return ThreadpoolController()


def one_openmp_thread():
    """A context in which the calling thread's OpenMP kernels (torch's) run on one thread."""
    # torch sets a thread's OpenMP limit to its own global number at the thread's first torch call: make that call
    # first, or a limit set before it would be overwritten in a thread that had not used torch yet
    torch.get_num_threads()
    return _controller().limit(limits=1, user_api="openmp")

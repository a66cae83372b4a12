"""One OpenMP thread for the calling thread, one BLAS thread for the process: scenes run side by side.

torch runs its CPU kernels on OpenMP threads (two here). When several scenes run in threads of one process (the
collection flows) the cores are already busy, and each kernel's two threads spin waiting for each other: the
point renderer's projection took ~10x the CPU time of one thread (``models/reconstruction/pointrender.py``), the
fit's small elementwise kernels alike. ``one_openmp_thread`` sets the calling thread's OpenMP limit to 1 with
``threadpoolctl`` (the OpenMP thread count is a per-thread setting: other threads keep theirs) and restores it.
(``torch.set_num_threads`` would not do: it also sets MKL's thread count, process-wide.)
numba's parallel kernels (the CPU rasterizer) pass their own thread count and keep it.

``one_blas_thread`` limits numpy's BLAS (OpenBLAS, MKL, ...) to one thread and restores it. The collection flows
run their whole body so: two scenes entering OpenBLAS's thread pool at once were seen to hang a demo run for good
(2026-12-03, ``py-spy dump --native``: one scene's thread spinning in OpenBLAS's ``exec_blas`` under the simulated
synthesizer, the other waiting on OpenBLAS's lock under a 4x4 pose product of the evaluation); with one BLAS thread
a call never enters that pool and the scenes themselves keep both cores busy. The collision-aware optimiser
(``models/planning/planners.py``) runs its L-BFGS starts so too, for callers outside the flows. ``threadpoolctl``
sets it at run time (the environment variables would have to be set before numpy is imported).
"""

from __future__ import annotations

import functools

import torch
from threadpoolctl import ThreadpoolController, threadpool_limits


@functools.cache
def _controller() -> ThreadpoolController:
    return ThreadpoolController()


def one_openmp_thread():
    """A context in which the calling thread's OpenMP kernels (torch's) run on one thread."""
    # torch sets a thread's OpenMP limit to its own global number at the thread's first torch call: make that call
    # first, or a limit set before it would be overwritten in a thread that had not used torch yet
    torch.get_num_threads()
    return _controller().limit(limits=1, user_api="openmp")


def one_blas_thread() -> threadpool_limits:
    """A context in which BLAS libraries (OpenBLAS, MKL, ...) use one thread; restored when it ends. Entered in
    the flow's body (a decorator would hide the flow's annotations from Prefect's parameter validation)."""
    return threadpool_limits(limits=1, user_api="blas")

"""One BLAS thread while scenes run in threads of one process.

The collection flows run several scenes at once on a thread pool. numpy's OpenBLAS keeps one thread pool of its
own, and two scenes entering it at once were seen to hang a demo run for good (2026-12-03, ``py-spy dump
--native``: one scene's thread spinning in OpenBLAS's ``exec_blas`` under the simulated synthesizer, the other
waiting on OpenBLAS's lock under a 4x4 pose product of the evaluation). With one BLAS thread a call never
enters that pool; the scenes themselves keep both cores busy. ``threadpoolctl`` sets it at run time (the
environment variables would have to be set before numpy is imported) and restores it when the flow ends.
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def one_blas_thread() -> threadpool_limits:
    """A context in which BLAS libraries (OpenBLAS, MKL, ...) use one thread; restored when it ends. Entered in
    the flow's body (a decorator would hide the flow's annotations from Prefect's parameter validation)."""
    return threadpool_limits(limits=1, user_api="blas")

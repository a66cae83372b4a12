"""The collection flows run with one BLAS thread (flows/blas.py): scenes run in threads, and numpy's OpenBLAS
pool hung when two of them entered it at once."""

import numpy as np
from threadpoolctl import threadpool_info

from navcrafter.flows.blas import one_blas_thread
from navcrafter.flows.evaluate import evaluate_store
from navcrafter.flows.explore import explore_collection


def _blas_threads() -> list[int]:
    np.ones((2, 2)) @ np.ones((2, 2))  # the BLAS library is loaded
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_inside_and_restored_after():
    before = _blas_threads()
    assert before, "numpy has no BLAS library threadpoolctl can see"
    inside = one_blas_thread(_blas_threads)()
    assert inside == [1] * len(before)
    assert _blas_threads() == before


def test_the_collection_flows_are_limited():
    for flow_ in (explore_collection, evaluate_store):
        assert getattr(flow_.fn, "__wrapped__", None) is not None, f"{flow_.name} runs without one_blas_thread"

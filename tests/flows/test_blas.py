"""The collection flows run with one BLAS thread (models/threads.py): scenes run in threads, and numpy's OpenBLAS
pool hung when two of them entered it at once."""

import numpy as np
from threadpoolctl import threadpool_info

from navcrafter.flows.evaluate import evaluate_store
from navcrafter.flows.explore import explore_collection
from navcrafter.models.threads import one_blas_thread


def _blas_threads() -> list[int]:
    np.ones((2, 2)) @ np.ones((2, 2))  # the BLAS library is loaded
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_inside_and_restored_after():
    before = _blas_threads()
    assert before, "numpy has no BLAS library threadpoolctl can see"
    with one_blas_thread():
        inside = _blas_threads()
    assert inside == [1] * len(before)
    assert _blas_threads() == before


def test_the_collection_flows_are_limited(monkeypatch):
    """Each flow's body runs inside the limit (seen from the body the flow calls)."""
    import navcrafter.flows.evaluate as evaluate_mod
    import navcrafter.flows.explore as explore_mod

    seen = {}
    monkeypatch.setattr(explore_mod, "_explore_collection", lambda *a: seen.setdefault("explore", _blas_threads()))
    monkeypatch.setattr(evaluate_mod, "_evaluate_store", lambda *a: seen.setdefault("evaluate", _blas_threads()))
    explore_collection.fn("photos", "store", None)
    evaluate_store.fn("store", None)
    assert set(seen["explore"]) == {1} and set(seen["evaluate"]) == {1}

"""``models.threads.one_openmp_thread``: the calling thread's torch kernels on one OpenMP thread, others untouched."""

from __future__ import annotations

import threading

import torch

from navcrafter.models.threads import one_openmp_thread


def test_one_openmp_thread_limits_the_calling_thread_only_and_restores_it():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        inside, entered, checked = {}, threading.Event(), threading.Event()

        def scene():
            with one_openmp_thread():
                inside["threads"] = torch.get_num_threads()
                entered.set()
                checked.wait(10)
            inside["after"] = torch.get_num_threads()

        t = threading.Thread(target=scene)
        t.start()
        assert entered.wait(10)
        assert torch.get_num_threads() == 2  # this thread's setting while the other is inside the limit
        checked.set()
        t.join()
        assert inside["threads"] == 1 and inside["after"] == 2
    finally:
        torch.set_num_threads(before)

"""The z-buffered point renderer: its projection runs on the calling thread's one OpenMP thread, with the values of
torch's multi-threaded kernels."""

from __future__ import annotations

import threading

import numpy as np
import torch

from navcrafter.models.camera.cameras import Intrinsics, look_at
from navcrafter.models.reconstruction.pointrender import _project, render_points
from navcrafter.models.threads import one_openmp_thread


def test_projection_on_one_thread_has_the_values_of_several_and_restores_the_setting():
    rng = np.random.default_rng(0)
    points = rng.uniform([-3, -2, 1], [3, 2, 8], (300_000, 3)).astype(np.float32)
    K = Intrinsics.from_fov(70, 256, 192).K
    c2w = look_at(np.array([0.2, -0.1, -0.5]), np.array([0.0, 0.0, 4.0]), up=np.array([0.0, -1.0, 0.0]))
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        several = _project(points, c2w, K, 192, 256, 0.02, 3, 1e-3)  # torch's threads, as before the limit
        r = render_points(points, c2w, K, 192, 256, point_size=0.02)
        assert torch.get_num_threads() == 2  # the calling thread's setting is restored
        seen = {}

        def other():  # the limit is the calling thread's own: another thread keeps its setting meanwhile
            seen["threads"] = torch.get_num_threads()

        t = threading.Thread(target=other)
        t.start()
        t.join()
        assert seen["threads"] == 2
    finally:
        torch.set_num_threads(before)
    with one_openmp_thread():
        assert torch.get_num_threads() == 1
        one = _project(points, c2w, K, 192, 256, 0.02, 3, 1e-3)
    for a, b in zip(one[:5], several[:5], strict=True):
        np.testing.assert_array_equal(a, b)
    assert r.mask.mean() > 0.5 and (r.depth[r.mask] > 0).all()

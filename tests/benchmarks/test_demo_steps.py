"""benchmarks/demo_steps.py: step kinds, the /usr/bin/time file and the bit-identity count of two stores' arrays
(each can fail: a changed value, dtype or a missing array must be counted)."""

from __future__ import annotations

import numpy as np
import zarr

from benchmarks.demo_steps import compare_arrays, read_cpu, step_kind


def test_step_kinds():
    assert step_kind("iter_2/synthesize") == "synthesize"
    assert step_kind("iter_0/geometry") == "geometry"
    assert step_kind("gaussians") == "gaussians"
    assert step_kind("evaluation") == "evaluation"


def test_cpu_file(tmp_path):
    f = tmp_path / "cpu.txt"
    f.write_text("cpu user 812.50 sys 40.25 wall 600.10 maxrss_kb 4000000\n")
    got = read_cpu(str(f))
    assert got["cpu_s"] == 852.8 and got["wall_s"] == 600.1 and got["maxrss_kb"] == 4_000_000


def _store(root, values, dtype="float32", extra=False):
    g = zarr.open_group(str(root / "scenes"), mode="w")
    s = g.create_group("abc").create_group("iter_1")
    s.create_array("frames", shape=(3,), dtype=dtype)[...] = values
    s.create_array("nan", shape=(2,), dtype="float32")[...] = [np.nan, 1.0]
    if extra:
        g["abc"].create_array("only_here", shape=(1,), dtype="int8")[...] = [1]
    return str(root)


def test_compare_arrays_counts_what_differs(tmp_path):
    a = _store(tmp_path / "a", [1, 2, 3], extra=True)
    same = _store(tmp_path / "same", [1, 2, 3])
    changed = _store(tmp_path / "changed", [1, 2, 4])
    other_dtype = _store(tmp_path / "dtype", [1, 2, 3], dtype="float64")
    assert compare_arrays(same, a) == {"equal": 2, "differ": 0, "missing": 0, "differing": []}  # NaN == NaN
    assert compare_arrays(a, same) == {"equal": 2, "differ": 0, "missing": 1, "differing": ["/abc/only_here"]}
    assert compare_arrays(same, changed)["differing"] == ["/abc/iter_1/frames"]
    assert compare_arrays(same, other_dtype)["differ"] == 1

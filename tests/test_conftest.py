"""The suite's own rules (tests/conftest.py): a test that starts a process of its own must carry the ``subprocess``
(or ``system``) marker; the ONNX export cache (helpers.cached_export) exports once for concurrent callers."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import pytest
from helpers import cached_export


def test_an_unmarked_test_cannot_start_a_python_process():
    with pytest.raises(pytest.fail.Exception, match="without @pytest.mark.subprocess"):
        subprocess.run([sys.executable, "-c", "pass"], check=True)


@pytest.mark.subprocess
def test_a_marked_test_can():
    assert subprocess.run([sys.executable, "-c", "print(6 * 7)"], capture_output=True, text=True).stdout == "42\n"


def test_other_tools_are_not_refused(tmp_path):
    assert subprocess.run(["true"]).returncode == 0


def test_concurrent_callers_of_the_export_cache_export_once(tmp_path):
    """The pytest-xdist workers of one run ask for the same export at about the same time: one exports, the
    others wait for it and copy its files (conftest.export_cache)."""
    calls = []

    def export(out):
        calls.append(threading.get_ident())
        time.sleep(0.5)  # long enough for every other caller to arrive while the first is exporting
        out.mkdir(parents=True)
        (out / "model.onnx").write_bytes(b"graph")
        return {"inputs": ["x"]}

    results = {}

    def ask(i):
        results[i] = cached_export(tmp_path / "cache", tmp_path / f"dest{i}", "tiny", {"seed": 0}, export)

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert all(results[i] == {"inputs": ["x"]} for i in range(3))
    assert all((tmp_path / f"dest{i}" / "model.onnx").read_bytes() == b"graph" for i in range(3))
    # another argument is another export; the first one's entry stays
    assert cached_export(tmp_path / "cache", tmp_path / "dest3", "tiny", {"seed": 1}, export) == {"inputs": ["x"]}
    assert len(calls) == 2
    entries = sorted(p.name for p in (tmp_path / "cache").iterdir() if p.is_dir())
    assert len(entries) == 2 and all(json.loads((tmp_path / "cache" / e / "result.json").read_text())
                                     for e in entries)

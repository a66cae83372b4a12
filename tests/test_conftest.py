"""The suite's own rules (tests/conftest.py): a test that starts a process of its own must carry the ``subprocess``
(or ``system``) marker; the ONNX export cache (helpers.cached_export) exports once for concurrent callers."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers import cached_export

ROOT = Path(__file__).resolve().parents[1]


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



@pytest.mark.subprocess
def test_modules_with_module_fixtures_run_whole_and_long_work_first(tmp_path):
    """deploy/local/run-tests.sh runs ``--dist loadgroup --no-loadscope-reorder``: conftest.schedule_for_xdist
    makes each module with module fixtures one work unit (test_worker's `prefect server start` was set up twice
    when worksteal split it) and hands out the long units first, the short tests last."""
    (tmp_path / "groups_plugin.py").write_text(
        "def pytest_collection_finish(session):\n"
        "    for item in session.items:\n"
        "        groups = [m.args[0] for m in item.iter_markers('xdist_group')]\n"
        "        long = bool(item.get_closest_marker('slow') or item.get_closest_marker('system'))\n"
        "        print('ITEM', item.nodeid, ','.join(groups) or '-', long, flush=True)\n")
    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                          "-p", "groups_plugin", "tests/test_conftest.py", "tests/flows/test_cli.py",
                          "tests/flows/test_worker.py"], capture_output=True, text=True, check=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(tmp_path)}).stdout
    items = [line.split()[1:] for line in out.splitlines() if line.startswith("ITEM ")]
    modules = [nodeid.split("::")[0] for nodeid, _, _ in items]
    worker = "tests/flows/test_worker.py"
    n = modules.count(worker)
    assert n >= 5 and modules[:n] == [worker] * n  # the long module with module fixtures first, whole
    assert all(group == worker for _, group, _ in items[:n])
    assert all(group == "-" for _, group, _ in items[n:])  # test_cli and this module have no module fixtures
    long = [is_long == "True" for _, _, is_long in items[n:]]
    assert any(long) and not all(long) and long == sorted(long, reverse=True)  # long singles, then short
    assert "--dist loadgroup --no-loadscope-reorder" in (ROOT / "deploy/local/run-tests.sh").read_text()

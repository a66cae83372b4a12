"""The suite's own rules (tests/conftest.py): a test that starts a process of its own must carry the ``subprocess``
(or ``system``) marker."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_an_unmarked_test_cannot_start_a_python_process():
    with pytest.raises(pytest.fail.Exception, match="without @pytest.mark.subprocess"):
        subprocess.run([sys.executable, "-c", "pass"], check=True)


@pytest.mark.subprocess
def test_a_marked_test_can():
    assert subprocess.run([sys.executable, "-c", "print(6 * 7)"], capture_output=True, text=True).stdout == "42\n"


def test_other_tools_are_not_refused(tmp_path):
    assert subprocess.run(["true"]).returncode == 0

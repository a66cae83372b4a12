"""Every benchmark script is a module of the ``benchmarks`` package (issue 33): ``import benchmarks.<name>`` works
(tests and ``gpu_check`` import them so, never by path) as well as ``python benchmarks/<name>.py``. A script that
imports a sibling does so as ``from benchmarks.<sibling> import ...`` after putting the repository root on the path
when run as a script (``if __package__ in (None, ""): sys.path.insert(...)``). Import only: nothing runs."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
# none of the scripts needs a GPU to be imported (gpu_check and the *_gpu scripts look for CUDA when they run)
NAMES = sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem != "__init__")


def test_the_scripts_are_found():
    assert {"gpu_check", "seeds", "synthesis", "fit_defaults", "pose_floor"} <= set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_imports_as_a_module(name):
    module = importlib.import_module(f"benchmarks.{name}")
    assert Path(module.__file__).resolve() == BENCHMARKS / f"{name}.py"

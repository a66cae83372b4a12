"""The deploy helpers in Python are modules of the ``deploy`` package (issue 33): tests import them as
``deploy.<folder>.<name>``, never load them by path; each also runs as a script. Import only: nothing runs."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
NAMES = sorted(".".join(p.relative_to(DEPLOY).with_suffix("").parts) for p in DEPLOY.rglob("*.py")
               if p.name != "__init__.py")


def test_the_helpers_are_found():
    assert {"local.browser", "local.dashboard_screenshot", "gpu.emulate_image"} <= set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_imports_as_a_module(name):
    module = importlib.import_module(f"deploy.{name}")
    assert Path(module.__file__).resolve() == DEPLOY.joinpath(*name.split(".")).with_suffix(".py")

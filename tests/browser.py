"""Screenshots of web pages with a real headless browser, for the tests: the functions of
``deploy/local/browser.py`` (a plain module beside the scripts that use it too), importable as ``browser``.

    from browser import find_chromium, screenshot
    if find_chromium() is None: pytest.skip(...)
    screenshot("http://127.0.0.1:8080", tmp_path / "page.png", 1280, 800, wait_ms=8000)
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_PATH = Path(__file__).resolve().parents[1] / "deploy" / "local" / "browser.py"
_NAME = "navcrafter_deploy_browser"

if _NAME not in sys.modules:
    _spec = importlib.util.spec_from_file_location(_NAME, _PATH)
    _module = importlib.util.module_from_spec(_spec)
    sys.modules[_NAME] = _module
    _spec.loader.exec_module(_module)
_impl = sys.modules[_NAME]

CANDIDATES = _impl.CANDIDATES
find_chromium = _impl.find_chromium
screenshot = _impl.screenshot
screenshot_and_dom = _impl.screenshot_and_dom

__all__ = ["CANDIDATES", "find_chromium", "screenshot", "screenshot_and_dom"]

"""Screenshots of web pages with a real headless browser, for the tests: ``deploy/local/browser.py`` (the module
the deploy scripts use too), importable as ``browser``.

    from browser import find_chromium, screenshot
    if find_chromium() is None: pytest.skip(...)
    screenshot("http://127.0.0.1:8080", tmp_path / "page.png", 1280, 800, wait_ms=8000)
"""

from __future__ import annotations

from deploy.local.browser import CANDIDATES, find_chromium, screenshot, screenshot_and_dom

__all__ = ["CANDIDATES", "find_chromium", "screenshot", "screenshot_and_dom"]

"""Local helper scripts (``browser``: headless-Chromium screenshots; ``dashboard_screenshot``), importable as
``deploy.local.<name>`` from the repository root (tests put it on the path) and run as scripts."""

"""Screenshots of web pages with a real headless browser (Debian's ``chromium``; ``deploy/local/setup.sh test``
installs it). General: any URL (the 3D viewer, a Prefect dashboard...). WebGL runs on the CPU (SwiftShader).

A plain module, no navcrafter import: ``deploy/local/dashboard_screenshot.py`` loads it beside itself and the
tests through ``tests/browser.py``:

    from browser import find_chromium, screenshot
    if find_chromium() is None: pytest.skip(...)
    screenshot("http://127.0.0.1:8080", tmp_path / "page.png", 1280, 800, wait_ms=8000)
    png, dom = screenshot_and_dom(url, tmp_path / "page.png")  # also the page's DOM as rendered (SPAs)
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome executable: ``$CHROMIUM`` if set, else the first on PATH; None if none."""
    env = os.environ.get("CHROMIUM")
    if env:
        return env if shutil.which(env) else None
    return next((p for p in map(shutil.which, CANDIDATES) if p), None)


def _chromium(url: str, out_png: str | os.PathLike, width: int, height: int, wait_ms: int, extra_args: tuple[str, ...],
              timeout_s: float, dump_dom: bool) -> tuple[Path, str]:
    exe = find_chromium()
    if exe is None:
        raise RuntimeError("no chromium found: apt-get install chromium (or set CHROMIUM=/path/to/chrome)")
    out = Path(out_png).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        args = [exe, "--headless", f"--user-data-dir={profile}", "--hide-scrollbars", "--mute-audio",
                "--no-first-run", "--no-default-browser-check", "--disable-extensions",
                # WebGL on the CPU: ANGLE on SwiftShader (no GPU, no display)
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                f"--window-size={int(width)},{int(height)}", f"--virtual-time-budget={int(wait_ms)}",
                f"--screenshot={out}", *(("--dump-dom",) if dump_dom else ()), *extra_args]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            args.append("--no-sandbox")  # Chromium refuses to run as root with its sandbox
        args.append(url)
        proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s)
    if not out.is_file() or out.stat().st_size == 0:
        raise RuntimeError(f"chromium wrote no screenshot of {url} (exit {proc.returncode}):\n"
                           f"{(proc.stdout + proc.stderr)[-3000:]}")
    return out, (proc.stdout if dump_dom else "")


def screenshot(url: str, out_png: str | os.PathLike, width: int = 1280, height: int = 800, wait_ms: int = 8000,
               *, extra_args: tuple[str, ...] = (), timeout_s: float = 90.0) -> Path:
    """Load ``url`` in headless Chromium and save a ``width`` x ``height`` PNG to ``out_png``.

    ``wait_ms`` is Chromium's virtual-time budget: the page's timers and network run that long (in virtual time,
    usually much less wall time) before the shot. Raises RuntimeError (with Chromium's output) when no PNG came."""
    return _chromium(url, out_png, width, height, wait_ms, extra_args, timeout_s, dump_dom=False)[0]


def screenshot_and_dom(url: str, out_png: str | os.PathLike, width: int = 1280, height: int = 800,
                       wait_ms: int = 8000, *, extra_args: tuple[str, ...] = (),
                       timeout_s: float = 90.0) -> tuple[Path, str]:
    """``screenshot`` that also returns the page's DOM (HTML) as it was at the shot, from the same page load:
    what a JavaScript app (the Prefect UI) had rendered by then, to check the shot shows what it should."""
    return _chromium(url, out_png, width, height, wait_ms, extra_args, timeout_s, dump_dom=True)

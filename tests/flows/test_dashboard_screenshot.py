"""The Prefect dashboard as a user sees it: ``deploy/local/dashboard_screenshot.py`` starts a real
``prefect server start``, explores one tiny demo scene against it and screenshots the scene's flow-run page
(artifacts tab) in headless Chromium; the page must have rendered the run's artifacts and not be blank.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from browser import find_chromium
from PIL import Image

SCRIPT = Path(__file__).resolve().parents[2] / "deploy" / "local" / "dashboard_screenshot.py"


def _script():
    from deploy.local import dashboard_screenshot

    return dashboard_screenshot


def test_blank_pages_are_recognised(tmp_path):
    image_problem = _script().image_problem
    blank = tmp_path / "blank.png"
    Image.new("RGB", (200, 100), (37, 38, 44)).save(blank)
    assert "blank" in image_problem(blank)
    noise = tmp_path / "noise.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (100, 200, 3), dtype=np.uint8)).save(noise)
    assert image_problem(noise) is None


@pytest.mark.system  # starts a Prefect server, a flow run and a browser
@pytest.mark.timeout(300)
def test_dashboard_screenshot_shows_the_scene_run_and_its_artifacts(tmp_path):
    if find_chromium() is None:
        pytest.skip("chromium is not installed (bash deploy/local/setup.sh test installs it)")
    out = tmp_path / "dashboard.png"
    res = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), "--wait-ms", "10000", "--json"],
                         capture_output=True, text=True, timeout=280)
    assert res.returncode == 0, res.stdout + res.stderr
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    name = summary["flow_run_name"]
    assert name.startswith("scene-") and summary["state"] == "COMPLETED"
    short = name.removeprefix("scene-")
    assert {f"progress-{short}", f"dashboard-{short}", f"scene-{short}", f"plan-{short}-1"} <= set(summary["artifacts"])
    url = summary["shots"]["flow_run"]["url"]
    assert url == f"{summary['ui_url']}/v2/runs/flow-run/{summary['flow_run_id']}?tab=Artifacts"
    assert summary["shots"]["flow_run"]["path"] == str(out) and 10_000 < out.stat().st_size < 500_000
    px = np.asarray(Image.open(out).convert("RGB"))
    assert px.shape == (1000, 1400, 3)
    colours, counts = np.unique(px.reshape(-1, 3), axis=0, return_counts=True)
    assert px.std() > 20 and len(colours) > 100, (px.std(), len(colours))  # a rendered page, not a blank one
    assert counts.max() / counts.sum() < 0.9  # not one background colour with a few lines on it

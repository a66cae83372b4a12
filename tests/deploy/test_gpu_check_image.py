"""The GPU check on a stand-in for the bare, air-gapped CUDA image it will run on (deploy/gpu, issue 29).

The stand-in (``deploy/gpu/emulate_image.py``): a venv of this machine's Python 3.11 (the image runs 3.12.3) holding
the image's packages that this machine has, linked from the project's venv (CPU builds: torch 2.13.0+cpu where the
image has 2.11.0+cu130; numpy, onnx, onnxruntime, tokenizers the nearest here), huggingface_hub 1.33.0 /
transformers 5.17.0 / onnx-ir 1.0.0 at the image's exact versions, and nothing else: no diffusers, pydantic,
gsplat, zarr, prefect, open3d, pycolmap, plyfile, navcrafter. The carried wheels are ``deploy/gpu/wheels.txt``'s
pins, fetched by ``fetch_wheels.sh`` for this Python (pydantic_core is the one binary wheel: its cp311 build,
hash-pinned beside the cp312 one). Building it all takes seconds (links, pip's cache), once per module.

Then ``run_check.sh`` runs as on the node (its wheel check, the offline install into a temporary target, navcrafter
made importable from the tree, the preflight, the check) with ``--device cpu --dry-run --inline`` (one process for
the items: the subprocess-per-item plumbing is tests/benchmarks/test_gpu_check.py's), and every item must report a
status and results.json / results.md must be written. Without run_check.sh the same check must report failed
imports as such, and still write its results.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[2]
GPU = ROOT / "deploy" / "gpu"
NOT_ON_IMAGE = ("diffusers", "pydantic", "pydantic_core", "gsplat", "zarr", "prefect", "open3d", "pycolmap", "plyfile",
                "navcrafter")


def _gpu_check():
    from benchmarks import gpu_check

    return gpu_check


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    base = tmp_path_factory.mktemp("gpu-image")
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, str(GPU / "emulate_image.py"), str(base / "venv")], capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    report = json.loads(p.stdout)
    t1 = time.perf_counter()
    wheels = base / "wheels"
    env = os.environ | {"PYVER": f"{sys.version_info.major}.{sys.version_info.minor}", "PYTHON": sys.executable}
    p = subprocess.run(["bash", str(GPU / "fetch_wheels.sh"), str(wheels)], env=env, capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    t2 = time.perf_counter()
    print(f"stand-in venv {t1 - t0:.1f} s, wheels {t2 - t1:.1f} s; {report['python']}, {report['linked']} image "
          f"packages, versions that differ: {report['versions_differ']}")
    return {"python": base / "venv" / "bin" / "python", "wheels": wheels, "report": report, "base": base}


def test_the_stand_in_holds_the_image_and_nothing_else(image):
    probe = ("import importlib.util, json; from importlib.metadata import version; "
             f"print(json.dumps({{'absent': [m for m in {list(NOT_ON_IMAGE)!r} if importlib.util.find_spec(m)], "
             "'hub': version('huggingface_hub'), 'torch': version('torch')}))")
    p = subprocess.run([str(image["python"]), "-c", probe], capture_output=True, text=True, cwd="/", timeout=120)
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)
    assert got["absent"] == [] and got["hub"] == "1.33.0" and got["torch"].startswith("2.")
    assert len(list(image["wheels"].glob("*.whl"))) == sum(
        1 for ln in (GPU / "wheels.txt").read_text().splitlines() if ln[:1].isalpha())


def test_without_run_check_every_item_reports_its_failed_import(image, tmp_path):
    """The node as the issue found it (the tree copied, nothing installed): no item may crash the run or say a
    module 'does not exist yet'; each says which import failed, and the results are written."""
    out = tmp_path / "out"
    cmd = [str(image["python"]), str(ROOT / "benchmarks" / "gpu_check.py"), "--out", str(out), "--device", "cpu",
           "--dry-run", "--inline"]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    items = json.loads((out / "results.json").read_text())["items"]
    assert items["training"]["status"] == "skipped"  # CUDA-only, before any import
    for name, it in items.items():
        if name != "training":
            assert it["status"] == "import error" and it["missing_module"] == "navcrafter", (name, it)
            assert "run_check.sh" in it["reason"]
    md = (out / "results.md").read_text()
    assert "does not exist" not in md and "| dit | import error |" in md
    p = subprocess.run(cmd[:2] + ["--preflight", "--device", "cpu", "--dry-run"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=300)
    assert p.returncode == 3 and "FAIL import navcrafter.models" in p.stderr


def test_run_check_dry_run_on_the_image(image, tmp_path):
    out, cache = tmp_path / "out", tmp_path / "cache"
    env = os.environ | {"PYTHON": str(image["python"]), "WHEELS": str(image["wheels"]), "OUT": str(out),
                        "NAVCRAFTER_GPU_CACHE": str(cache)}
    env.pop("PYTHONPATH", None)
    t0 = time.perf_counter()
    p = subprocess.run(["bash", str(GPU / "run_check.sh"), "--device", "cpu", "--dry-run", "--inline"], env=env,
                       capture_output=True, text=True, cwd=tmp_path, timeout=900)
    print(f"run_check.sh --device cpu --dry-run --inline: {time.perf_counter() - t0:.1f} s")
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    assert {f.name for f in out.iterdir()} <= {"results.json", "results.md", "preflight.json", "run_check.log",
                                               "gsplat-build.json", "gsplat-build.log"}  # $OUT: few files, no tree
    report = json.loads((out / "results.json").read_text())
    assert report["dry_run"] and not report["running"]
    items = report["items"]
    gc = _gpu_check()
    assert list(items) == list(gc.ITEMS)
    assert all(it.get("status") for it in items.values())
    assert {n: it["status"] for n, it in items.items()} == {
        "gsplat": "skipped", "dit": "ok", "fun-camera": "ok", "vggt": "ok", "moge": "ok", "difix": "ok",
        "training": "skipped", "scene": "ok"}, {n: (it["status"], it.get("reason") or it.get("error"))
                                                 for n, it in items.items()}
    assert "CUDA" in items["gsplat"]["reason"]
    assert items["scene"]["composed"]["iterations"] == 3
    md = (out / "results.md").read_text()
    assert gc.DRY_RUN_LABEL in md and all(f"| {n} | " in md for n in gc.ITEMS)
    assert "What did not run here" in md
    pf = json.loads((out / "preflight.json").read_text())
    checks = {c["check"]: c for c in pf["checks"]}
    assert pf["ok"] and checks["import navcrafter.models"]["ok"]
    # the carried wheels, not anything of this machine's, and gsplat installed but not built
    assert str(cache / "site") in checks["import diffusers"]["detail"]
    assert str(cache / "site") in checks["import pydantic"]["detail"]
    assert pf["gsplat"]["installed"] and not pf["gsplat"]["built"]


def test_run_check_refuses_a_wheel_that_is_not_pinned(image, tmp_path):
    wheels = tmp_path / "wheels"
    shutil.copytree(image["wheels"], wheels)
    (wheels / "zarr-3.1.6-py3-none-any.whl").write_bytes(b"not the pinned wheel")
    env = os.environ | {"PYTHON": str(image["python"]), "WHEELS": str(wheels), "OUT": str(tmp_path / "out"),
                        "NAVCRAFTER_GPU_CACHE": str(tmp_path / "cache")}
    p = subprocess.run(["bash", str(GPU / "run_check.sh"), "--device", "cpu", "--dry-run"], env=env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode != 0 and "zarr-3.1.6-py3-none-any.whl is not pinned in wheels.txt" in p.stdout
    assert not (tmp_path / "cache" / "site").exists()

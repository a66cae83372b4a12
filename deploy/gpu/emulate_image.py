"""A stand-in for the GPU node's Python on a CPU machine: a virtual environment holding the image's packages
(``image-packages.txt``) and nothing else, for the test that replays ``run_check.sh`` here.

    .venv/bin/python deploy/gpu/emulate_image.py DEST          # prints a JSON report of what it linked

It is built from the environment that runs it (the project's venv): a bare venv of the same interpreter
(``--without-pip``, no system site-packages), into whose site-packages every distribution of the image that this
environment has is *symlinked* (its top-level files and folders from its RECORD, its dist-info included), so the
venv costs a second and no download. What that means, and what the report lists:

* versions are this environment's (CPU builds: torch 2.13.0+cpu, not the image's 2.11.0+cu130; numpy, onnxruntime,
  transformers, typer likewise the nearest this machine installs), under Python 3.11 rather than 3.12.3;
* the image's packages this environment lacks (jax, cupy, opencv, torchvision, pandas, the nvidia-* runtime, ...)
  are missing here: none is on the check's import path (the test fails if one were needed: the check would report
  the failed import), but e.g. transformers behaves as without torchvision;
* nothing outside the image travels in: not the project's own dependencies (diffusers, pydantic, zarr, prefect,
  open3d, pycolmap, plyfile), not navcrafter itself. ``run_check.sh`` brings the carried wheels and navcrafter.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

HERE = Path(__file__).resolve().parent
# never linked, whatever the image list says: the gap the carried wheels fill, and what the node must not have
# pure-Python packages whose version here would change the import path (huggingface_hub 2.x needs httpx2, which the
# image lacks; transformers follows the hub): installed at the image's exact versions (pip, --no-deps: their
# dependencies are linked like the rest) instead of linked
EXACT = {"huggingface-hub": "1.33.0", "transformers": "5.17.0", "onnx-ir": "1.0.0"}
NOT_ON_IMAGE = ("diffusers", "pydantic", "pydantic-core", "gsplat", "prefect", "zarr", "open3d", "pycolmap", "plyfile",
                "onnxruntime-gpu", "navcrafter")


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def image_packages(path: Path = HERE / "image-packages.txt") -> dict[str, str | None]:
    """name -> version on the image (None where the inventory gives none)."""
    out: dict[str, str | None] = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, _, version = line.partition("==")
            out[norm(name)] = version or None
    return out


def _top_levels(dist: metadata.Distribution) -> set[str]:
    tops = set()
    for f in dist.files or ():
        first = f.parts[0]
        if first in ("..", "", "__pycache__") or first.endswith(".pth") and first.startswith("__editable__"):
            continue  # console scripts (../../bin), editable installs
        tops.add(first)
    return tops


def build(dest: Path) -> dict:
    want = image_packages()
    dest = Path(dest)
    if not (dest / "pyvenv.cfg").is_file():
        subprocess.run([getattr(sys, "_base_executable", sys.executable), "-m", "venv", "--without-pip", str(dest)],
                       check=True)
    py = dest / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    owners: dict[str, set[str]] = {}  # top-level entry -> distributions owning files under it
    dists: dict[str, metadata.Distribution] = {}
    for d in metadata.distributions():
        name = norm(d.metadata["Name"])
        dists.setdefault(name, d)
        for top in _top_levels(d):
            owners.setdefault(top, set()).add(name)
    linked, missing, shared = {}, [], []
    for name, image_version in sorted(want.items()):
        d = dists.get(name)
        if d is None or name in NOT_ON_IMAGE:
            missing.append(name)
            continue
        if name in EXACT:
            continue
        root = Path(d.locate_file(""))
        for top in sorted(_top_levels(d)):
            src, dst = root / top, site / top
            if not src.exists() or dst.is_symlink() or dst.exists():
                continue
            if owners[top] - set(want) - {name}:  # a namespace folder shared with a package not on the image
                shared.append(f"{top} ({name})")
                dst.mkdir(parents=True, exist_ok=True)
                for sub in {Path(*f.parts[:2]) for f in d.files or () if f.parts[0] == top and len(f.parts) > 1}:
                    if not (site / sub).exists():
                        os.symlink(root / sub, site / sub)
                continue
            os.symlink(src, dst)
        linked[name] = {"here": d.version, "image": image_version}
    pins = [f"{n}=={v}" for n, v in EXACT.items()]
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-compile", "--disable-pip-version-check",
                    *pins], check=True)
    linked.update({n: {"here": v, "image": want.get(n), "installed": "exact (pip)"} for n, v in EXACT.items()})
    present = {norm(p.name.split("-")[0]) for p in site.glob("*.dist-info")}
    leaked = sorted(present & {norm(n) for n in NOT_ON_IMAGE})
    if leaked:
        raise RuntimeError(f"the emulated image holds {leaked}, which the real one lacks")
    differ = {n: v for n, v in linked.items() if v["image"] and v["image"] != v["here"].split("+")[0]}
    return {"venv": str(dest), "python": subprocess.run([str(py), "-V"], capture_output=True, text=True).stdout.strip(),
            "image_python": "3.12.3", "linked": len(linked), "missing_here": missing,
            "versions_differ": differ, "shared_namespace_folders": shared}


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} DEST")
    print(json.dumps(build(Path(sys.argv[1])), indent=1))

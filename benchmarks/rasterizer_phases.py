"""Where the compiled CPU rasterizer's time goes: single-thread process CPU time per kernel (phase) of one
forward + backward at 100k Gaussians x 256x256 (``benchmarks/rasterizer.py``'s scene), RGB and SH3 + RGB+ED,
optionally beside the kernels of another git revision in the same process (the two alternate call by call).

    python benchmarks/rasterizer_phases.py                          # this tree
    python benchmarks/rasterizer_phases.py --baseline e30e0c0       # that revision's kernels, then this tree's
    python benchmarks/rasterizer_phases.py --threads 2 --wall       # wall time per phase on 2 threads
    NUMBA_CACHE_DIR=$(mktemp -d) python benchmarks/rasterizer_phases.py --in-process   # a first run's kernels

Process CPU time (``time.process_time``) on one numba thread and one torch thread is the stable figure on a
shared machine (wall time counts other processes' turns). Each kernel the autograd glue calls through the
``cpu_kernels`` module is timed; "Python / PyTorch" is the rest of the forward + backward (conversions, the
render modes' tensor ops, the loss and autograd). The baseline is ``git show REV:`` of ``cpu_kernels.py``,
``cpu_rasterize.py`` and ``rasterize.py`` (the render modes around the kernels) written to a directory per commit
under the system's temporary directory (kept: numba caches the baseline's kernels there) and imported from there
(the rest of the package is this tree's). **Both versions
run cache-loaded kernels**: when a kernel had to be compiled in this process (no cache yet, or a changed source),
the script runs itself again after the warm-up (once; ``benchmarks.rasterizer.rerun_if_compiled``: code compiled
in the timing process runs slower than the same code loaded from numba's cache).
Medians over ``--repeats`` after two warm-up calls; the load average is printed before and after.
``--threads N --wall`` times the phases in wall time on N threads instead (what the benchmark's goal counts:
serial phases and thread imbalance show there; the Python / PyTorch rows are split into forward and backward).
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: the repository root makes the benchmarks package importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as benchmarks/rasterizer.py: before torch loads OpenMP

import torch  # noqa: E402

from benchmarks.rasterizer import compiled_here, make_scene, rerun_if_compiled  # noqa: E402
from navcrafter.models.gaussians import cpu_kernels, cpu_rasterize  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KERNELS = "models/gaussians/cpu_kernels.py"
GLUE = "models/gaussians/cpu_rasterize.py"
MODES = "models/gaussians/rasterize.py"
IMPORT_LINE = "from navcrafter.models.gaussians import cpu_kernels as K"
MODES_IMPORT = "from navcrafter.models.gaussians.rasterize import"


def load_baseline(rev: str, tmp: Path):
    """The (kernels, glue) modules of git revision ``rev``, imported from files under ``tmp`` (written there
    unless they already hold the same text: rewriting them would invalidate numba's cache of them); the glue
    renders through that revision's ``rasterize.py`` (its render modes around the kernels)."""
    kernels, glue, modes = (subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True,
                                           capture_output=True, text=True).stdout for path in (KERNELS, GLUE, MODES))
    for line in (IMPORT_LINE, MODES_IMPORT):
        if line not in glue:
            raise SystemExit(f"{rev}:{GLUE} does not import {line!r}; cannot rebind it")
    glue = glue.replace(IMPORT_LINE, "import baseline_cpu_kernels as K").replace(MODES_IMPORT,
                                                                                "from baseline_rasterize import")
    for name, text in (("baseline_cpu_kernels.py", kernels), ("baseline_rasterize.py", modes),
                       ("baseline_cpu_rasterize.py", glue)):
        if not (tmp / name).exists() or (tmp / name).read_text() != text:
            (tmp / name).write_text(text)
    sys.path.insert(0, str(tmp))
    mods = []
    for name in ("baseline_cpu_kernels", "baseline_rasterize", "baseline_cpu_rasterize"):
        spec = importlib.util.spec_from_file_location(name, tmp / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
        mods.append(mod)
    return mods[0], mods[2]


CLOCK = time.process_time  # --wall: time.perf_counter


def baseline_dir(rev: str) -> Path:
    """A directory per commit for the baseline's modules and numba's cache of them (kept between runs)."""
    sha = subprocess.run(["git", "rev-parse", f"{rev}^{{commit}}"], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip()
    path = Path(tempfile.gettempdir()) / "navcrafter-rasterizer-baselines" / sha
    path.mkdir(parents=True, exist_ok=True)
    return path


def instrument(kernels, acc: dict) -> None:
    """Replace every compiled kernel (and older revisions' ``depth_keys``) on the module by a wrapper adding its time
    (``CLOCK``) to ``acc[name]``; the glue calls them as ``K.name(...)``, so it calls the wrappers."""
    for name in dir(kernels):
        fn = getattr(kernels, name)
        if name.startswith("_") or not (hasattr(fn, "py_func") or name == "depth_keys"):
            continue

        def timed(*args, _fn=fn, _name=name):
            c0 = CLOCK()
            out = _fn(*args)
            acc[_name] = acc.get(_name, 0.0) + CLOCK() - c0
            return out

        setattr(kernels, name, functools.wraps(fn)(timed))


def run(glue, acc: dict, scene: dict, sh: int | None, mode: str, repeats: int) -> list[dict]:
    rows = []
    for _ in range(repeats):
        params = [p.clone().requires_grad_() for p in scene["params"]]
        weights = torch.rand((1, scene["size"], scene["size"], 3 if sh is None else 4),
                             generator=torch.Generator().manual_seed(1))
        acc.clear()
        c0 = CLOCK()
        out, alpha, _ = glue.rasterization(*params, scene["viewmats"], scene["Ks"], scene["size"], scene["size"],
                                           sh_degree=sh, render_mode=mode)
        fwd = CLOCK() - c0
        fwd_k = sum(acc.values())
        ((out * weights).sum() + alpha.sum()).backward()
        total = CLOCK() - c0
        rows.append({**acc, "Python / PyTorch, forward": fwd - fwd_k,
                     "Python / PyTorch, backward": total - fwd - (sum(acc.values()) - fwd_k), "total": total})
    return rows


def medians(rows: list[dict]) -> dict:
    return {k: statistics.median(r.get(k, 0.0) for r in rows) * 1000 for k in rows[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", help="a git revision whose kernels run beside this tree's")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=1, help="numba and torch threads (default 1)")
    ap.add_argument("--wall", action="store_true", help="wall time (perf_counter) instead of process CPU time")
    ap.add_argument("--in-process", action="store_true",
                    help="time the kernels even when compiled in this process (a first run's cost) instead of "
                         "running again with them cached")
    args = ap.parse_args()
    global CLOCK
    if args.wall:
        CLOCK = time.perf_counter
    torch.set_num_threads(args.threads)
    cpu_rasterize.set_threads(args.threads)
    versions = {}
    if args.baseline:
        versions[args.baseline] = load_baseline(args.baseline, baseline_dir(args.baseline))
    versions["this tree"] = (cpu_kernels, cpu_rasterize)
    for sh, mode in ((None, "RGB"), (3, "RGB+ED")):  # compile or load every kernel the timed calls use
        small = make_scene(2000, 64, sh)
        for _, glue in versions.values():
            run(glue, {}, small, sh, mode, 1)
    if args.in_process:
        print(f"compiled in this process: {({name: compiled_here(k) for name, (k, _) in versions.items()})}")
    else:
        rerun_if_compiled({name: kernels for name, (kernels, _) in versions.items()})
    accs = {name: {} for name in versions}
    for name, (kernels, _) in versions.items():
        instrument(kernels, accs[name])
    print(f"load average before: {os.getloadavg()}", flush=True)
    for sh, mode in ((None, "RGB"), (3, "RGB+ED")):
        scene = make_scene(args.gaussians, args.size, sh)
        res = {}
        for name, (_, glue) in versions.items():
            run(glue, accs[name], scene, sh, mode, 2)  # warm-up (compiles or loads the kernels)
        rows = {name: [] for name in versions}
        for _ in range(args.repeats):  # the versions alternate call by call: a change in load hits both
            for name, (_, glue) in versions.items():
                rows[name] += run(glue, accs[name], scene, sh, mode, 1)
        res = {name: medians(r) for name, r in rows.items()}
        keys = list(dict.fromkeys(k for r in res.values() for k in r if k != "total")) + ["total"]
        kind = "RGB" if sh is None else f"SH{sh}, {mode}"
        title = f"{args.gaussians // 1000}k Gaussians x {args.size}², {kind}"
        clock = "wall time" if args.wall else "process CPU"
        print(f"\n{title}: {clock} on {args.threads} thread(s) per forward + backward, "
              f"median of {args.repeats} (ms)")
        print(f"| phase | {' | '.join(res)} |")
        print("|---|" + "---:|" * len(res))
        for k in keys:
            print(f"| {k} | " + " | ".join(f"{r.get(k, 0.0):.1f}" for r in res.values()) + " |")
    print(f"\nload average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()

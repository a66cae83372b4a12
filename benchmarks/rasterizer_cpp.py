"""The C++ compositing kernels (models/gaussians/cpu_ext.py) against numba's, side by side in one process.

Two measures at 100k Gaussians x 256² (benchmarks/rasterizer.py's scene), RGB and SH3 + RGB+ED, float32:
(1) the two compositing kernels alone on one call's captured arrays, the versions alternating call by call
(process CPU time on one thread, or wall time on ``--threads``); their outputs compared; (2) the whole
forward + backward call with ``cpu_rasterize.set_kernels`` alternating between ``numba`` and ``cpp`` (wall time
on ``--threads``). Prints medians and the load average; writes ``--out``/results.json when given.

    python benchmarks/rasterizer_cpp.py --repeats 15 [--threads 2] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: the repository root makes the benchmarks package importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as benchmarks/rasterizer.py: before torch loads OpenMP

import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.rasterizer import make_scene  # noqa: E402
from navcrafter.models.gaussians import cpu_ext, cpu_kernels, cpu_rasterize  # noqa: E402
from navcrafter.models.gaussians.cpu_rasterize import rasterization  # noqa: E402


def capture(scene: dict, sh: int | None, mode: str) -> dict:
    """One call's compositing arguments (numba kernels), and its outputs."""
    got: dict = {}
    fw, bw = cpu_kernels.composite_forward, cpu_kernels.composite_backward

    def cf(*a):
        got["fwd"] = [x.copy() if isinstance(x, np.ndarray) else x for x in a]
        fw(*a)
        got["fwd_out"] = [x.copy() if isinstance(x, np.ndarray) else x for x in a]

    def cb(*a):
        got["bwd"] = [x.copy() if isinstance(x, np.ndarray) else x for x in a]
        bw(*a)
        got["bwd_out"] = a[-1].copy()

    cpu_kernels.composite_forward, cpu_kernels.composite_backward = cf, cb
    try:
        cpu_rasterize.set_kernels("numba")
        params = [p.clone().requires_grad_() for p in scene["params"]]
        size = scene["size"]
        out, alpha, _ = rasterization(*params, scene["viewmats"], scene["Ks"], size, size, sh_degree=sh,
                                      render_mode=mode)
        w = torch.rand(out.shape, generator=torch.Generator().manual_seed(1))
        ((out * w).sum() + alpha.sum()).backward()
    finally:
        cpu_kernels.composite_forward, cpu_kernels.composite_backward = fw, bw
    return got


def clock(wall: bool) -> float:
    return time.perf_counter() if wall else time.process_time()


def kernels(got: dict, repeats: int, threads: int, wall: bool) -> dict:
    fa, ba = got["fwd"], got["bwd"]
    names = ("numba", "cpp7", "cpp3")
    res: dict = {f"{n}_{p}": [] for n in names for p in ("fwd", "bwd")}
    outs = {}
    for _ in range(repeats):
        for name in names:
            if name != "numba":
                cpu_ext.set_variant(int(name[3:] or 0))
            f = [x.copy() if isinstance(x, np.ndarray) else x for x in fa]
            b = [x.copy() if isinstance(x, np.ndarray) else x for x in ba]
            t0 = clock(wall)
            if name == "numba":
                cpu_kernels.composite_forward(*f)
            else:
                cpu_ext.composite_forward(*f, threads)
            t1 = clock(wall)
            if name == "numba":
                cpu_kernels.composite_backward(*b)
            else:
                cpu_ext.composite_backward(*b, threads)
            t2 = clock(wall)
            res[f"{name}_fwd"].append((t1 - t0) * 1e3)
            res[f"{name}_bwd"].append((t2 - t1) * 1e3)
            outs[name] = (f, b)
    med = {k: statistics.median(v) for k, v in res.items()}
    (fn, bn), (fc, bc) = outs["numba"], outs[names[1]]
    # forward outputs: render (9), t_final (10), pend (12), pix/pes/pts (13-15)
    cmp = {}
    for i, nm in ((9, "render"), (10, "t_final")):
        cmp[f"{nm}_max_abs"] = float(np.abs(fn[i] - fc[i]).max())
    cmp["pend_equal"] = bool(np.array_equal(fn[12], fc[12]))
    cmp["pix_equal"] = bool(np.array_equal(fn[13], fc[13]))
    cmp["pes_max_rel"] = float((np.abs(fn[14] - fc[14]) / np.maximum(np.abs(fn[14]), 1e-30)).max())
    s_n, s_c = bn[-1], bc[-1]
    cmp["slots_max_abs_over_max"] = float(np.abs(s_n - s_c).max() / np.abs(s_n).max())
    return {"median_ms": med, "compare": cmp}


def whole(scene: dict, sh: int | None, mode: str, repeats: int) -> dict:
    size = scene["size"]
    w = None
    t: dict = {"numba": [], "cpp": []}
    for _ in range(repeats):
        for name in ("numba", "cpp"):
            cpu_rasterize.set_kernels(name)
            params = [p.clone().requires_grad_() for p in scene["params"]]
            t0 = time.perf_counter()
            out, alpha, _ = rasterization(*params, scene["viewmats"], scene["Ks"], size, size, sh_degree=sh,
                                          render_mode=mode)
            if w is None:
                w = torch.rand(out.shape, generator=torch.Generator().manual_seed(1))
            ((out * w).sum() + alpha.sum()).backward()
            t[name].append((time.perf_counter() - t0) * 1e3)
    return {k: statistics.median(v) for k, v in t.items()} | {f"{k}_min": min(v) for k, v in t.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--skip-whole", action="store_true")
    ap.add_argument("--out")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    torch.set_num_threads(args.threads)
    report = {"threads": args.threads, "load_before": os.getloadavg(), "cases": {}}
    for label, sh, mode in (("RGB", None, "RGB"), ("SH3 + RGB+ED", 3, "RGB+ED")):
        scene = make_scene(args.gaussians, args.size, sh)
        got = capture(scene, sh, mode)
        k = kernels(got, args.repeats, args.threads, wall=args.threads > 1)
        case = {"kernels": k}
        if not args.skip_whole:
            case["whole_wall_ms"] = whole(scene, sh, mode, args.repeats)
        report["cases"][label] = case
        print(label, json.dumps(case, indent=1), flush=True)
    report["load_after"] = os.getloadavg()
    print("load", report["load_before"], "->", report["load_after"])
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "results.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()

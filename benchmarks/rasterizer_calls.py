"""Per call of the compiled CPU rasterizer (forward + backward at 100k Gaussians x 256², one camera, the scene of
``benchmarks/rasterizer.py``): wall time, process CPU time, context switches and the machine's idle time, to tell
a call that *waits* (the same CPU time, more wall time: a thread woken late) from one that works more.

    python benchmarks/rasterizer_calls.py --case sh3 --calls 40
    NUMBA_THREADING_LAYER=workqueue python benchmarks/rasterizer_calls.py --case sh3   # another threading layer

Prints one line per call after two warm-up calls, then the median, 90th percentile and maximum wall time, and the
threading layer numba used (raster31 in ``models/gaussians/README.md``). Not a timed test; nothing is written.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: the repository root makes the benchmarks package importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as benchmarks/rasterizer.py: before torch loads OpenMP

import numba  # noqa: E402
import torch  # noqa: E402

from benchmarks.rasterizer import make_scene  # noqa: E402
from navcrafter.models.gaussians import cpu_rasterize  # noqa: E402


def _cpu_jiffies() -> tuple[int, int]:
    """(idle, steal) of all CPUs from /proc/stat (0, 0 where there is none)."""
    try:
        fields = [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return 0, 0
    return fields[3], fields[7] if len(fields) > 7 else 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=("rgb", "sh3"), default="sh3", help="RGB, or SH degree 3 with RGB+ED")
    ap.add_argument("--calls", type=int, default=40)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cpu_rasterize.set_threads(args.threads)
    sh = None if args.case == "rgb" else 3
    mode = "RGB" if sh is None else "RGB+ED"
    scene = make_scene(100_000, 256, sh)
    weights = None
    walls = []
    for i in range(args.calls + 2):
        params = [p.clone().requires_grad_() for p in scene["params"]]
        r0, j0 = resource.getrusage(resource.RUSAGE_SELF), _cpu_jiffies()
        c0, t0 = time.process_time(), time.perf_counter()
        out, alpha, _ = cpu_rasterize.rasterization(*params, scene["viewmats"], scene["Ks"], 256, 256,
                                                    sh_degree=sh, render_mode=mode)
        if weights is None:
            weights = torch.rand(out.shape, generator=torch.Generator().manual_seed(1))
        ((out * weights).sum() + alpha.sum()).backward()
        wall, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        r1, j1 = resource.getrusage(resource.RUSAGE_SELF), _cpu_jiffies()
        if i < 2:
            continue
        walls.append(wall)
        print(f"wall {wall:5.1f} ms  cpu {cpu:5.1f} ms  voluntary switches {r1.ru_nvcsw - r0.ru_nvcsw:4d}  "
              f"involuntary {r1.ru_nivcsw - r0.ru_nivcsw:4d}  idle {j1[0] - j0[0]} / steal {j1[1] - j0[1]} jiffies")
    walls.sort()
    print(f"{args.case}, {args.threads} threads, numba layer {numba.threading_layer()}: median "
          f"{statistics.median(walls):.1f} ms, p90 {walls[int(0.9 * len(walls))]:.1f}, max {walls[-1]:.1f}, "
          f"min {walls[0]:.1f}")


if __name__ == "__main__":
    main()

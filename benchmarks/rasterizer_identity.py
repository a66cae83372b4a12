"""Are this tree's compiled CPU kernels' outputs bit-identical to a git revision's? Renders, alphas and every
gradient (means, quaternions or covariances, scales, opacities, colours, ``means2d``) of one forward + backward,
both versions on the same inputs in one process, on 1 and 2 threads.

    python benchmarks/rasterizer_identity.py --baseline 7676402

Scenes: ``benchmarks/rasterizer.py``'s (100k x 256² RGB and SH3 + RGB+ED; 50k x 128² SH3; 10k x 128² RGB+D),
the ``covars`` input path and ``antialiased`` mode (compensation gradients) at 10k x 128², and float64 at 10k x
128² SH3 + RGB+ED. Prints, per scene and thread count, each tensor as ``equal`` or its largest absolute difference
relative to the tensor's largest magnitude; exits 1 when a float32 tensor differs (float64 differences are
reported, not failed: fast-math may reorder float64 sums). The baseline is loaded as in ``rasterizer_phases.py``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

if __package__ in (None, ""):  # run as a script: the repository root makes the benchmarks package importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from benchmarks.rasterizer import make_scene  # noqa: E402
from benchmarks.rasterizer_phases import load_baseline  # noqa: E402
from navcrafter.models.gaussians import cpu_rasterize  # noqa: E402

# (name, Gaussians, size, SH degree, render mode, dtype, extra keyword arguments)
SCENES = [
    ("100k x 256² RGB", 100_000, 256, None, "RGB", torch.float32, {}),
    ("100k x 256² SH3 RGB+ED", 100_000, 256, 3, "RGB+ED", torch.float32, {}),
    ("50k x 128² SH3 RGB", 50_000, 128, 3, "RGB", torch.float32, {}),
    ("10k x 128² RGB+D", 10_000, 128, None, "RGB+D", torch.float32, {}),
    ("10k x 128² RGB antialiased", 10_000, 128, None, "RGB", torch.float32, {"rasterize_mode": "antialiased"}),
    ("10k x 128² covars RGB+ED antialiased", 10_000, 128, None, "RGB+ED", torch.float32,
     {"rasterize_mode": "antialiased", "covars": True}),
    ("10k x 128² SH3 RGB+ED float64", 10_000, 128, 3, "RGB+ED", torch.float64, {}),
]


def covariances(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)
    return R @ torch.diag_embed(scales * scales) @ R.transpose(-1, -2)


def outputs(glue, scene: dict, sh, mode: str, dtype, kw: dict) -> dict:
    kw = dict(kw)
    # fresh leaves per call: ``p.to(dtype)`` of a tensor already in ``dtype`` is that tensor, so both versions
    # would share the leaves and their ``.grad`` (the second call accumulating into the first's: "equal")
    means, quats, scales, opacities, colors = (p.detach().to(dtype).clone() for p in scene["params"])
    if kw.pop("covars", False):
        leaves = {"means": means, "covars": covariances(quats, scales), "opacities": opacities, "colors": colors}
        args = (leaves["means"], None, None)
    else:
        leaves = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors}
        args = (leaves["means"], leaves["quats"], leaves["scales"])
    for t in leaves.values():
        t.requires_grad_()
    if "covars" in leaves:
        kw["covars"] = leaves["covars"]
    out, alpha, meta = glue.rasterization(*args, leaves["opacities"], leaves["colors"], scene["viewmats"].to(dtype),
                                          scene["Ks"].to(dtype), scene["size"], scene["size"], sh_degree=sh,
                                          render_mode=mode, **kw)
    meta["means2d"].retain_grad()
    weights = torch.rand(out.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    ((out * weights).sum() + alpha.sum()).backward()
    res = {"render": out.detach(), "alpha": alpha.detach(), "v_means2d": meta["means2d"].grad}
    res.update({f"v_{k}": t.grad for k, t in leaves.items()})
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", required=True, help="the git revision whose kernels are compared")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts (default 1,2)")
    args = ap.parse_args()
    failed = False
    with tempfile.TemporaryDirectory() as tmp:
        _, base_glue = load_baseline(args.baseline, Path(tmp))
        for threads in (int(t) for t in args.threads.split(",")):
            torch.set_num_threads(threads)
            cpu_rasterize.set_threads(threads)
            for name, n, size, sh, mode, dtype, kw in SCENES:
                scene = make_scene(n, size, sh)
                a = outputs(base_glue, scene, sh, mode, dtype, kw)
                b = outputs(cpu_rasterize, scene, sh, mode, dtype, kw)
                cells = []
                for key in a:
                    x, y = a[key], b[key]
                    if torch.equal(x, y):
                        cells.append(f"{key} equal")
                        continue
                    scale = max(x.abs().max().item(), 1e-300)
                    rel = ((x - y).abs().max() / scale).item()
                    cells.append(f"{key} DIFFERS (max |d| / max |x| = {rel:.2e})")
                    failed |= dtype == torch.float32
                print(f"{threads} thread(s), {name}: " + "; ".join(cells), flush=True)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()

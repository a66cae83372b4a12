"""3DGS fit throughput on CUDA with gsplat (``models/gaussians/renderer.py``), and renderer parity.

Needs a CUDA GPU and gsplat (``pip install navcrafter[cuda]``; gsplat compiles its kernels on the first call,
which can take minutes: reported separately as ``first_call_seconds``). Refuses to run otherwise.

    python benchmarks/gsplat_fit.py --out bench-out/gsplat-fit            # 100k Gaussians, 256x256, 500 its
    python benchmarks/gsplat_fit.py --out bench-out/gsplat-fit --quick    # 100k Gaussians, 128x128, 100 its

Scene: a synthetic "truth" of N random Gaussians (a slab at depth 3-6 in front of the cameras, random
rotations, log-uniform scales, opacities U(0.3, 0.95), random SH degree-1 colours) rendered from V cameras
with gsplat; the fit starts from the truth's means with noise, grey colours, opacity 0.1, and trains with
``GaussianTrainer`` (device ``cuda``, renderer ``gsplat``; L1 + depth, DropGaussian, no densification unless
``--densify``, so N stays fixed). Reported: iterations/s of the trainer's ``step`` (render, losses, backward,
Adam, strategy, the per-step history sync: the real loop), the same for our PyTorch renderer on the same GPU
for a few iterations (``--torch-iterations``), PSNR on the training views before/after, and parity errors:
our renderer on the CPU (``alpha_clamp=0.999``) vs gsplat on a 2k-Gaussian 64x64 scene (the test's), and our
renderer on CUDA vs gsplat on one view of the fit scene. Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.renderer import INSTALL_HINT, gsplat_available, rasterize
from navcrafter.models.gaussians.train import GaussianTrainer, TrainView
from navcrafter.schemas.config import FitConfig

DEVICE = "cuda"  # module-level so that the script's logic can be dry-run elsewhere (never changed by main)


def _sync() -> None:
    if torch.device(DEVICE).type == "cuda":
        torch.cuda.synchronize()


def _peak_gib(reset: bool = False) -> float:
    if torch.device(DEVICE).type != "cuda":
        return float("nan")
    if reset:
        torch.cuda.reset_peak_memory_stats()
    return torch.cuda.max_memory_allocated() / 2**30


def refuse_without_cuda() -> str | None:
    if not torch.cuda.is_available():
        return (f"this benchmark needs a CUDA GPU: torch {torch.__version__} sees none "
                f"(CUDA build: {torch.version.cuda or 'no'}). {INSTALL_HINT}")
    if not gsplat_available():
        return f"this benchmark needs gsplat, which does not import here; {INSTALL_HINT}"
    return None


def look_at_c2w(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (+z forward, +y down) at ``eye`` looking at ``target``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, -1.0, 0.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def synthetic_scene(n: int, size: int, n_views: int, seed: int = 0) -> tuple[GaussianModel, GaussianModel, list]:
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g) * 3 + 3
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * z[:, None] * 0.6
    means = torch.cat([xy, z[:, None]], dim=1)
    scale = torch.exp(torch.rand(n, 3, generator=g) * 1.5 - 5.0) * math.sqrt(1e5 / n)  # similar coverage for any n
    opac = torch.rand(n, generator=g) * 0.65 + 0.3
    sh = torch.randn(n, 4, 3, generator=g) * 0.3
    truth = GaussianModel(means, torch.randn(n, 4, generator=g), torch.log(scale), torch.logit(opac),
                          sh[:, 0], sh[:, 1:])
    init = GaussianModel(means + torch.randn(n, 3, generator=g) * 0.02, truth.quats.clone(),
                         torch.log(scale * 1.2), torch.full((n,), math.log(0.1 / 0.9)), torch.zeros(n, 3),
                         torch.zeros(n, 3, 3))
    f = 0.5 * size / math.tan(math.radians(30))
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float32)
    views, dev_truth = [], truth.to(DEVICE)
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        c2w = torch.tensor(look_at_c2w(np.array([0.4 * math.cos(a), 0.3 * math.sin(a), 0.0]),
                                       np.array([0.0, 0.0, 4.5])), dtype=torch.float32)
        with torch.no_grad():
            out, _, _ = dev_truth.render(torch.linalg.inv(c2w)[None].to(DEVICE), K[None].to(DEVICE), size, size,
                                         render_mode="RGB+ED", backend="gsplat")
        views.append(TrainView(out[0, ..., :3].clamp(0, 1).cpu(), c2w, K, out[0, ..., 3].cpu()))
    return truth, init, views


def diff_stats(a: torch.Tensor, b: torch.Tensor) -> dict:
    d = (a.float().cpu() - b.float().cpu()).abs().flatten()
    return {"max": float(d.max()), "mean": float(d.mean()), "p999": float(torch.quantile(d[: 16_000_000], 0.999))}


def parity_small() -> dict:
    """Our CPU renderer (alpha_clamp 0.999) vs gsplat: 2k Gaussians, SH degree 3, 64x64, RGB+ED (the test's scene)."""
    g = torch.Generator().manual_seed(7)
    n = 2000
    params = (torch.rand(n, 3, generator=g) * 3 + torch.tensor([-1.5, -1.5, 2.0]), torch.randn(n, 4, generator=g),
              torch.exp(torch.rand(n, 3, generator=g) * 2 - 4), 0.05 + 0.95 * torch.rand(n, generator=g),
              torch.randn(n, 16, 3, generator=g) * 0.5)
    vm = torch.eye(4)[None]
    K = torch.tensor([[[57.6, 0.0, 32.0], [0.0, 57.6, 32.0], [0.0, 0.0, 1.0]]])
    bg = torch.tensor([[0.1, 0.2, 0.3]])
    kw = dict(sh_degree=3, render_mode="RGB+ED")
    ours, oa, _ = rasterize(*params, vm, K, 64, 64, backgrounds=bg, alpha_clamp=0.999, backend="torch", **kw)
    dev = [t.to(DEVICE) for t in (*params, vm, K)]
    theirs, ta, _ = rasterize(*dev, 64, 64, backgrounds=bg.to(DEVICE), backend="gsplat", **kw)
    return {"colour": diff_stats(ours[..., :3], theirs[..., :3]), "alpha": diff_stats(oa, ta),
            "depth_rel": _depth_rel(ours, oa, theirs)}


def _depth_rel(ours, oa, theirs) -> dict:
    mask = oa[..., 0].cpu() > 0.5
    o, t = ours[..., 3].cpu()[mask], theirs[..., 3].cpu()[mask]
    return diff_stats(o / o.clamp(min=1e-6), t / o.clamp(min=1e-6))


def parity_fit_scene(truth: GaussianModel, view: TrainView) -> dict:
    """Our renderer on CUDA (alpha_clamp 0.999) vs gsplat, one view of the fit scene."""
    m = truth.to(DEVICE)
    vm, K = torch.linalg.inv(view.c2w)[None].to(DEVICE), view.K[None].to(DEVICE)
    W, H = view.size
    with torch.no_grad():
        ours, oa, _ = m.render(vm, K, W, H, render_mode="RGB+ED", backend="torch", alpha_clamp=0.999)
        theirs, ta, _ = m.render(vm, K, W, H, render_mode="RGB+ED", backend="gsplat")
    return {"colour": diff_stats(ours[..., :3], theirs[..., :3]), "alpha": diff_stats(oa, ta),
            "depth_rel": _depth_rel(ours, oa, theirs)}


def psnr(trainer: GaussianTrainer, views: list[TrainView]) -> float:
    rgb, _ = trainer.evaluate(views)
    gt = np.stack([v.image.numpy() for v in views])
    mse = ((rgb.astype(np.float64) - gt) ** 2).mean(axis=(1, 2, 3))
    return float(np.mean(10 * np.log10(1.0 / np.maximum(mse, 1e-12))))


def time_steps(trainer: GaussianTrainer, start: int, n: int) -> float:
    _sync()
    t0 = time.perf_counter()
    for s in range(start, start + n):
        trainer.step(s)
    _sync()
    return time.perf_counter() - t0


def run(args) -> dict:
    t0 = time.perf_counter()
    warm = rasterize(*(t.to(DEVICE) for t in (torch.zeros(1, 3) + torch.tensor([0.0, 0.0, 3.0]),
                                          torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),
                                          torch.tensor([0.5]), torch.rand(1, 3), torch.eye(4)[None],
                                          torch.tensor([[[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]]]))),
                     32, 32, backend="gsplat")
    _sync()
    del warm
    first_call = time.perf_counter() - t0  # includes gsplat's JIT build when its cache is cold

    truth, init, views = synthetic_scene(args.gaussians, args.size, args.views)
    cfg = FitConfig(iterations=args.iterations, sh_degree=1, sh_degree_interval=max(args.iterations // 4, 1),
                    lambda_lpips=0.0, lambda_depth=0.1, drop_gamma=0.1, densify=args.densify,
                    densify_start=args.iterations // 5, densify_every=max(args.iterations // 10, 1),
                    densify_stop=int(args.iterations * 0.8), reset_every=0, max_gaussians=2 * args.gaussians,
                    lr_means=1.6e-4, lr_means_final=1.6e-6, device=DEVICE, renderer="gsplat")
    trainer = GaussianTrainer(init, views, cfg, scene_scale=4.5)
    psnr0 = psnr(trainer, views)
    warmup = min(10, args.iterations)
    time_steps(trainer, 0, warmup)
    secs = time_steps(trainer, warmup, args.iterations - warmup)
    psnr1 = psnr(trainer, views)
    gs = {"iterations": args.iterations - warmup, "seconds": secs, "its_per_s": (args.iterations - warmup) / secs,
          "psnr_before": psnr0, "psnr_after": psnr1, "n_gaussians_end": int(trainer.params["means"].shape[0]),
          "peak_mem_gib": _peak_gib()}

    torch_row = None
    if args.torch_iterations > 0:
        _peak_gib(reset=True)
        torch_cfg = cfg.model_copy(update={"renderer": "torch", "densify": False})
        tt = GaussianTrainer(init, views, torch_cfg, scene_scale=4.5)
        time_steps(tt, 0, 2)
        s = time_steps(tt, 2, args.torch_iterations)
        torch_row = {"iterations": args.torch_iterations, "seconds": s, "its_per_s": args.torch_iterations / s,
                     "peak_mem_gib": _peak_gib()}

    name = torch.cuda.get_device_name(0) if torch.device(DEVICE).type == "cuda" else DEVICE
    return {"quick": args.quick, "device": name, "torch": torch.__version__,
            "gsplat": __import__("gsplat").__version__, "python": platform.python_version(),
            "gaussians": args.gaussians, "size": args.size, "views": args.views, "densify": args.densify,
            "first_call_seconds": first_call, "gsplat_fit": gs, "torch_fit_on_cuda": torch_row,
            "speedup_vs_torch_renderer": (gs["its_per_s"] / torch_row["its_per_s"]) if torch_row else None,
            "parity_small_cpu_vs_gsplat": parity_small(), "parity_fit_scene_cuda_torch_vs_gsplat":
            parity_fit_scene(truth, views[0])}


def markdown(r: dict) -> str:
    g, t = r["gsplat_fit"], r["torch_fit_on_cuda"]
    lines = [f"# 3DGS fit on CUDA with gsplat{' — quick' if r['quick'] else ''}", "",
             f"{r['device']}, torch {r['torch']}, gsplat {r['gsplat']}; {r['gaussians']:,} Gaussians, "
             f"{r['size']}x{r['size']}, {r['views']} views, densify: {r['densify']}. First gsplat call "
             f"(kernel build when not cached): {r['first_call_seconds']:.1f} s.", "",
             "| renderer | iterations | it/s | peak GPU memory (GiB) |", "|---|---:|---:|---:|",
             f"| gsplat | {g['iterations']} | {g['its_per_s']:.1f} | {g['peak_mem_gib']:.2f} |"]
    if t:
        lines.append(f"| ours (PyTorch) on CUDA | {t['iterations']} | {t['its_per_s']:.2f} | {t['peak_mem_gib']:.2f} |")
        lines += ["", f"gsplat / ours: {r['speedup_vs_torch_renderer']:.1f}x."]
    lines += ["", f"Training-view PSNR {g['psnr_before']:.2f} -> {g['psnr_after']:.2f} dB; "
              f"{g['n_gaussians_end']:,} Gaussians at the end.", "",
              "Parity (abs difference: max / mean / 99.9th pct):",
              "", "| comparison | colour | alpha | depth (relative, alpha > 0.5) |", "|---|---|---|---|"]
    for key, name in [("parity_small_cpu_vs_gsplat", "ours CPU vs gsplat, 2k Gaussians 64² (clamp 0.999)"),
                      ("parity_fit_scene_cuda_torch_vs_gsplat", "ours CUDA vs gsplat, fit scene, one view")]:
        p = r[key]
        cells = [f"{p[c]['max']:.1e} / {p[c]['mean']:.1e} / {p[c]['p999']:.1e}"
                 for c in ("colour", "alpha", "depth_rel")]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Both rows render ours with alpha_clamp=0.999 (gsplat's). Opacities reach 0.95, so gsplat may list "
              "a Gaussian's faint tail (alpha < 0.011) in tiles that ours does not (models/gaussians/renderer.py); "
              "the rest is float32 rounding."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", action="store_true", help="128x128 and 100 iterations (a minute or two after the build)")
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", type=int, default=None, help="image side (default 256, quick 128)")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=None, help="default 500, quick 100")
    ap.add_argument("--torch-iterations", type=int, default=None, help="our renderer on CUDA (default 10, quick 3)")
    ap.add_argument("--densify", action="store_true")
    args = ap.parse_args(argv)
    why = refuse_without_cuda()
    if why:
        print(f"gsplat_fit: refusing to run: {why}", file=sys.stderr)
        return 2
    args.size = args.size or (128 if args.quick else 256)
    args.iterations = args.iterations or (100 if args.quick else 500)
    if args.torch_iterations is None:
        args.torch_iterations = 3 if args.quick else 10
    if args.iterations <= 10:
        ap.error("--iterations must be > 10 (10 warm-up iterations are not timed)")
    results = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    md = markdown(results)
    (args.out / "results.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

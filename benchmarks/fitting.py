"""3DGS fitting ablation (the shape of the paper's Table VII): the geometry-aware fit's parts switched on one
at a time on the simulation scenes, scored on held-out frames.

Variants, all from the same explored scene (same frames, cameras, cloud and seeds):

* **none**: L1 only (``lambda_depth = 0``, ``drop_gamma = 0``);
* **+depth**: plus the calibrated monocular depth term (``lambda_depth`` of the config);
* **+depth+DropGaussian**: plus DropGaussian (``drop_gamma`` of the config).

LPIPS is in the loss only when the official LPIPS weights are present (``--eval-weights``); otherwise it is in
no variant and the report says so. Held-out frames are every ``fit.holdout_every``-th frame.

    python benchmarks/fitting.py --out bench-out/fitting            # 3 kinds x 3 seeds, 64x64 fit, 600 iterations
    python benchmarks/fitting.py --out bench-out/fitting --quick    # 3 kinds x 1 seed, the tiny preset's fit

Writes ``results.json`` and ``results.md`` into ``--out``. Simulation mode: frames are perfect renders and the
geometry is ground truth with noise, so these numbers measure the fitting recipe, not learned models.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from navcrafter.models.simulation import LABEL
from navcrafter.models.simulation.demo import write_demo_collection
from navcrafter.models.simulation.scenes import KINDS
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import FIT
from navcrafter.schemas.store import Store
from navcrafter.tasks.fit import fit
from navcrafter.tasks.ingest import ingest
from navcrafter.tasks.pipeline import run_scene

VARIANTS = {
    "none": {"fit.lambda_depth": 0.0, "fit.drop_gamma": 0.0},
    "+depth": {"fit.drop_gamma": 0.0},
    "+depth+DropGaussian": {},
}


def base_overrides(quick: bool, weights: str | None) -> dict:
    over = {"iterations": 2, "synthesis.num_frames": 17, "synthesis.height": 96, "synthesis.width": 96,
            "fit.resolution": 64, "fit.iterations": 600, "fit.max_init_points": 20_000, "fit.sh_degree": 1,
            "fit.sh_degree_interval": 200, "fit.refine_start": 100, "fit.refine_every": 50, "fit.refine_stop": 450,
            "fit.reset_every": 0, "fit.max_gaussians": 30_000, "fit.lr_means": 1.6e-3, "fit.lr_means_final": 1.6e-5}
    if quick:
        over = {}
    if weights:
        over["evaluation.weights_dir"] = weights
    return over


def run(out: Path, quick: bool, seeds: int, kinds: tuple[str, ...], weights: str | None) -> list[dict]:
    base = base_overrides(quick, weights)
    cfg0 = RunConfig.load(preset="tiny" if quick else "paper", overrides=base)
    rows = []
    with tempfile.TemporaryDirectory(prefix="navcrafter-fitbench-") as tmp:
        photos = Path(tmp) / "photos"
        paths = write_demo_collection(photos, kinds=kinds, per_kind=seeds, width=320, height=240, supersample=1)
        store = str(Path(tmp) / "store")
        for photo in paths:
            res = ingest(store, str(photo), cfg0, "bench")
            if not res.ok:
                raise RuntimeError(res.error)
            run_scene(store, res.scene_id, cfg0, "bench")
            for name, over in VARIANTS.items():
                cfg = RunConfig.load(preset="tiny" if quick else "paper",
                                     overrides={**base, "fit.enabled": True, **over})
                t0 = time.perf_counter()
                fit(store, res.scene_id, cfg, "bench")
                a = Store(store).scene(res.scene_id).status(FIT).attrs
                rows.append({"photo": photo.name, "kind": photo.name.split("-")[0], "variant": name,
                             "psnr": a["psnr"], "ssim": a["ssim"], "lpips": a["lpips"], "init_psnr": a["init_psnr"],
                             "n_gaussians": a["n_gaussians"], "seconds": time.perf_counter() - t0,
                             "lpips_note": a["lpips_note"], "resolution": a["resolution"],
                             "iterations": cfg.fit.iterations})
                print(f"{photo.name:16s} {name:22s} PSNR {a['psnr']:.2f} SSIM {a['ssim']:.3f} "
                      f"({rows[-1]['seconds']:.1f} s)", flush=True)
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for kind in sorted({r["kind"] for r in rows}) + ["all"]:
        for name in VARIANTS:
            sel = [r for r in rows if r["variant"] == name and (kind == "all" or r["kind"] == kind)]
            if not sel:
                continue
            p, s = np.array([r["psnr"] for r in sel]), np.array([r["ssim"] for r in sel])
            lp = [r["lpips"] for r in sel if r["lpips"] is not None]
            out.append({"kind": kind, "variant": name, "n": len(sel), "psnr": float(p.mean()),
                        "psnr_std": float(p.std()), "ssim": float(s.mean()), "ssim_std": float(s.std()),
                        "lpips": float(np.mean(lp)) if len(lp) == len(sel) else None,
                        "seconds": float(np.mean([r["seconds"] for r in sel]))})
    return out


def markdown(summary: list[dict], rows: list[dict], quick: bool) -> str:
    lines = [f"# 3DGS fitting ablation (Table VII shape){' — quick' if quick else ''}", "",
             f"*{LABEL}: frames are perfect renders, geometry is ground truth with noise.*", "",
             "| scenes | variant | n | PSNR (dB) | SSIM | LPIPS | fit time (s) |", "|---|---|---:|---:|---:|---:|---:|"]
    for s in summary:
        lp = f"{s['lpips']:.3f}" if s["lpips"] is not None else "n/a"
        lines.append(f"| {s['kind']} | {s['variant']} | {s['n']} | {s['psnr']:.2f} ± {s['psnr_std']:.2f} | "
                     f"{s['ssim']:.3f} ± {s['ssim_std']:.3f} | {lp} | {s['seconds']:.1f} |")
    if rows:
        r = rows[0]
        lines += ["", f"Fit: {r['iterations']} iterations at {r['resolution'][0]}x{r['resolution'][1]}; held-out "
                  "frames: every 8th. Mean ± std over scenes.", "", f"LPIPS: {r['lpips_note']}"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", action="store_true", help="1 seed, the tiny preset (about a minute)")
    ap.add_argument("--seeds", type=int, default=None, help="scene seeds per kind (default 3, quick 1)")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--eval-weights", default=None, help="folder with the official LPIPS weights")
    args = ap.parse_args(argv)
    seeds = args.seeds or (1 if args.quick else 3)
    kinds = tuple(k for k in args.kinds.split(",") if k)
    rows = run(args.out, args.quick, seeds, kinds, args.eval_weights)
    summary = summarise(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"quick": args.quick, "seeds": seeds, "kinds": kinds,
                                                        "label": LABEL, "rows": rows, "summary": summary}, indent=1))
    md = markdown(summary, rows, args.quick)
    (args.out / "results.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

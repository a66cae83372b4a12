"""3DGS fitting ablation (the shape of the paper's Table VI): the geometry-aware fit's parts switched on one
at a time on the simulation scenes, scored on held-out frames and on off-trajectory views.

Variants, all from the same explored scene (same frames, cameras, cloud and seeds):

* **none**: L1 only (``lambda_depth = 0``, ``drop_gamma = 0``);
* **+depth**: plus the calibrated monocular depth term (``lambda_depth`` of the config);
* **+depth+DropGaussian**: plus DropGaussian (``drop_gamma`` of the config);
* **+depth+DropGaussian+longer**: the control for the next one: that fit trained ``refine.iterations`` more
  iterations on the real views only, with the refine step's settings;
* **+depth+DropGaussian+refine**: that fit, then the refine step (``refine.iterations`` more iterations with
  refined novel views added; the refiner is the simulation stand-in, ``simulation.refine_strength``). Its
  paired gain is measured against the control, so it is the refined views' contribution.

Scores: held-out frames (every ``fit.holdout_every``-th frame of the explored trajectory: between training
frames, so they mostly test interpolation) and **off-trajectory views** (the held-out cameras displaced
sideways/up by 0.15 x the scene scale and turned up to 10 degrees, scored against the simulation's true
renders: they test the geometry a user flying through the scene would see). Results are written after every
scene (``complete: false`` until the end); a paired table gives each component's gain scene by scene.

LPIPS is in the loss only when the official LPIPS weights are present (``--eval-weights``); otherwise it is in
no variant and the report says so.

    python benchmarks/fitting.py --out bench-out/fitting --seeds 10-12          # 3 kinds x 3 seeds, 64x64, 300 it.
    python benchmarks/fitting.py --out bench-out/fitting --quick --seeds 10-12  # the tiny preset's fit

``--seeds A-B``: the scene seeds of every kind (0-9 is the development range, where anything may be tuned;
results are judged on other ranges). Writes ``results.json`` and ``results.md`` into ``--out``. Simulation mode,
honest preset (``simulation.preset``): the frames are the simulated video model's (drifting cameras, hallucinated
unseen content, corrupted close-ups), the fit trains on the geometry model's estimated cameras, and the
off-trajectory views are scored against the true scene, so the recipe is measured against what real models get
wrong; the numbers still measure the fitting recipe, not learned models.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from seeds import is_development, parse_seeds  # benchmarks/seeds.py (the script's folder is on the path)

from navcrafter.models.gaussians.recipe import continue_training, heldout_metrics, load_lpips
from navcrafter.models.simulation import LABEL
from navcrafter.models.simulation.demo import write_demo_collection
from navcrafter.models.simulation.scenes import KINDS
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import FIT, REFINE
from navcrafter.schemas.store import Store
from navcrafter.tasks import runner
from navcrafter.tasks.common import load_cloud, simulation_truth
from navcrafter.tasks.ingest import ingest
from navcrafter.tasks.readers import load_fit_views, load_gaussians, load_refined_gaussians
from navcrafter.tasks.runner import run_scene

VARIANTS = {
    "none": {"fit.lambda_depth": 0.0, "fit.drop_gamma": 0.0},
    "+depth": {"fit.drop_gamma": 0.0},
    "+depth+DropGaussian": {},
    # control: that fit trained refine.iterations more on the real views only (as long as the refine variant)
    "+depth+DropGaussian+longer": {"refine.enabled": True, "control": True},
    "+depth+DropGaussian+refine": {"refine.enabled": True},  # that fit, then the refine step
}
OFF_TRAJECTORY = {"offset": 0.15, "angle_deg": 10.0, "seed": 12345}


def base_overrides(quick: bool, weights: str | None) -> dict:
    over = {"iterations": 2, "synthesis.num_frames": 17, "synthesis.height": 96, "synthesis.width": 96,
            "fit.resolution": 64, "fit.iterations": 300, "fit.max_init_points": 10_000, "fit.sh_degree": 1,
            "fit.sh_degree_interval": 100, "fit.densify_start": 50, "fit.densify_every": 25, "fit.densify_stop": 225,
            "fit.reset_every": 0, "fit.max_gaussians": 15_000, "fit.lr_means": 1.6e-3, "fit.lr_means_final": 1.6e-5,
            "refine.iterations": 150}
    if quick:
        over = {"refine.iterations": 20}
    if weights:
        over["evaluation.weights_dir"] = weights
    return over


def off_trajectory_cameras(scene) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Cameras displaced from the fit's held-out cameras (seeded, the same for every variant), their K and
    the fit size (w, h)."""
    from navcrafter.models.gaussians.novelviews import novel_cameras

    g = scene.read_all(FIT)
    a = scene.status(FIT).attrs
    held = np.nonzero(g["holdout"])[0]
    c2w, src = novel_cameras(g["c2w"], held, load_cloud(scene, int(g["frame_ref"][-1][0])).points,
                             offset=OFF_TRAJECTORY["offset"] * a["scene_scale"], angle_deg=OFF_TRAJECTORY["angle_deg"],
                             rng=np.random.default_rng(OFF_TRAJECTORY["seed"]))
    w, h = a["resolution"]
    return c2w, g["K"][src], w, h


def off_trajectory_psnr(scene, model, cams) -> tuple[float, float]:
    """PSNR / SSIM of ``model`` at the off-trajectory cameras against the simulation's true views."""
    from navcrafter.models.camera.cameras import Intrinsics
    from navcrafter.models.gaussians.train import render_model
    from navcrafter.models.metrics.image import psnr, ssim
    from navcrafter.models.simulation.render import render

    c2w, K, w, h = cams
    truth = simulation_truth(scene)
    gt = np.stack([render(truth.scene, truth.gt_pose(c2w[i][None])[0], Intrinsics.from_matrix(K[i], w, h),
                          supersample=2).rgb for i in range(len(c2w))]).astype(np.float64) / 255
    rgb = render_model(model, c2w, K, w, h).astype(np.float64) / 255
    return float(np.mean(psnr(rgb, gt))), float(np.mean(ssim(rgb, gt)))


def longer_fit(scene, cfg: RunConfig) -> tuple[dict, object]:
    """The control of the refine variant: the fitted model trained as many more iterations as the refine step
    does, with the same settings, on the real training views only. (attrs with psnr/ssim/lpips, model)."""
    train, test = load_fit_views(scene)
    fa = scene.status(FIT).attrs
    lpips_model, _ = load_lpips(cfg.evaluation)
    trainer, result = continue_training(load_gaussians(scene), train, cfg.fit, cfg.refine, 0, float(fa["scene_scale"]),
                                        lpips_model)
    rgb, _ = trainer.evaluate(test)
    gt = np.stack([v.image.numpy() for v in test]).astype(np.float64)
    return {**heldout_metrics(rgb, gt, lpips_model), "n_gaussians": len(result.model)}, result.model


def run(out: Path, quick: bool, seeds: tuple[int, int], kinds: tuple[str, ...], weights: str | None,
        on_scene=None) -> list[dict]:
    base = base_overrides(quick, weights)
    cfg0 = RunConfig.load(preset="tiny" if quick else "paper", overrides=base)
    rows = []
    with tempfile.TemporaryDirectory(prefix="navcrafter-fitbench-") as tmp:
        photos = Path(tmp) / "photos"
        paths = [p for seed in range(seeds[0], seeds[1] + 1) for p in write_demo_collection(
            photos, kinds=kinds, per_kind=1, seed=seed, width=320, height=240, supersample=1)]
        paths = sorted(paths, key=lambda p: (int(p.stem.rsplit("-", 1)[1]), kinds.index(p.stem.rsplit("-", 1)[0])))
        store = str(Path(tmp) / "store")
        for photo in paths:  # seed by seed, so partial results cover every kind
            res = ingest(store, str(photo), cfg0, "bench")
            if not res.ok:
                raise RuntimeError(res.error)
            run_scene(store, res.scene_id, cfg0, "bench")
            scene = Store(store).scene(res.scene_id)
            cams = None
            for name, over in VARIANTS.items():
                over = dict(over)
                control = over.pop("control", False)
                cfg = RunConfig.load(preset="tiny" if quick else "paper",
                                     overrides={**base, "fit.enabled": True, **over})
                t0 = time.perf_counter()
                runner.run(store, res.scene_id, "fit", cfg, "bench")  # skipped when the last variant fitted the same
                if control:
                    a, model = longer_fit(scene, cfg)
                elif cfg.refine.enabled:
                    runner.run(store, res.scene_id, "refine", cfg, "bench")
                    a, model = scene.status(REFINE).attrs, load_refined_gaussians(scene)
                else:
                    a, model = scene.status(FIT).attrs, load_gaussians(scene)
                seconds = time.perf_counter() - t0
                fa = scene.status(FIT).attrs
                cams = cams if cams is not None else off_trajectory_cameras(scene)
                off_psnr, off_ssim = off_trajectory_psnr(scene, model, cams)
                rows.append({"photo": photo.name, "kind": photo.name.split("-")[0], "variant": name,
                             "psnr": a["psnr"], "ssim": a["ssim"], "lpips": a["lpips"], "init_psnr": fa["init_psnr"],
                             "off_psnr": off_psnr, "off_ssim": off_ssim, "n_off": len(cams[0]),
                             "n_gaussians": a["n_gaussians"], "seconds": seconds,
                             "lpips_note": fa["lpips_note"], "resolution": fa["resolution"],
                             "iterations": cfg.fit.iterations,
                             "refine_iterations": cfg.refine.iterations if cfg.refine.enabled else 0})
                print(f"{photo.name:16s} {name:28s} PSNR {a['psnr']:.2f} SSIM {a['ssim']:.3f} off-trajectory PSNR "
                      f"{off_psnr:.2f} ({seconds:.1f} s)", flush=True)
            if on_scene is not None:
                on_scene(rows)
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for kind in sorted({r["kind"] for r in rows}) + ["all"]:
        for name in VARIANTS:
            sel = [r for r in rows if r["variant"] == name and (kind == "all" or r["kind"] == kind)]
            if not sel:
                continue
            p, s = np.array([r["psnr"] for r in sel]), np.array([r["ssim"] for r in sel])
            op = np.array([r["off_psnr"] for r in sel])
            lp = [r["lpips"] for r in sel if r["lpips"] is not None]
            out.append({"kind": kind, "variant": name, "n": len(sel), "psnr": float(p.mean()),
                        "psnr_std": float(p.std()), "ssim": float(s.mean()), "ssim_std": float(s.std()),
                        "off_psnr": float(op.mean()), "off_psnr_std": float(op.std()),
                        "lpips": float(np.mean(lp)) if len(lp) == len(sel) else None,
                        "seconds": float(np.mean([r["seconds"] for r in sel]))})
    return out


def paired_gains(rows: list[dict]) -> list[dict]:
    """Each variant against the one before it, scene by scene: mean gain and how many scenes gained."""
    names = list(VARIANTS)
    by = {(r["photo"], r["variant"]): r for r in rows}
    photos = sorted({r["photo"] for r in rows})
    out = []
    for prev, cur in zip(names, names[1:]):
        pairs = [(by[(p, prev)], by[(p, cur)]) for p in photos if (p, prev) in by and (p, cur) in by]
        if not pairs:
            continue
        d = np.array([b["psnr"] - a["psnr"] for a, b in pairs])
        do = np.array([b["off_psnr"] - a["off_psnr"] for a, b in pairs])
        out.append({"component": cur.rsplit("+", 1)[1], "from": prev, "to": cur,
                    "n": len(pairs), "psnr_gain": float(d.mean()), "psnr_gain_std": float(d.std()),
                    "psnr_wins": int((d > 0).sum()), "off_psnr_gain": float(do.mean()),
                    "off_psnr_gain_std": float(do.std()), "off_psnr_wins": int((do > 0).sum())})
    return out


def markdown(summary: list[dict], gains: list[dict], rows: list[dict], quick: bool) -> str:
    seed_range = sorted({int(r["photo"].rsplit("-", 1)[1].split(".")[0]) for r in rows}) if rows else []
    lines = [f"# 3DGS fitting ablation (Table VI shape){' — quick' if quick else ''}", "",
             f"*{LABEL}, honest preset: the frames are the simulated video model's (its cameras drift, unseen "
             "content is hallucinated, close-ups are corrupted), the fit trains on the simulated geometry model's "
             "estimated cameras; the refiner is the simulation stand-in (the render moved 70 % of the way to the "
             "true view, plus noise).*", "",
             f"Scene seeds {seed_range[0]}-{seed_range[-1]} of every kind" + (
                 " (the development range)." if is_development((seed_range[0], seed_range[-1])) else
                 " (held out: nothing was tuned on them; the development range is 0-9).") if seed_range else "", "",
             "| scenes | variant | n | held-out PSNR (dB) | SSIM | LPIPS | off-trajectory PSNR (dB) | time (s) |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for s in summary:
        lp = f"{s['lpips']:.3f}" if s["lpips"] is not None else "n/a"
        lines.append(f"| {s['kind']} | {s['variant']} | {s['n']} | {s['psnr']:.2f} ± {s['psnr_std']:.2f} | "
                     f"{s['ssim']:.3f} ± {s['ssim_std']:.3f} | {lp} | {s['off_psnr']:.2f} ± {s['off_psnr_std']:.2f} | "
                     f"{s['seconds']:.1f} |")
    lines += ["", "Paired by scene (each component added to the variant before it; refine against the equally long "
              "control):", "",
              "| component | scenes | held-out PSNR gain (dB) | scenes gaining | off-trajectory PSNR gain (dB) | "
              "scenes gaining |", "|---|---:|---:|---:|---:|---:|"]
    for g in gains:
        lines.append(f"| {g['component']} | {g['n']} | {g['psnr_gain']:+.2f} ± {g['psnr_gain_std']:.2f} | "
                     f"{g['psnr_wins']}/{g['n']} | {g['off_psnr_gain']:+.2f} ± {g['off_psnr_gain_std']:.2f} | "
                     f"{g['off_psnr_wins']}/{g['n']} |")
    if rows:
        r = rows[0]
        ref_it = max(x["refine_iterations"] for x in rows)
        lines += ["", f"Fit: {r['iterations']} iterations at {r['resolution'][0]}x{r['resolution'][1]} (refine: "
                  f"{ref_it} more). Held-out frames: every 8th frame of the explored trajectory. Off-trajectory "
                  f"views: {r['n_off']} per scene, the held-out cameras displaced sideways/up by "
                  f"{OFF_TRAJECTORY['offset']} x the scene scale and turned up to {OFF_TRAJECTORY['angle_deg']}°, "
                  "scored against the simulation's true views (the same cameras for every variant). "
                  "Mean ± std over scenes. Time: the variant's own work, including the off-trajectory scoring "
                  "(the +longer and +refine variants start from the +depth+DropGaussian fit and add only their "
                  "extra iterations).", "", f"LPIPS: {r['lpips_note']}"]
    return "\n".join(lines) + "\n"


def rerender(out: Path) -> str:
    """Write ``results.md`` again from ``results.json`` (after a change to the report's wording)."""
    data = json.loads((out / "results.json").read_text())
    md = markdown(data["summary"], data["paired_gains"], data["rows"], data["quick"])
    if not data.get("complete", True):
        md = "**Partial results (the run is still going or was stopped).**\n\n" + md
    (out / "results.md").write_text(md)
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", action="store_true", help="1 seed, the tiny preset (about a minute)")
    ap.add_argument("--seeds", type=parse_seeds, default=None, help="scene seeds A-B of every kind (default 10-12, "
                    "quick 10-10; 0-9 is the development range); a single N means 0-(N-1)")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--eval-weights", default=None, help="folder with the official LPIPS weights")
    args = ap.parse_args(argv)
    seeds = args.seeds or ((10, 10) if args.quick else (10, 12))
    kinds = tuple(k for k in args.kinds.split(",") if k)
    args.out.mkdir(parents=True, exist_ok=True)

    def write(rows: list[dict], partial: bool = True) -> str:
        summary, gains = summarise(rows), paired_gains(rows)
        (args.out / "results.json").write_text(json.dumps(
            {"quick": args.quick, "seeds": list(seeds), "kinds": kinds, "label": LABEL, "complete": not partial,
             "rows": rows, "summary": summary, "paired_gains": gains}, indent=1))
        md = markdown(summary, gains, rows, args.quick)
        if partial:
            md = "**Partial results (the run is still going or was stopped).**\n\n" + md
        (args.out / "results.md").write_text(md)
        return md

    md = write(run(args.out, args.quick, seeds, kinds, args.eval_weights, on_scene=write), partial=False)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

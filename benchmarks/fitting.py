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

**Sparse views** (``--views 3,6,12``; issue 31, "a Table VI that can answer"): the regime DropGaussian exists for.
Each scene is explored for ``--clips`` clips (3); the last clip is held out WHOLE (its frames are the test views)
and the fit starts from the cloud of the clips before it (``iter_{N-1}/lift``), so nothing of the test clip's
lift reaches the fit. V training frames are chosen by farthest-point sampling of the estimated camera centres of
every frame of the other clips (``models.gaussians.sparse.farthest_views``, from the input frame). The test views
are scored against the simulation's TRUE renders at their true cameras, mapped into the fit's estimated frame by
a similarity fitted (Umeyama) from the training clips' frames, estimated to true: their camera centres and their
pixels lifted with the geometry model's depth and camera and with the true depth and camera (``sparse.depth_pairs``,
every 8th row and column; centres alone are degenerate when the clips turn in place), so the camera
estimate's error is removed; we evaluate in the estimated frame and multiply rendered depth by the similarity's
scale. Scores are over the pixels some training view saw (``sparse.visibility_mask``: the true surface point of a
test pixel projects into a training view's true camera, in front, and agrees with that view's true depth to
3 %; sky excluded): PSNR, SSIM (the SSIM map averaged over those pixels), LPIPS with its official weights (unseen
pixels set to the truth in both images), and the rendered expected depth's AbsRel against the true depth. Variants:
``none`` (L1), ``depth`` (+ calibrated monocular depth, ``depth_space`` median, ``--lambda-depth``),
``dropgaussian`` (+ DropGaussian, gamma 0.2 over the whole fit: its paper's schedule), ``longer`` / ``refine``
(that fit trained ``--refine-fraction`` x more iterations on the real views only / with refined novel views),
controls ``oracle_depth`` (the true depth instead of the calibrated monocular one) and ``sparse_init`` /
``sparse_init_depth`` (the fit started from 10 % of the cloud, with and without depth). Convergence: the
held-out masked L1 is measured at 60, 80 and 100 % of each fit; a fit counts as converged when it changed by
<= 2 % over the last 20 % (recorded per fit). ``--tune-lambda`` (development seeds only) runs none/depth for a
grid of lambda_depth and names the best by mean masked PSNR over views and scenes.

    python benchmarks/fitting.py --out bench-out/sparse --views 3,6,12 --seeds 10-12
    python benchmarks/fitting.py --out bench-out/sparse-quick --quick --views 3,6 --seeds 10-10
    python benchmarks/fitting.py --out bench-out/lambda --quick --views 3,6 --seeds 0-0 --tune-lambda
    python benchmarks/fitting.py --out bench-out/pooled --merge bench-out/seed10,bench-out/seed11  # pool seeds
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

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

if __package__ in (None, ""):  # run as a script: the repository root makes the benchmarks package importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.seeds import is_development, parse_seeds  # noqa: E402

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



# ---------------------------------------------------------------------------------------------------------------
# Sparse views (--views): V farthest-point training frames, a whole clip held out, masked scores at aligned poses
SPARSE_VARIANTS = ("none", "depth", "dropgaussian", "longer", "refine", "oracle_depth", "sparse_init",
                   "sparse_init_depth")
PAIRS = {"depth": ("none", "depth"), "dropgaussian": ("depth", "dropgaussian"), "refine": ("longer", "refine"),
         "oracle_depth": ("none", "oracle_depth"), "depth_sparse_init": ("sparse_init", "sparse_init_depth")}
DROP_GAMMA = 0.2  # DropGaussian's paper schedule: r_t = 0.2 t / T over the whole fit
LAMBDA_GRID = (0.03, 0.1, 0.3, 1.0, 3.0, 10.0)  # 3 and 10: the grid went on past 1, its best before
SPARSE_INIT_FRACTION = 0.1
DEPTH_SPACES = ("median", "relative")  # the scale-free spaces of fit.depth_space
CONVERGENCE_TOL = 0.02
VISIBILITY_TOL = 0.03
ALIGN_STRIDE = 8  # pixels of a lifted frame used in the test-pose alignment (each 8th row and column)


def sparse_overrides(quick: bool, clips: int, weights: str | None) -> dict:
    """The exploration's settings (the fit step itself is off: the benchmark fits)."""
    over = {"iterations": clips, "fit.enabled": False, "refine.enabled": False}
    if not quick:
        over.update({"synthesis.num_frames": 17, "synthesis.height": 96, "synthesis.width": 96,
                     "fit.resolution": 64, "fit.max_init_points": 10_000, "fit.sh_degree": 1,
                     "fit.max_gaussians": 15_000, "fit.lr_means": 1.6e-3, "fit.lr_means_final": 1.6e-5})
    if weights:
        over["evaluation.weights_dir"] = weights
    return over


def fit_settings(fit, iterations: int, lambda_depth: float, drop_gamma: float, depth_space: str = "median"):
    """The fit's settings at ``iterations`` with 3DGS's schedule scaled to it (density control from 10 % to 75 %
    every 5 %, SH degree +1 every quarter), the depth term in a scale-free space (``depth_space``: median-normalised
    or per-pixel relative, ``fit.depth_space``)."""
    return fit.model_copy(update={
        "iterations": iterations, "lambda_depth": lambda_depth, "drop_gamma": drop_gamma, "depth_space": depth_space,
        "densify_start": max(1, iterations // 10), "densify_stop": int(0.75 * iterations),
        "densify_every": max(1, iterations // 20), "reset_every": 0,
        "sh_degree_interval": max(1, iterations // 4)})


class SparseScene:
    """One explored scene, read once: every frame at the fit's size with its estimated and true camera, the
    training pool (clips 1..N-1) and the held-out clip N, the truth at the test cameras and the alignment."""

    def __init__(self, scene, cfg: RunConfig, seed: int) -> None:
        from navcrafter.models.camera.cameras import Intrinsics
        from navcrafter.models.gaussians.recipe import fit_size
        from navcrafter.models.gaussians.sparse import align_to_estimated
        from navcrafter.models.simulation.render import render
        from navcrafter.schemas.layout import SYNTHESIZE
        from navcrafter.tasks.common import load_backend
        from navcrafter.tasks.readers import camera_path, true_cameras

        self.scene, self.cfg, self.seed = scene, cfg, seed
        N = cfg.iterations
        if N < 2:
            raise ValueError("--views needs at least 2 clips (--clips): one to train on, the last held out")
        path = camera_path(scene, cfg, cameras="estimated").distinct()
        self.refs, self.c2w = path.refs, path.c2w
        self.K_full = path.K
        self.H, self.W = scene.read_rows(SYNTHESIZE, 1, "frames", [0]).shape[1:3]
        self.h, self.w = fit_size(self.H, self.W, cfg.fit.resolution)
        self.K = np.stack([path.intrinsics(f).resize(self.w, self.h).K for f in range(len(path))])
        self.true_c2w = np.stack([true_cameras(scene, k)[i] for k, i in self.refs])
        clip = np.array([k for k, _ in self.refs])
        self.pool, self.test = np.nonzero(clip < N)[0], np.nonzero(clip == N)[0]
        self.truth = simulation_truth(scene)
        if self.truth is None or self.truth.world_scale is None:
            raise ValueError("--views needs a simulation scene with its truth (the demo collection)")
        self.ws = float(self.truth.world_scale)
        # alignment: the training clips' frames (the frame the fit lives in: its cameras and initial cloud),
        # estimated -> true; the true test poses mapped into the fit's frame
        self._lifts: dict[int, dict] = {}
        est, true = self.alignment_pairs()
        self.test_c2w, self.align_scale, self.align = align_to_estimated(est, true, self.true_c2w[self.test])
        self.test_rgb, self.test_depth = [], []
        for f in self.test:
            r = render(self.truth.scene, self.truth.gt_pose(self.true_c2w[f][None])[0],
                       Intrinsics.from_matrix(self.K[f], self.w, self.h), supersample=2)
            self.test_rgb.append(r.rgb.astype(np.float64) / 255)
            self.test_depth.append(r.depth.astype(np.float64) * self.ws)
        self.cloud = load_cloud(scene, N - 1)
        self.backend = load_backend(scene, cfg)
        self._frames: dict[int, np.ndarray] = {}
        self._true_depth: dict[int, np.ndarray] = {}
        self._targets: dict[tuple[int, bool], np.ndarray | None] = {}

    def alignment_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Matched points [M, 3] (estimated frame, true frame) for the test-pose alignment: the pool's camera
        centres and, for every pool frame the lift ran on, its pixels (every ``ALIGN_STRIDE``-th) lifted with the
        geometry model's depth and camera and with the frame's true depth and camera (what it shows). Centres
        alone are degenerate when the training clips barely move (the paper preset's first clips turn in place:
        room-10's pool cameras lie within 0.007 of the origin, and a similarity from them mapped the test views
        off the scene: masked PSNR 7.8 dB, rendered depth AbsRel 0.99 in every variant)."""
        from navcrafter.models.gaussians.sparse import depth_pairs
        from navcrafter.tasks.readers import frame_truth

        est, true = [self.c2w[self.pool, :3, 3]], [self.true_c2w[self.pool, :3, 3]]
        for f in self.pool:
            k, i = self.refs[f]
            lift = self.lift(k)
            at = np.nonzero(np.asarray(lift["view_index"]) == i)[0]
            if not len(at):
                continue
            true_c2w, true_depth = frame_truth(self.scene, k, [i])
            if true_depth[0] is None:
                raise ValueError("--views needs the synthesize step's true_depth (a simulation scene)")
            pe, pt = depth_pairs(lift["depth"][at[0]], np.asarray(lift["c2w"][at[0]], dtype=np.float64),
                                 true_depth[0], true_c2w[0], np.asarray(lift["K"][at[0]], dtype=np.float64),
                                 valid=np.asarray(lift["confidence"][at[0]]) >= self.cfg.fit.depth_confidence,
                                 stride=ALIGN_STRIDE)
            est.append(pe)
            true.append(pt)
        return np.concatenate(est), np.concatenate(true)

    def lift(self, k: int) -> dict:
        """Clip k's lift (read once: the alignment and every depth target of its frames use it)."""
        from navcrafter.schemas.layout import LIFT

        if k not in self._lifts:
            self._lifts[k] = self.scene.read_all(LIFT, k)
        return self._lifts[k]

    def frame(self, f: int) -> np.ndarray:
        """Frame f at the synthesis size (uint8)."""
        from navcrafter.schemas.layout import SYNTHESIZE

        if f not in self._frames:
            k, i = self.refs[f]
            self._frames[f] = self.scene.read_rows(SYNTHESIZE, k, "frames", [i])[0]
        return self._frames[f]

    def scene_depth_at(self, f: int) -> np.ndarray:
        """The true scene's z-depth (world units) at frame f's true camera, the fit's size (visibility)."""
        from navcrafter.models.camera.cameras import Intrinsics
        from navcrafter.models.simulation.render import render

        if f not in self._true_depth:
            r = render(self.truth.scene, self.truth.gt_pose(self.true_c2w[f][None])[0],
                       Intrinsics.from_matrix(self.K[f], self.w, self.h), colour=False)
            self._true_depth[f] = r.depth.astype(np.float64) * self.ws
        return self._true_depth[f]

    def choose(self, views: int) -> np.ndarray:
        from navcrafter.models.gaussians.sparse import farthest_views

        if views > len(self.pool):
            raise ValueError(f"--views {views}: the training clips have only {len(self.pool)} frames; explore "
                             "more (--clips) or longer clips")
        return self.pool[farthest_views(self.c2w[self.pool, :3, 3], views)]

    def shown_truthfully(self, f: int) -> np.ndarray:
        """[h, w] bool: where frame f (a generated frame) shows the true scene, i.e. the depth of what it shows
        agrees with the true scene's depth at its true camera to ``VISIBILITY_TOL``. Elsewhere the video model
        hallucinated (moved objects, walls, re-coloured content): a fit trained on it learned the variant, not the
        truth, so such pixels witness nothing (tabletop-12's test clip was scored on a ball that the training
        frames of clip 2 showed elsewhere: 52-62 % of their pixels off by > 10 %)."""
        from navcrafter.models.gaussians.recipe import resize_depth
        from navcrafter.tasks.readers import frame_truth

        k, i = self.refs[f]
        _, shown = frame_truth(self.scene, k, [i])
        if shown[0] is None:
            raise ValueError("--views needs the synthesize step's true_depth (a simulation scene)")
        shown = resize_depth(np.asarray(shown[0], dtype=np.float32), self.h, self.w).astype(np.float64)
        true = self.scene_depth_at(f)
        return (true > 0) & np.isfinite(shown) & (np.abs(shown - true) <= VISIBILITY_TOL * true)

    def masks(self, train: np.ndarray) -> list[np.ndarray]:
        """Per test view: the pixels whose true surface point some training view saw unoccluded *and showed
        truthfully* (its generated frame agrees with the truth there: ``shown_truthfully``)."""
        from navcrafter.models.gaussians.sparse import visibility_mask

        td = np.stack([np.where(self.shown_truthfully(int(f)), self.scene_depth_at(int(f)), 0.0) for f in train])
        return [visibility_mask(d, self.true_c2w[f], self.K[f], td, self.true_c2w[train], self.K[train],
                                rel_tol=VISIBILITY_TOL) for d, f in zip(self.test_depth, self.test)]

    def depth_target(self, f: int, oracle: bool) -> np.ndarray | None:
        """Frame f's depth supervision (computed once; the monocular prediction is seeded by the frame)."""
        if (f, oracle) not in self._targets:
            self._targets[(f, oracle)] = self._depth_target(f, oracle)
        return self._targets[(f, oracle)]

    def _depth_target(self, f: int, oracle: bool) -> np.ndarray | None:
        """Frame f's depth supervision at the fit's size: the calibrated monocular depth as the fit step makes it
        (against the lift's geometry depth where it ran on the frame, else the cloud rendered into it), or with
        ``oracle`` the frame's true depth (what it shows, world units)."""
        from navcrafter.models.gaussians.recipe import resize_depth
        from navcrafter.models.reconstruction.depthcalib import CalibrationError, calibrate_depth
        from navcrafter.models.reconstruction.pointrender import render_points
        from navcrafter.tasks.readers import frame_truth

        k, i = self.refs[f]
        true_c2w, true_depth = frame_truth(self.scene, k, [i])
        if oracle:
            if true_depth[0] is None:
                raise ValueError("the oracle-depth control needs the synthesize step's true_depth")
            return resize_depth(np.asarray(true_depth[0], dtype=np.float32), self.h, self.w)
        fc = self.cfg.fit
        lift = self.lift(k)
        at = np.nonzero(np.asarray(lift["view_index"]) == i)[0]
        if len(at):
            d_v, valid = lift["depth"][at[0]], lift["confidence"][at[0]] >= fc.depth_confidence
        else:
            pr = render_points(self.cloud.points, self.c2w[f], self.K_full[f], self.H, self.W,
                               point_size=fc.depth_point_size)
            d_v, valid = pr.depth, pr.mask
        mono = self.backend.mono_depth.predict(self.frame(f), seed=self.seed + f, hint_c2w=true_c2w,
                                               hint_depth=true_depth[0])
        try:
            cal = calibrate_depth(mono.inv_depth, d_v, valid, mono.sky)
        except CalibrationError:
            return None
        return resize_depth(cal.depth, self.h, self.w)

    def train_views(self, train: np.ndarray, depth: str | None) -> list:
        """TrainViews of frames ``train`` at their estimated cameras; depth None / 'mono' / 'oracle'."""
        import torch

        from navcrafter.models.gaussians.recipe import resize_image
        from navcrafter.models.gaussians.train import TrainView

        out = []
        for f in train:
            f = int(f)
            img = resize_image(self.frame(f), self.h, self.w).astype(np.float32) / 255.0
            d = self.depth_target(f, depth == "oracle") if depth else None
            out.append(TrainView(torch.from_numpy(img), torch.as_tensor(self.c2w[f], dtype=torch.float32),
                                 torch.as_tensor(self.K[f], dtype=torch.float32),
                                 None if d is None else torch.from_numpy(np.ascontiguousarray(d, dtype=np.float32))))
        return out

    def test_views(self) -> list:
        import torch

        from navcrafter.models.gaussians.train import TrainView

        return [TrainView(torch.from_numpy(rgb.astype(np.float32)), torch.as_tensor(c, dtype=torch.float32),
                          torch.as_tensor(self.K[f], dtype=torch.float32))
                for rgb, c, f in zip(self.test_rgb, self.test_c2w, self.test)]


def score(sc: SparseScene, rgb: np.ndarray, depth: np.ndarray, masks: list[np.ndarray], lpips_model=None) -> dict:
    """Masked PSNR / SSIM (/ LPIPS) and depth AbsRel (rendered depth x the alignment's scale) over the test
    views, each the mean over views with a non-empty mask."""
    from navcrafter.models.gaussians.sparse import depth_absrel, masked_psnr, masked_ssim

    ps, ss, ds, lp = [], [], [], []
    for j, m in enumerate(masks):
        if not m.any():
            continue
        gt = sc.test_rgb[j]
        ps.append(masked_psnr(rgb[j], gt, m))
        ss.append(masked_ssim(rgb[j], gt, m))
        ds.append(depth_absrel(depth[j] * sc.align_scale, sc.test_depth[j], m))
        if lpips_model is not None:
            from navcrafter.models.metrics.evalnets.lpips import lpips_distance

            comp = np.where(m[..., None], rgb[j], gt)
            lp.append(float(np.mean(lpips_distance(comp[None], gt[None], model=lpips_model))))
    if not ps:
        raise ValueError("no test pixel was seen by any training view; nothing to score")
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "depth_absrel": float(np.nanmean(ds)),
            "lpips": float(np.mean(lp)) if lp else None, "n_test_views": len(ps)}


def masked_l1(sc: SparseScene, rgb: np.ndarray, masks: list[np.ndarray]) -> float:
    return float(np.mean([np.abs(rgb[j] - sc.test_rgb[j])[m].mean() for j, m in enumerate(masks) if m.any()]))


def grid_name(space: str, lam: float, default_space: str) -> str:
    """A tuning row's variant name: ``depth@lambda``, with its space where it is not the run's."""
    return f"depth@{lam:g}" if space == default_space else f"depth@{space}:{lam:g}"


def parse_grid(text: str | None, default_space: str) -> tuple:
    """``--lambda-grid``: comma-separated ``lambda`` or ``space:lambda`` entries (default: LAMBDA_GRID)."""
    if not text:
        return tuple((default_space, lam) for lam in LAMBDA_GRID)
    out = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        space, _, lam = item.rpartition(":")
        space = space or default_space
        if space not in DEPTH_SPACES:
            raise SystemExit(f"--lambda-grid {item!r}: the depth space must be one of {DEPTH_SPACES}")
        out.append((space, float(lam)))
    return tuple(out)


def sparse_fit(sc: SparseScene, train: np.ndarray, masks, *, iterations: int, lambda_depth: float,
               drop_gamma: float, depth: str | None, init_fraction: float = 1.0, lpips_model=None,
               depth_space: str = "median") -> tuple:
    """One fit on the chosen frames; (record, trainer, train views, scene scale)."""
    from navcrafter.models.gaussians.model import GaussianModel
    from navcrafter.models.gaussians.recipe import init_subset, scene_scale
    from navcrafter.models.gaussians.sparse import converged
    from navcrafter.models.gaussians.train import GaussianTrainer

    fc = fit_settings(sc.cfg.fit, iterations, lambda_depth, drop_gamma, depth_space)
    views = sc.train_views(train, depth if lambda_depth > 0 else None)
    n = min(sc.cfg.fit.max_init_points or len(sc.cloud.points), len(sc.cloud.points))
    pts, cols = init_subset(sc.cloud.points, sc.cloud.colors, max(1, int(round(init_fraction * n))), sc.seed)
    init = GaussianModel.from_point_cloud(pts, cols, sh_degree=fc.sh_degree)
    scale = scene_scale(sc.c2w[train], pts)
    trainer = GaussianTrainer(init, views, fc, scene_scale=scale, seed=sc.seed, lambda_lpips=0.0)
    tests = sc.test_views()
    checks = {int(round(p * iterations)) - 1: p for p in (0.6, 0.8, 1.0)}
    curve: list[float] = []

    def check(step: int, _rec: dict) -> None:
        if step in checks:
            curve.append(masked_l1(sc, trainer.evaluate(tests)[0], masks))

    t0 = time.perf_counter()
    result = trainer.train(check)
    seconds = time.perf_counter() - t0
    rgb, d = trainer.evaluate(tests)
    ok, change = converged(curve, CONVERGENCE_TOL)
    rec = {**score(sc, rgb, d, masks, lpips_model), "iterations": iterations, "n_gaussians": len(result.model),
           "n_init": len(pts), "n_depth_views": sum(v.depth is not None for v in views),
           "heldout_l1_at_60_80_100": curve, "converged": ok, "heldout_l1_change_last20": change,
           "train_seconds": seconds}
    return rec, trainer, views, scale


def sparse_continue(sc: SparseScene, trainer, views, masks, scale: float, iterations: int, refine: bool,
                    lambda_depth: float, lpips_model=None) -> dict:
    """The ``longer`` control (``iterations`` more on the real views) or ``refine`` (plus refined novel views
    next to the training cameras, as the refine step makes them, with their calibrated depth)."""
    import torch

    from navcrafter.models.camera.cameras import Intrinsics
    from navcrafter.models.gaussians.novelviews import nearest_views, novel_cameras
    from navcrafter.models.gaussians.recipe import continuation_trainer
    from navcrafter.models.gaussians.sparse import converged
    from navcrafter.models.gaussians.train import TrainView, render_model
    from navcrafter.models.reconstruction.depthcalib import CalibrationError, calibrate_depth
    from navcrafter.models.reconstruction.pointrender import render_points

    fc, rc = trainer.config, sc.cfg.refine.model_copy(update={"iterations": iterations})
    model = trainer.model
    extra = []
    if refine:
        if sc.backend.refiner is None:
            raise RuntimeError("the refine variant needs the backend's Refiner role")
        c2w_tr = torch.stack([v.c2w for v in views]).double().numpy()
        K = views[0].K.double().numpy()
        rng = np.random.default_rng(sc.seed)
        c2w, _ = novel_cameras(c2w_tr, np.arange(len(views))[:rc.views], model.means.numpy(),
                               offset=rc.offset * scale, angle_deg=rc.angle_deg, rng=rng)
        renders = render_model(model, c2w, np.repeat(K[None], len(c2w), 0), sc.w, sc.h)
        ref = nearest_views(c2w, c2w_tr)
        if hasattr(sc.backend.refiner, "observe"):
            sc.backend.refiner.observe(sc.cloud.points)
        intr = Intrinsics.from_matrix(K, sc.w, sc.h)
        for i in range(len(c2w)):
            ref_img = np.round(views[int(ref[i])].image.numpy() * 255).astype(np.uint8)
            out = sc.backend.refiner.refine(renders[i], ref_img, seed=sc.seed + i, hint_c2w=c2w[i],
                                            hint_intrinsics=intr)
            d = None
            if lambda_depth > 0 and rc.depth:
                pr = render_points(sc.cloud.points, c2w[i], K, sc.h, sc.w, point_size=fc.depth_point_size)
                mono = sc.backend.mono_depth.predict(out, seed=sc.seed + 7919 + i, hint_c2w=c2w[i])
                try:
                    d = torch.from_numpy(np.ascontiguousarray(
                        calibrate_depth(mono.inv_depth, pr.depth, pr.mask, mono.sky).depth, dtype=np.float32))
                except CalibrationError:
                    d = None
            extra.append(TrainView(torch.from_numpy(out.astype(np.float32) / 255.0),
                                   torch.as_tensor(c2w[i], dtype=torch.float32),
                                   torch.as_tensor(K, dtype=torch.float32), d, rc.weight))
    tests = sc.test_views()
    curve: list[float] = []
    checks = {int(round(p * iterations)) - 1 for p in (0.6, 0.8, 1.0)}

    def check(step: int, _rec: dict) -> None:
        if step in checks:
            curve.append(masked_l1(sc, tr2.evaluate(tests)[0], masks))

    tr2 = continuation_trainer(model, views + extra, fc, rc, sc.seed, scale)
    t0 = time.perf_counter()
    result = tr2.train(check)
    seconds = time.perf_counter() - t0
    rgb, d = tr2.evaluate(tests)
    ok, change = converged(curve, CONVERGENCE_TOL)
    return {**score(sc, rgb, d, masks, lpips_model), "iterations": fc.iterations + iterations,
            "n_gaussians": len(result.model), "n_refined_views": len(extra),
            "heldout_l1_at_60_80_100": curve, "converged": ok, "heldout_l1_change_last20": change,
            "train_seconds": seconds}


def run_sparse(quick: bool, seeds: tuple[int, int], kinds: tuple[str, ...], views: list[int], *,
               lambda_depth: float, iterations: int, refine_fraction: float, clips: int, weights: str | None,
               tune: bool = False, on_scene=None, depth_space: str = "median",
               grid: tuple = ()) -> list[dict]:
    """Every scene x views x variant; one record each (scene, kind, seed, views, variant, scores...)."""
    from navcrafter.models.gaussians.recipe import load_lpips

    over = sparse_overrides(quick, clips, weights)
    cfg = RunConfig.load(preset="tiny" if quick else "paper", overrides=over)
    lpips_model, _ = load_lpips(cfg.evaluation)
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="navcrafter-sparsebench-") as tmp:
        photos = Path(tmp) / "photos"
        paths = [p for seed in range(seeds[0], seeds[1] + 1) for p in write_demo_collection(
            photos, kinds=kinds, per_kind=1, seed=seed, width=320, height=240, supersample=1)]
        paths = sorted(paths, key=lambda p: (int(p.stem.rsplit("-", 1)[1]), kinds.index(p.stem.rsplit("-", 1)[0])))
        store = str(Path(tmp) / "store")
        for photo in paths:
            res = ingest(store, str(photo), cfg, "bench")
            if not res.ok:
                raise RuntimeError(res.error)
            t0 = time.perf_counter()
            run_scene(store, res.scene_id, cfg, "bench")
            seed = int(photo.stem.rsplit("-", 1)[1])
            sc = SparseScene(Store(store).scene(res.scene_id), cfg, seed)
            explore_s = time.perf_counter() - t0
            for V in views:
                train = sc.choose(V)
                masks = sc.masks(train)
                base = {"photo": photo.name, "kind": photo.name.split("-")[0], "seed": seed, "views": V,
                        "train_frames": [list(map(int, sc.refs[f])) for f in train],
                        "n_test_views": len(sc.test), "visible_fraction": float(np.mean([m.mean() for m in masks])),
                        "align_scale": sc.align_scale, "align_rmse": sc.align["rmse"], "explore_seconds": explore_s}

                def add(variant: str, rec: dict, base=base, V=V) -> None:
                    rows.append({**base, "variant": variant, **rec})
                    print(f"{base['photo']:16s} V={V:<3d} {variant:20s} PSNR {rec['psnr']:.2f} SSIM {rec['ssim']:.3f} "
                          f"AbsRel {rec['depth_absrel']:.3f} conv {rec['converged']} "
                          f"({rec['heldout_l1_change_last20']:.3f}) {rec['train_seconds']:.1f} s", flush=True)

                kw = {"iterations": iterations, "lpips_model": lpips_model, "depth_space": depth_space}
                add("none", sparse_fit(sc, train, masks, lambda_depth=0.0, drop_gamma=0.0, depth=None, **kw)[0])
                if tune:
                    for space, lam in grid:
                        add(grid_name(space, lam, depth_space),
                            sparse_fit(sc, train, masks, lambda_depth=lam, drop_gamma=0.0, depth="mono",
                                       **{**kw, "depth_space": space})[0])
                    continue
                add("depth", sparse_fit(sc, train, masks, lambda_depth=lambda_depth, drop_gamma=0.0, depth="mono",
                                        **kw)[0])
                rec, trainer, tviews, scale = sparse_fit(sc, train, masks, lambda_depth=lambda_depth,
                                                         drop_gamma=DROP_GAMMA, depth="mono", **kw)
                add("dropgaussian", rec)
                more = max(10, int(round(refine_fraction * iterations)))
                for name, ref in (("longer", False), ("refine", True)):
                    add(name, sparse_continue(sc, trainer, tviews, masks, scale, more, ref, lambda_depth,
                                              lpips_model))
                add("oracle_depth", sparse_fit(sc, train, masks, lambda_depth=lambda_depth, drop_gamma=0.0,
                                               depth="oracle", **kw)[0])
                add("sparse_init", sparse_fit(sc, train, masks, lambda_depth=0.0, drop_gamma=0.0, depth=None,
                                              init_fraction=SPARSE_INIT_FRACTION, **kw)[0])
                add("sparse_init_depth", sparse_fit(sc, train, masks, lambda_depth=lambda_depth, drop_gamma=0.0,
                                                    depth="mono", init_fraction=SPARSE_INIT_FRACTION, **kw)[0])
            if on_scene is not None:
                on_scene(rows)
    return rows


def _stats(x: np.ndarray) -> tuple[float, float | None]:
    return float(x.mean()), (float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else None)


def sparse_results(rows: list[dict], protocol: dict) -> dict:
    """``{"protocol", "views": {V: {variant: {...}}}, "paired": {V: {component: {...}}}}``."""
    views: dict[str, dict] = {}
    paired: dict[str, dict] = {}
    for V in sorted({r["views"] for r in rows}):
        sel = [r for r in rows if r["views"] == V]
        vv = {}
        for variant in dict.fromkeys(r["variant"] for r in sel):
            fits = [r for r in sel if r["variant"] == variant]
            arr = {k: np.array([f[k] for f in fits], dtype=np.float64) for k in ("psnr", "ssim", "depth_absrel")}
            lp = [f["lpips"] for f in fits if f["lpips"] is not None]
            vv[variant] = {"psnr": float(arr["psnr"].mean()), "ssim": float(arr["ssim"].mean()),
                           "depth_absrel": float(np.nanmean(arr["depth_absrel"])),
                           "lpips": float(np.mean(lp)) if len(lp) == len(fits) else None,
                           "psnr_std": float(arr["psnr"].std()), "n": len(fits),
                           "converged": sum(bool(f["converged"]) for f in fits),
                           "visible_fraction": float(np.mean([f["visible_fraction"] for f in fits])),
                           "fits": [{k: f[k] for k in ("photo", "kind", "seed", "psnr", "ssim", "depth_absrel",
                                                       "lpips", "converged", "heldout_l1_change_last20",
                                                       "heldout_l1_at_60_80_100", "iterations", "n_gaussians",
                                                       "visible_fraction", "align_rmse", "train_seconds")}
                                    for f in fits]}
        views[str(V)] = vv
        by = {(r["photo"], r["variant"]): r for r in sel}
        photos = sorted({r["photo"] for r in sel})
        pv = {}
        for comp, (a, b) in PAIRS.items():
            pairs = [(by[(p, a)], by[(p, b)]) for p in photos if (p, a) in by and (p, b) in by]
            if not pairs:
                continue
            dp = np.array([y["psnr"] - x["psnr"] for x, y in pairs])
            ds = np.array([y["ssim"] - x["ssim"] for x, y in pairs])
            dd = np.array([y["depth_absrel"] - x["depth_absrel"] for x, y in pairs])
            m, se = _stats(dp)
            md, sed = _stats(dd)
            pv[comp] = {"from": a, "to": b, "delta_psnr": m, "delta_ssim": float(ds.mean()),
                        "delta_depth_absrel": md, "se": se, "se_depth_absrel": sed,
                        "wins": int((dp > 0).sum()), "wins_depth": int((dd < 0).sum()), "n": len(pairs)}
        paired[str(V)] = pv
    return {"protocol": protocol, "views": views, "paired": paired}


def merge_sparse(results: list[dict]) -> dict:
    """One ``results.json`` from runs of the same protocol over different seeds or view counts (``--merge``): the
    per-fit records are pooled and the tables and pairs recomputed; a fit found in two runs (same view count,
    photo and variant) is refused."""
    keys = ("quick", "clips", "iterations", "continue_iterations", "resolution", "lambda_depth",
            "depth_space", "drop_gamma", "sparse_init_fraction", "convergence_tol", "visibility_tol",
            "witness")
    p0 = results[0]["protocol"]
    for r in results[1:]:
        diff = [k for k in keys if r["protocol"].get(k) != p0.get(k)]
        if diff:
            raise ValueError(f"cannot merge runs of different protocols (they differ in {diff})")
    rows = [{**f, "views": int(V), "variant": name} for r in results for V, vv in r["views"].items()
            for name, s in vv.items() for f in s["fits"]]
    seen: set[tuple] = set()
    for r in rows:
        key = (r["views"], r["photo"], r["variant"])
        if key in seen:
            raise ValueError(f"the fit {key} is in two of the merged runs: merge runs of other seeds or view counts")
        seen.add(key)
    seeds = sorted({r["seed"] for r in rows})
    protocol = {**p0, "seeds": [seeds[0], seeds[-1]], "seed_list": seeds,
                "views": sorted({r["views"] for r in rows}),
                "kinds": sorted({k for r in results for k in r["protocol"]["kinds"]}),
                "development": any(r["protocol"]["development"] for r in results),
                "complete": all(r["protocol"]["complete"] for r in results),
                "n_scenes": len({r["photo"] for r in rows}), "merged_from": len(results)}
    return sparse_results(rows, protocol)


def sparse_markdown(res: dict) -> str:
    p = res["protocol"]
    lines = [f"# 3DGS fitting ablation, sparse views (Table VI shape){' — quick' if p['quick'] else ''}", "",
             f"*{LABEL}, honest preset.* Seeds {p['seeds'][0]}-{p['seeds'][1]} of {', '.join(p['kinds'])} "
             f"({'DEVELOPMENT range' if p['development'] else 'held out: nothing was tuned on them'}); "
             f"{p['n_scenes']} scenes.", "",
             f"Protocol: {p['description']}", "",
             f"Fit: {p['iterations']} iterations at {p['resolution'][0]}x{p['resolution'][1]} (longer / refine: "
             f"+{p['continue_iterations']}); " + (
                 f"lambda_depth tuned over {p['lambda_grid']} in {p['depth_space']} depth (the depth@lambda rows): "
                 f"mean masked PSNR over views and scenes {p.get('lambda_scores')}, choice "
                 f"**{p.get('lambda_choice')}**" if p.get("lambda_grid") else
                 f"lambda_depth {p['lambda_depth']} in {p['depth_space']} depth ({p['lambda_source']})") +
             f"; DropGaussian gamma {p['drop_gamma']} over the whole fit.", "",
             "| views | variant | n | masked PSNR (dB) | masked SSIM | LPIPS | depth AbsRel | converged | "
             "visible px |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for V, vv in res["views"].items():
        for name, s in vv.items():
            lp = f"{s['lpips']:.3f}" if s["lpips"] is not None else "n/a"
            lines.append(f"| {V} | {name} | {s['n']} | {s['psnr']:.2f} ± {s['psnr_std']:.2f} | {s['ssim']:.3f} | "
                         f"{lp} | {s['depth_absrel']:.3f} | {s['converged']}/{s['n']} | "
                         f"{100 * s['visible_fraction']:.0f} % |")
    lines += ["", "Paired by scene (b − a; se: standard error of the mean difference, n − 1; wins: scenes where "
              "b's PSNR is higher / its AbsRel lower):", "",
              "| views | component | a → b | n | Δ PSNR (dB) | se | wins | Δ AbsRel | se | wins (depth) |",
              "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for V, pv in res["paired"].items():
        for comp, g in pv.items():
            se = f"{g['se']:.2f}" if g["se"] is not None else "n/a"
            sed = f"{g['se_depth_absrel']:.3f}" if g["se_depth_absrel"] is not None else "n/a"
            lines.append(f"| {V} | {comp} | {g['from']} → {g['to']} | {g['n']} | {g['delta_psnr']:+.2f} | {se} | "
                         f"{g['wins']}/{g['n']} | {g['delta_depth_absrel']:+.3f} | {sed} | "
                         f"{g['wins_depth']}/{g['n']} |")
    return "\n".join(lines) + "\n"


def sparse_main(args, seeds: tuple[int, int], kinds: tuple[str, ...]) -> str:
    views = [int(v) for v in args.views.split(",") if v]
    if args.tune_lambda and not is_development(seeds):
        raise SystemExit("--tune-lambda runs on development seeds only (0-9): pass --seeds within 0-9")
    grid = parse_grid(args.lambda_grid, args.depth_space)
    iterations = args.fit_iterations or (300 if args.quick else 1500)
    cfg = RunConfig.load(preset="tiny" if args.quick else "paper",
                         overrides=sparse_overrides(args.quick, args.clips, args.eval_weights))
    from navcrafter.models.gaussians.recipe import fit_size, load_lpips

    h, w = fit_size(cfg.synthesis.height, cfg.synthesis.width, cfg.fit.resolution)
    protocol = {
        "quick": args.quick, "seeds": list(seeds), "kinds": list(kinds), "development": is_development(seeds),
        "views": views, "clips": args.clips, "label": LABEL, "iterations": iterations,
        "continue_iterations": max(10, int(round(args.refine_fraction * iterations))), "resolution": [w, h],
        "lambda_depth": args.lambda_depth, "lambda_source": args.lambda_source, "depth_space": args.depth_space,
        "drop_gamma": DROP_GAMMA, "lambda_grid": [list(g) for g in grid] if args.tune_lambda else None,
        "sparse_init_fraction": SPARSE_INIT_FRACTION, "convergence_tol": CONVERGENCE_TOL,
        "visibility_tol": VISIBILITY_TOL, "witness": "seen and shown truthfully",
        "lpips_note": load_lpips(cfg.evaluation)[1], "complete": False,
        "description": ("train on V frames chosen by farthest-point sampling of the estimated camera centres of "
                        "clips 1..N-1, initialised from the cloud of those clips; test on every frame of clip N "
                        "(held out whole) against the true scene rendered at its true camera, mapped into the "
                        "fit's estimated frame by an Umeyama similarity over the training clips' camera centres "
                        "and their pixels lifted with estimated and true depth "
                        "(rendered depth x its scale); PSNR/SSIM/LPIPS/depth AbsRel only over test pixels whose true "
                        "surface point a training view saw unoccluded (true depths, 3 % tolerance, sky excluded) and "
                        "showed truthfully (its generated frame's depth within 3 % of the true depth there: "
                        "hallucinated content witnesses nothing). "
                        "Convergence: held-out masked L1 changed <= 2 % over the last 20 % of the fit."),
    }

    def write(rows: list[dict], done: bool = False) -> str:
        protocol.update(complete=done, n_scenes=len({r["photo"] for r in rows}))
        res = sparse_results(rows, protocol)
        if args.tune_lambda and rows:
            names = [grid_name(space, lam, args.depth_space) for space, lam in grid]
            score_of = {n: np.mean([s["psnr"] for vv in res["views"].values() for k, s in vv.items() if k == n])
                        for n in names}
            protocol["lambda_scores"] = {n.removeprefix("depth@"): float(v) for n, v in score_of.items()}
            protocol["lambda_choice"] = max(score_of, key=score_of.get).removeprefix("depth@")
            res = sparse_results(rows, protocol)
        (args.out / "results.json").write_text(json.dumps(res, indent=1))
        md = sparse_markdown(res)
        if not done:
            md = "**Partial results (the run is still going or was stopped).**\n\n" + md
        (args.out / "results.md").write_text(md)
        return md

    rows = run_sparse(args.quick, seeds, kinds, views, lambda_depth=args.lambda_depth, iterations=iterations,
                      refine_fraction=args.refine_fraction, clips=args.clips, weights=args.eval_weights,
                      tune=args.tune_lambda, on_scene=write, depth_space=args.depth_space, grid=grid)
    return write(rows, done=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", action="store_true", help="1 seed, the tiny preset (about a minute)")
    ap.add_argument("--seeds", type=parse_seeds, default=None, help="scene seeds A-B of every kind (default 10-12, "
                    "quick 10-10; 0-9 is the development range); a single N means 0-(N-1)")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--eval-weights", default=None, help="folder with the official LPIPS weights")
    ap.add_argument("--views", default=None, help="sparse views: comma-separated training-view counts (e.g. "
                    "3,6,12); the protocol of the module's docstring")
    ap.add_argument("--clips", type=int, default=3, help="--views: clips explored; the last is held out")
    ap.add_argument("--fit-iterations", type=int, default=None, help="--views: iterations of each fit "
                    "(default 1500, quick 300)")
    ap.add_argument("--refine-fraction", type=float, default=0.5, help="--views: longer/refine add this x the "
                    "fit's iterations")
    ap.add_argument("--lambda-depth", type=float, default=0.1, help="--views: weight of the median-normalised "
                    "depth term (choose it with --tune-lambda on development seeds)")
    ap.add_argument("--lambda-source", default="the 'light' weighting's value, not tuned by this protocol",
                    help="--views: where --lambda-depth comes from (recorded in the protocol)")
    ap.add_argument("--depth-space", default="median", choices=DEPTH_SPACES, help="--views: the depth term's "
                    "scale-free space (fit.depth_space): 'median' |ED - D| / median(D), 'relative' |ED - D| / (ED + D)")
    ap.add_argument("--lambda-grid", default=None, help="--tune-lambda: comma-separated lambda or space:lambda "
                    f"entries (default {','.join(f'{x:g}' for x in LAMBDA_GRID)} in --depth-space)")
    ap.add_argument("--tune-lambda", action="store_true", help="--views, development seeds only: fit none and "
                    f"depth at lambda_depth in {LAMBDA_GRID}, and name the best by mean masked PSNR")
    ap.add_argument("--merge", default=None, help="--views: comma-separated output folders of runs of the same "
                    "protocol over other seeds; writes their pooled results.json / results.md into --out")
    args = ap.parse_args(argv)
    if args.merge:
        res = merge_sparse([json.loads((Path(d) / "results.json").read_text()) for d in args.merge.split(",") if d])
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.json").write_text(json.dumps(res, indent=1))
        md = sparse_markdown(res)
        (args.out / "results.md").write_text(md)
        print(md)
        return 0
    seeds = args.seeds or ((10, 10) if args.quick else (10, 12))
    kinds = tuple(k for k in args.kinds.split(",") if k)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.views:
        print(sparse_main(args, seeds, kinds))
        return 0

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

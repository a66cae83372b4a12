"""Profile of the 3DGS fit step at the demo's defaults: each part's share of an iteration, and of the step.

One demo scene (``--kind``, ``--seed``; the demo collection's generator) is explored at the paper's settings (the
demo's: 3 iterations of 81 frames at 256x256, fit off), then the ``fit`` step runs at its defaults
(``schemas/config.py``: 128 px, 500 iterations, <= 50k Gaussians, the paper's loss) with timers wrapped around
its parts (in this script only; the product code is not changed):

* per iteration: rasterization forward (covariances, projection, binning, sorting, compositing: the compiled
  kernels' autograd functions) and backward (the same functions' backward passes), SH evaluation (forward; its
  backward is in "other backward"), the loss terms (L1, LPIPS when its weights are given, the depth term),
  DropGaussian, density control (both strategy hooks), the optimizers, "other backward" (autograd outside the
  rasterizer: SH, losses, activations) and the rest (view choice, zero_grad, history: "other");
* per step, once: reading frames and resizing (data loading), monocular depth (the simulated role) and its
  calibration, the cloud rendered into frames (depth targets), evaluation renders, and training as a whole.

A timed part nested in another (SH inside the renderer call, the rasterizer's backward inside ``backward()``) is
charged to the inner part only.

    python benchmarks/fit_profile.py --out bench-out/fit-profile                 # room, seed 0, ~4 min idle
    python benchmarks/fit_profile.py --out bench-out/fit-profile --store /tmp/s  # keeps / reuses the explored scene
    python benchmarks/fit_profile.py --out DIR --iterations 100                  # a shorter fit (schedule as is)

Writes ``results.json`` and ``results.md`` into ``--out``. Times are wall times on a shared machine: the shares
(parts over the same run's total) are what to compare; ``nproc`` and the load average are recorded.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI sets it (torch's OpenMP threads beside numba's)

import torch  # noqa: E402

from navcrafter.models.gaussians import cpu_rasterize, dropgaussian, train  # noqa: E402
from navcrafter.models.gaussians import rasterize as rasterize_module  # noqa: E402
from navcrafter.models.simulation.backend import SimulationMonoDepth  # noqa: E402
from navcrafter.models.simulation.demo import write_demo_collection  # noqa: E402
from navcrafter.schemas.config import RunConfig  # noqa: E402
from navcrafter.schemas.layout import STEPS  # noqa: E402
from navcrafter.schemas.store import Store  # noqa: E402
from navcrafter.tasks import fit as fit_task  # noqa: E402
from navcrafter.tasks import steps  # noqa: E402
from navcrafter.tasks.ingest import ingest  # noqa: E402
from navcrafter.tasks.runner import body_of, run_scene  # noqa: E402

SECONDS: dict[str, float] = defaultdict(float)
CALLS: dict[str, int] = defaultdict(int)
_ACTIVE: list[str] = []  # the stack of timed parts (nested parts are charged to the innermost only)


def timed(name: str, fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        _ACTIVE.append(name)
        try:
            return fn(*args, **kwargs)
        finally:
            _ACTIVE.pop()
            dt = time.perf_counter() - t0
            SECONDS[name] += dt
            CALLS[name] += 1
            if _ACTIVE:  # the parent keeps only its own time (its parent subtracts the parent's whole time)
                SECONDS[_ACTIVE[-1]] -= dt
    return wrapper


def instrument() -> None:
    """Wrap the fit's parts in timers (this process only)."""
    train.rasterize = timed("rasterization forward", train.rasterize)  # the renderer call, SH charged apart
    # every autograd function of the compiled renderer but the SH (charged to "other backward"); _ProjectQS, the
    # default projection since raster21, was missing here until raster22 (its backward went to "other backward")
    for name in ("_Covar", "_Project", "_ProjectQS", "_Composite"):
        if hasattr(cpu_rasterize, name):
            cls = getattr(cpu_rasterize, name)
            cls.backward = staticmethod(timed("rasterization backward", cls.backward))
    rasterize_module.resolve_colors = timed("SH evaluation (forward)", rasterize_module.resolve_colors)
    if hasattr(cpu_rasterize, "resolve_colors"):  # the compiled SH (its backward is in "other backward")
        cpu_rasterize.resolve_colors = timed("SH evaluation (forward)", cpu_rasterize.resolve_colors)
    if hasattr(cpu_rasterize, "sh_colors"):  # the fit's SH on the compiled kernels (sh_dc, sh_rest apart)
        cpu_rasterize.sh_colors = timed("SH evaluation (forward)", cpu_rasterize.sh_colors)
    T = train.GaussianTrainer
    T.losses = timed("losses (forward)", T.losses)
    T.step = timed("iteration", T.step)
    T.evaluate = timed("evaluation renders (step)", T.evaluate)
    dropgaussian.DropGaussian.__call__ = timed("DropGaussian", dropgaussian.DropGaussian.__call__)
    for cls in (train.DefaultStrategy, train.NoStrategy):
        cls.step_pre_backward = timed("densification", cls.step_pre_backward)
        cls.step_post_backward = timed("densification", cls.step_post_backward)
    torch.optim.Adam.step = timed("optimizer", torch.optim.Adam.step)
    torch.Tensor.backward = timed("other backward (SH, losses, activations)", torch.Tensor.backward)
    fit_task.calibrate_depth = timed("depth calibration (step)", fit_task.calibrate_depth)
    fit_task.render_points = timed("cloud rendered into frames (step)", fit_task.render_points)
    fit_task.resize_image = timed("data loading: resize (step)", fit_task.resize_image)
    fit_task.frame_truth = timed("data loading: read (step)", fit_task.frame_truth)
    SimulationMonoDepth.predict = timed("monocular depth, simulated role (step)", SimulationMonoDepth.predict)
    fit_task.load_lpips = timed("LPIPS weights (step)", fit_task.load_lpips)
    fit_task.heldout_metrics = timed("held-out metrics (step)", fit_task.heldout_metrics)


ITERATION_PARTS = ["rasterization forward", "rasterization backward", "SH evaluation (forward)", "losses (forward)",
                   "other backward (SH, losses, activations)", "DropGaussian", "densification", "optimizer"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--kind", default="room")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--store", default=None, help="keep the explored scene here (reused when run again)")
    ap.add_argument("--iterations", type=int, default=None, help="fit.iterations (default: the config's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="further fit overrides")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    overrides: dict = {"fit.enabled": True}
    if args.iterations:
        overrides["fit.iterations"] = args.iterations
    for kv in args.set:
        k, v = kv.split("=", 1)
        overrides[k] = json.loads(v) if v[:1].isdigit() or v in ("true", "false", "null") else v
    with tempfile.TemporaryDirectory(prefix="navcrafter-fitprofile-") as tmp:
        store = args.store or str(Path(tmp) / "store")
        photo = write_demo_collection(Path(tmp) / "photos", kinds=(args.kind,), per_kind=1, seed=args.seed)[0]
        base = RunConfig.load(preset="paper", overrides={"fit.enabled": False})
        res = ingest(store, str(photo), base, "bench")
        if not res.ok:
            raise RuntimeError(res.error)
        t0 = time.perf_counter()
        run_scene(store, res.scene_id, base, "bench")
        print(f"{photo.name}: explored ({time.perf_counter() - t0:.0f} s)", flush=True)
        cfg = RunConfig.load(preset="paper", overrides=overrides)
        instrument()
        load_before = os.getloadavg()
        t0 = time.perf_counter()
        # the step's body under its own seed, always run (a complete fit in --store would make steps.run skip);
        # the group is committed under a key of its own, so a real run recomputes it
        scene = Store(store).scene(res.scene_id)
        spec = STEPS["fit"]
        seed = steps.step_seed(res.scene_id, spec, None, cfg, steps.step_key(scene, spec, None, cfg))
        writer = scene.begin(spec, None, f"fit-profile-{time.time_ns()}", cfg.backend)
        attrs = body_of(spec)(steps.StepContext(scene, None, cfg, seed, writer, "bench", None))
        step_s = time.perf_counter() - t0
        writer.commit(step_s, **attrs)
        load_after = os.getloadavg()
    n_it = CALLS["iteration"]
    iteration_s = sum(SECONDS[p] for p in ITERATION_PARTS) + SECONDS["iteration"]  # "iteration" keeps the rest
    parts = {p: SECONDS[p] for p in ITERATION_PARTS}
    parts["other (view choice, zero_grad, activations forward, history)"] = SECONDS["iteration"]
    raster = parts["rasterization forward"] + parts["rasterization backward"]
    step_parts = {k: v for k, v in SECONDS.items() if k.endswith("(step)")}
    step_parts["training (all iterations)"] = iteration_s
    step_parts["rest of the step (frames, init, writing)"] = step_s - sum(step_parts.values())
    result = {
        "benchmark": "fit_profile", "kind": args.kind, "seed": args.seed, "overrides": overrides,
        "fit": {k: attrs.get(k) for k in ("resolution", "n_gaussians", "n_train", "psnr", "train_seconds",
                                          "renderer", "lpips_note")},
        "machine": f"{platform.machine()}, nproc {os.cpu_count()}", "python": sys.version.split()[0],
        "torch_threads": torch.get_num_threads(), "load_average_before_after": [load_before, load_after],
        "iterations": n_it, "iteration_ms": 1000 * iteration_s / max(n_it, 1),
        "iteration_parts_ms": {k: 1000 * v / max(n_it, 1) for k, v in parts.items()},
        "iteration_shares": {k: v / iteration_s for k, v in parts.items()},
        "non_rasterization_share": 1 - raster / iteration_s,
        "step_seconds": step_s, "step_parts_s": step_parts,
    }
    (args.out / "results.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        "# Fit profile", "",
        f"Scene: demo {args.kind}, seed {args.seed}, explored at the paper's settings; fit at the defaults "
        f"({json.dumps(overrides)}): {attrs.get('resolution')} px, {attrs.get('n_train')} training views, "
        f"{attrs.get('n_gaussians')} Gaussians at the end, renderer {attrs.get('renderer')}; {result['machine']}, "
        f"load average {'/'.join(f'{x:.1f}' for x in load_before)} before, "
        f"{'/'.join(f'{x:.1f}' for x in load_after)} after.", "",
        f"One iteration: {result['iteration_ms']:.1f} ms (mean of {n_it}).", "",
        "| part of an iteration | ms | share |", "|---|---:|---:|",
    ]
    for k, v in parts.items():
        lines.append(f"| {k} | {1000 * v / max(n_it, 1):.1f} | {100 * v / iteration_s:.1f} % |")
    lines += ["", f"Everything but rasterization: **{100 * result['non_rasterization_share']:.1f} %** of an "
              "iteration (goal <= 30 %).", "", f"The step: {step_s:.1f} s.", "", "| part of the step | s | share |",
              "|---|---:|---:|"]
    for k, v in step_parts.items():
        lines.append(f"| {k} | {v:.1f} | {100 * v / step_s:.1f} % |")
    (args.out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

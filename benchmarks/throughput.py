"""Throughput benchmark: scenes per hour and Prefect's orchestration overhead, 1 vs 2 workers.

Three runs over the same simulation collection, each into a fresh store (nothing is skipped):

* **plain** (baseline): every scene run in this process by ``tasks.runner.run_scene`` (ingest, the
  steps, evaluation) with no Prefect at all;
* **prefect, 1 worker**: ``explore_collection`` with a one-thread task runner (one scene at a time);
* **prefect, 2 workers**: the same with two scenes at once (``max_parallel_scenes = 2``).

Task time is the sum of the steps' recorded execution times (the ``steps`` table). Orchestration
overhead is the part of the wall time not spent in step bodies, ``1 - task / (workers x wall)``; the
overhead *added by Prefect* is the 1-worker run's wall time over the plain run's. A warm-up flow starts
the temporary Prefect server first, so its ~15 s start-up is not counted. On 2 CPU cores the two
workers compete for the cores, so their step times grow; the speed-up is what a 2-core machine gets.

    python benchmarks/throughput.py --out bench-out/throughput            # 3 scenes, paper sizes
    python benchmarks/throughput.py --out bench-out/throughput --quick    # 3 scenes, tiny preset
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from navcrafter.models.simulation import LABEL
from navcrafter.models.simulation.demo import write_demo_collection
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.store import Store
from navcrafter.tasks.ingest import ingest
from navcrafter.tasks.runner import run_scene
from navcrafter.tasks.scene_metrics import evaluate_scene


def task_seconds(store: Path) -> float:
    events = Store(str(store)).tables.read("steps").to_pylist()
    return float(sum(e["seconds"] or 0.0 for e in events if e["event"] == "completed"))


def run_plain(photos: list[Path], store: Path, config: RunConfig) -> float:
    t0 = time.perf_counter()
    for photo in photos:
        res = ingest(str(store), str(photo), config, "bench-plain")
        if not res.ok:
            raise RuntimeError(res.error)
        run_scene(str(store), res.scene_id, config, "bench-plain")
        evaluate_scene(str(store), res.scene_id, config, "bench-plain")
    return time.perf_counter() - t0


def run_prefect(folder: Path, store: Path, config: RunConfig, workers: int) -> float:
    from prefect.task_runners import ThreadPoolTaskRunner

    from navcrafter.flows.explore import explore_collection

    flow_ = explore_collection.with_options(task_runner=ThreadPoolTaskRunner(max_workers=workers))
    t0 = time.perf_counter()
    run = flow_(str(folder), str(store), config.model_copy(update={"max_parallel_scenes": workers}))
    wall = time.perf_counter() - t0
    bad = [r for r in run.scenes if r.status != "done"]
    if bad:
        raise RuntimeError(f"{len(bad)} scenes failed: {bad[0].error}")
    return wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", action="store_true", help="tiny preset (a couple of minutes)")
    ap.add_argument("--per-kind", type=int, default=1, help="scenes per kind (room, street, tabletop)")
    args = ap.parse_args(argv)
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    config = RunConfig.load(preset="tiny" if args.quick else "paper")
    args.out.mkdir(parents=True, exist_ok=True)
    from prefect import flow

    @flow(name="warm-up")
    def warm_up() -> None:
        return None

    warm_up()  # starts the temporary server outside the measurements
    with tempfile.TemporaryDirectory(prefix="navcrafter-throughput-") as tmp:
        tmp = Path(tmp)
        photos = write_demo_collection(tmp / "photos", per_kind=args.per_kind)
        n = len(photos)
        runs = {}
        wall = run_plain(photos, tmp / "plain", config)
        runs["plain"] = {"workers": 1, "wall_s": wall, "task_s": task_seconds(tmp / "plain")}
        for workers in (1, 2):
            store = tmp / f"prefect-{workers}"
            wall = run_prefect(tmp / "photos", store, config, workers)
            runs[f"prefect-{workers}"] = {"workers": workers, "wall_s": wall, "task_s": task_seconds(store)}
    for r in runs.values():
        r["scenes_per_hour"] = 3600.0 * n / r["wall_s"]
        r["overhead_fraction"] = 1.0 - r["task_s"] / (r["workers"] * r["wall_s"])
    added = runs["prefect-1"]["wall_s"] / runs["plain"]["wall_s"] - 1.0
    speedup = runs["prefect-1"]["wall_s"] / runs["prefect-2"]["wall_s"]
    result = {"label": LABEL, "quick": args.quick, "scenes": n, "runs": runs,
              "prefect_added_overhead_fraction": added, "speedup_2_vs_1_workers": speedup,
              "goal_overhead_fraction": 0.05, "cpu_count": os.cpu_count()}
    (args.out / "results.json").write_text(json.dumps(result, indent=1))
    size = "tiny preset (2 iterations of 9 frames at 64x64)" if args.quick else \
        "paper sizes (3 iterations of 81 frames at 256x256)"
    lines = ["# Throughput benchmark", "", f"> {LABEL}.", "",
             f"{n} simulation scenes, {size}, {os.cpu_count()} CPU cores; one run each, same machine.", "",
             "| run | workers | wall (s) | task time (s) | scenes/hour | overhead (not in step bodies) |",
             "|---|---:|---:|---:|---:|---:|"]
    for name, r in runs.items():
        lines.append(f"| {name} | {r['workers']} | {r['wall_s']:.1f} | {r['task_s']:.1f} | "
                     f"{r['scenes_per_hour']:.0f} | {100 * r['overhead_fraction']:.1f} % |")
    lines += ["", f"Prefect's added wall time (1 worker vs plain): {100 * added:+.1f} % (goal: at most 5 %).",
              f"Speed-up of 2 workers over 1: {speedup:.2f}x.", ""]
    (args.out / "results.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The demo explore's step times, compared across runs: where a slower (or faster) explore spends its time.

Reads stores that ``navcrafter explore`` wrote (each a complete run into a new store) and sums every step's
recorded execution time (the manifest's ``timings``) over the scenes, per step kind (geometry, plan, synthesize,
lift, gaussians = the fit, exports, evaluation), beside each scene's cloud size and held-out 3DGS PSNR; with
``--compare`` it also says how many stored arrays of two stores are bit-identical (the same outputs: a difference
in time is then the code's or the machine's, not more work). Step times of scenes that run side by side include
their waits for each other and for the machine, so a comparison means something only between runs made one
after the other on the same load: give the load average with each run (``--load``) and, when the command was
timed by ``/usr/bin/time -f "cpu user %U sys %S wall %e maxrss_kb %M" -o FILE``, that file (``--cpu``), whose
process CPU seconds depend less on the other processes of the machine than wall time does.

    python benchmarks/demo_steps.py --out DIR --run old=/tmp/store-old --run new=/tmp/store-new \\
        [--cpu old=/tmp/cpu-old.txt ...] [--load old="7.3 -> 8.9" ...] [--note old="ca2fcab, warm cache" ...] \\
        [--compare old,new]

Ratios are against the first ``--run``. ``results.json``: ``{"runs": {label: {"steps": {kind: s}, "total_step_s",
"scenes": {image: {"points", "gs_psnr", "seconds"}}, "wall_s", "cpu_s", "load", "note"}}, "ratios": {label:
{kind: x}}, "identical": {"a,b": {"equal", "differ", "missing", "differing"}}}``.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from navcrafter.schemas.store import Store
from navcrafter.tasks.readers import read_manifest

KINDS = ("geometry", "plan", "synthesize", "lift", "gaussians", "refine", "renders", "exports", "evaluation")


def step_kind(path: str) -> str:
    """``iter_2/synthesize`` -> ``synthesize``; ``gaussians`` -> ``gaussians``."""
    return re.sub(r"_\d+$", "", path.rsplit("/", 1)[-1])


def run_steps(store: str) -> dict:
    """Step seconds summed per kind over the store's scenes, and each scene's cloud size, PSNR and seconds."""
    rows = read_manifest(Store(store, create=False)).to_pylist()
    steps: dict[str, float] = defaultdict(float)
    scenes = {}
    for r in rows:
        metrics = dict(r["metrics"] or [])
        timings = dict(r["timings"] or [])
        for path, seconds in timings.items():
            steps[step_kind(path)] += float(seconds)
        scenes[Path(r["source"]).name] = {"status": r["status"], "points": r["n_points"],
                                          "gs_psnr": metrics.get("gs_psnr"), "seconds": r["seconds"],
                                          "timings": timings}
    ordered = {k: round(steps[k], 1) for k in sorted(steps, key=lambda k: (KINDS + (k,)).index(k))}
    return {"steps": ordered, "total_step_s": round(sum(steps.values()), 1), "scenes": scenes}


def read_cpu(path: str) -> dict[str, float]:
    """``cpu user U sys S wall W maxrss_kb M`` (the ``/usr/bin/time`` format above) -> numbers."""
    words = Path(path).read_text().split()
    out = {}
    for key, name in (("user", "cpu_user_s"), ("sys", "cpu_sys_s"), ("wall", "wall_s"), ("maxrss_kb", "maxrss_kb")):
        if key in words:
            out[name] = float(words[words.index(key) + 1])
    if "cpu_user_s" in out and "cpu_sys_s" in out:
        out["cpu_s"] = round(out["cpu_user_s"] + out["cpu_sys_s"], 1)
    return out


def compare_arrays(a: str, b: str) -> dict:
    """How many Zarr arrays under the two stores' ``scenes`` groups are bit-identical (same shape, dtype and
    values, NaN equal to NaN); the paths of those that differ or exist in ``a`` only."""
    import warnings

    import zarr

    counts = {"equal": 0, "differ": 0, "missing": 0}
    differing: list[str] = []

    def walk(x, y, path: str) -> None:
        for name, node in x.members():
            p = f"{path}/{name}"
            try:
                other = y[name]
            except KeyError:
                counts["missing"] += 1
                differing.append(p)
                continue
            if isinstance(node, zarr.Group):
                walk(node, other, p)
                continue
            u, v = node[...], other[...]
            same = (u.shape == v.shape and u.dtype == v.dtype
                    and np.array_equal(u, v, equal_nan=u.dtype.kind in "fc"))
            counts["equal" if same else "differ"] += 1
            if not same:
                differing.append(p)

    with warnings.catch_warnings():  # exports (PLY, MP4, ...) sit beside the arrays: zarr warns about each
        warnings.simplefilter("ignore")
        walk(zarr.open_group(f"{a}/scenes", mode="r"), zarr.open_group(f"{b}/scenes", mode="r"), "")
    return {**counts, "differing": differing}


def _pairs(values: list[str] | None) -> dict[str, str]:
    out = {}
    for v in values or []:
        label, _, rest = v.partition("=")
        if not rest:
            raise SystemExit(f"expected LABEL=VALUE, got {v!r}")
        out[label] = rest
    return out


def markdown(res: dict) -> str:
    runs = res["runs"]
    labels = list(runs)
    kinds = [k for k in KINDS if any(k in r["steps"] for r in runs.values())]
    lines = ["# Demo explore: step times summed over the scenes", "",
             "Simulation mode (the demo collection). Each run a complete `navcrafter explore` into a new store; "
             "step times of scenes run side by side include their waits for each other and the machine, so only "
             "runs made one after the other on the same load compare.", "",
             "| step (s) | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    for k in kinds:
        lines.append(f"| {k} | " + " | ".join(f"{runs[lb]['steps'].get(k, 0):.1f}" for lb in labels) + " |")
    lines.append("| **all steps** | " + " | ".join(f"{runs[lb]['total_step_s']:.1f}" for lb in labels) + " |")
    for key, name in (("wall_s", "wall of the command"), ("cpu_s", "process CPU (user + sys)")):
        lines.append(f"| {name} | " + " | ".join(
            f"{runs[lb][key]:.1f}" if runs[lb].get(key) is not None else "" for lb in labels) + " |")
    lines.append("| load average | " + " | ".join(runs[lb].get("load") or "" for lb in labels) + " |")
    images = sorted({i for r in runs.values() for i in r["scenes"]})
    lines += ["", "| scene: points / 3DGS PSNR (dB) / scene seconds | " + " | ".join(labels) + " |",
              "|---|" + "---:|" * len(labels)]
    for img in images:
        cells = []
        for lb in labels:
            s = runs[lb]["scenes"].get(img)
            cells.append("" if s is None else f"{s['points']} / {s['gs_psnr']:.4f} / {s['seconds']:.0f}")
        lines.append(f"| {img} | " + " | ".join(cells) + " |")
    notes = [f"- **{lb}**: {runs[lb]['note']}" for lb in labels if runs[lb].get("note")]
    if notes:
        lines += ["", *notes]
    for pair, c in res.get("identical", {}).items():
        lines += ["", f"Stored arrays {pair}: {c['equal']} bit-identical, {c['differ']} differ, {c['missing']} "
                  f"missing in the second" + (f" ({', '.join(c['differing'][:6])}"
                                               f"{', ...' if len(c['differing']) > 6 else ''})"
                                               if c["differing"] else "") + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--run", action="append", required=True, help="LABEL=STORE (the first is the baseline)")
    ap.add_argument("--cpu", action="append", help="LABEL=FILE written by /usr/bin/time (format above)")
    ap.add_argument("--load", action="append", help="LABEL=TEXT: the load average before -> after the run")
    ap.add_argument("--note", action="append", help="LABEL=TEXT: what the run was")
    ap.add_argument("--compare", action="append", help="A,B: count bit-identical stored arrays of two runs")
    args = ap.parse_args(argv)
    stores, cpus, loads, notes = _pairs(args.run), _pairs(args.cpu), _pairs(args.load), _pairs(args.note)
    runs = {}
    for label, store in stores.items():
        runs[label] = {"store": store, **run_steps(store), **(read_cpu(cpus[label]) if label in cpus else {}),
                       "load": loads.get(label), "note": notes.get(label)}
    base = runs[next(iter(runs))]
    ratios = {lb: {k: round(v / base["steps"][k], 3) for k, v in r["steps"].items() if base["steps"].get(k)}
              for lb, r in runs.items()}
    for lb, r in runs.items():
        ratios[lb]["all steps"] = round(r["total_step_s"] / base["total_step_s"], 3)
        for key in ("wall_s", "cpu_s"):
            if r.get(key) and base.get(key):
                ratios[lb][key] = round(r[key] / base[key], 3)
    res = {"runs": runs, "ratios": ratios, "identical": {}}
    for pair in args.compare or []:
        a, b = pair.split(",")
        res["identical"][pair] = compare_arrays(stores[a], stores[b])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(res, indent=1) + "\n")
    (args.out / "results.md").write_text(markdown(res))
    print(markdown(res))
    return res


if __name__ == "__main__":
    main(sys.argv[1:])

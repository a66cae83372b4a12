"""Paired comparison of the explorer ('ours') between result files:
python compare.py OLD.json[,OLD2.json] NEW.json[,...] [OUT.json]"""
import json
import sys

import numpy as np

METRICS = ["seen", "coverage_at_0.05", "coverage_rel_0.01", "coverage", "fscore", "collisions", "planner_s",
           "object_coverage_at_0.05"]

def load(spec):
    rows = {}
    for f in spec.split(","):
        r = json.load(open(f))
        for run in r["runs"]:
            rows[(run["kind"], run["seed"])] = run
    return rows

def main():
    old, new = load(sys.argv[1]), load(sys.argv[2])
    keys = sorted(set(old) & set(new))
    for k in keys:
        assert old[k]["initial_cloud_sha256"] == new[k]["initial_cloud_sha256"], k
    out = {}
    kinds = sorted({k[0] for k in keys})
    for kind in kinds + ["all"]:
        ks = [k for k in keys if kind == "all" or k[0] == kind]
        res = {}
        for m in METRICS:
            a = np.array([old[k]["ours"].get(m, np.nan) for k in ks], float)
            b = np.array([new[k]["ours"].get(m, np.nan) for k in ks], float)
            ok = np.isfinite(a) & np.isfinite(b)
            if not ok.any():
                continue
            d = b[ok] - a[ok]
            res[m] = {"old": float(a[ok].mean()), "new": float(b[ok].mean()), "delta": float(d.mean()),
                      "se": float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else None,
                      "higher": int((d > 0).sum()), "lower": int((d < 0).sum()), "n": int(len(d))}
        res["collision_scenes_old"] = {f"{k[0]}-{k[1]}": old[k]["ours"]["collisions"] for k in ks
                                       if old[k]["ours"]["collisions"] > 0}
        res["collision_scenes_new"] = {f"{k[0]}-{k[1]}": new[k]["ours"]["collisions"] for k in ks
                                       if new[k]["ours"]["collisions"] > 0}
        out[kind] = res
    for kind, res in out.items():
        print(f"== {kind}")
        for m, v in res.items():
            if m.startswith("collision_scenes"):
                print(f"  {m}: {v}")
            else:
                se = f"{v['se']:.3f}" if v["se"] is not None else "-"
                print(f"  {m:24s} {v['old']:.4f} -> {v['new']:.4f}  d {v['delta']:+.4f} ± {se}  "
                      f"higher {v['higher']}/{v['n']} lower {v['lower']}")
    if len(sys.argv) > 3:
        json.dump(out, open(sys.argv[3], "w"), indent=1)

main()

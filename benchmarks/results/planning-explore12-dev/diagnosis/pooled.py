"""A lever's paired difference pooled over draws of the simulation (common random numbers, --base-seed):

python pooled.py BASE_0.json,VARIANT_0.json BASE_1.json,VARIANT_1.json ... [--out OUT.json]

Per scene and kind: variant - base in each draw, averaged over the draws; then mean ± SE over scenes, scenes higher /
lower, and the collision frames of base and variant summed over scenes and draws."""
import json
import sys

import numpy as np

METRICS = ["seen", "coverage_at_0.05", "coverage_rel_0.01", "coverage", "fscore"]


def rows(path):
    return {(r["kind"], r["seed"]): r["ours"] for r in json.load(open(path))["runs"]}


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--out")]
    out_path = next((a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--out=")), None)
    pairs = [tuple(rows(p) for p in a.split(",")) for a in args]
    keys = sorted(set.intersection(*[set(b) & set(v) for b, v in pairs]))
    out = {"draws": args}
    for kind in sorted({k for k, _ in keys}):
        ks = [k for k in keys if k[0] == kind]
        res = {}
        for m in METRICS:
            d = np.array([[v[k][m] - b[k][m] for k in ks] for b, v in pairs]).mean(0)
            res[m] = {"delta": float(d.mean()), "se": float(d.std(ddof=1) / np.sqrt(len(d))),
                      "higher": int((d > 0).sum()), "lower": int((d < 0).sum()), "n": len(d)}
        res["collision_frames_base"] = float(sum(b[k]["collisions"] for b, _ in pairs for k in ks))
        res["collision_frames_variant"] = float(sum(v[k]["collisions"] for _, v in pairs for k in ks))
        res["colliding_scene_draws_base"] = int(sum(b[k]["collisions"] > 0 for b, _ in pairs for k in ks))
        res["colliding_scene_draws_variant"] = int(sum(v[k]["collisions"] > 0 for _, v in pairs for k in ks))
        out[kind] = res
        print(f"== {kind} ({len(pairs)} draws x {len(ks)} scenes)")
        for m in METRICS:
            r = res[m]
            print(f"  {m:20s} {r['delta']:+.4f} ± {r['se']:.4f}  higher {r['higher']}/{r['n']} lower {r['lower']}")
        print(f"  collision frames base {res['collision_frames_base']:.0f} ({res['colliding_scene_draws_base']} "
              f"scene-draws), variant {res['collision_frames_variant']:.0f} "
              f"({res['colliding_scene_draws_variant']})")
    if out_path:
        json.dump(out, open(out_path, "w"), indent=1)


main()

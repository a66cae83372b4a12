"""How much of a paired difference is the simulation's draw: one lever measured twice, in two draws.

python draw_noise.py BASE_A.json VARIANT_A.json BASE_B.json VARIANT_B.json [OUT.json]

Per scene, d_A = variant - base in draw A and d_B in draw B (the same planners, another draw of the simulation).
d_A - d_B holds no lever, only draw noise (twice the variance of one draw's paired difference), so the draw noise
of one draw's 10-scene paired mean is sd(d_A - d_B) / sqrt(2 n). Printed beside each draw's paired mean."""
import json
import sys

import numpy as np

METRICS = ["seen", "coverage_at_0.05", "coverage_rel_0.01", "coverage", "fscore", "collisions"]


def rows(path):
    return {(r["kind"], r["seed"]): r["ours"] for r in json.load(open(path))["runs"]}


def main():
    base_a, var_a, base_b, var_b = (rows(p) for p in sys.argv[1:5])
    keys = sorted(set(base_a) & set(var_a) & set(base_b) & set(var_b))
    out = {"scenes": [f"{k}-{s}" for k, s in keys], "files": sys.argv[1:5]}
    for m in METRICS:
        da = np.array([var_a[k][m] - base_a[k][m] for k in keys])
        db = np.array([var_b[k][m] - base_b[k][m] for k in keys])
        n = len(keys)
        noise = float(np.std(da - db, ddof=1) / np.sqrt(2 * n))
        out[m] = {"draw_a": float(da.mean()), "se_a": float(da.std(ddof=1) / np.sqrt(n)), "draw_b": float(db.mean()),
                  "se_b": float(db.std(ddof=1) / np.sqrt(n)), "both": float((da + db).mean() / 2),
                  "draw_noise_of_one_mean": noise, "per_scene_a": da.tolist(), "per_scene_b": db.tolist()}
        print(f"{m:20s} A {da.mean():+.4f} ± {da.std(ddof=1) / np.sqrt(n):.4f}  B {db.mean():+.4f} ± "
              f"{db.std(ddof=1) / np.sqrt(n):.4f}  draw noise of one mean {noise:.4f}")
    if len(sys.argv) > 5:
        json.dump(out, open(sys.argv[5], "w"), indent=1)


main()

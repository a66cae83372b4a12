"""Whether two benchmark runs of the explorer agree scene by scene (collide13):
python identical.py A.json B.json KIND."""
import json
import sys

METRICS = ("seen", "coverage_at_0.05", "coverage", "fscore", "collisions")


def rows(path, kind):
    return {r["seed"]: r["ours"] for r in json.load(open(path))["runs"] if r["kind"] == kind}


a, b, kind = rows(sys.argv[1], sys.argv[3]), rows(sys.argv[2], sys.argv[3]), sys.argv[3]
same = sum(all(abs(a[s][m] - b[s][m]) < 1e-12 for m in METRICS) for s in b)
print(f"{kind}: {sys.argv[2]} identical to {sys.argv[1]} in {same} of {len(b)} scenes")

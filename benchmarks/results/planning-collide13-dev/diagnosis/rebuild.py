"""Rebuild one development scene under common random numbers and keep its store (collide13):
python rebuild.py KIND SEED BASE_SEED OUTDIR [KEY=VALUE ...] (plan.* settings for the explorer)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))  # the repository root, for `benchmarks`
from benchmarks import planning  # noqa: E402
from navcrafter.models.simulation.demo import write_demo_collection  # noqa: E402

kind, seed, base, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
variant = dict(a.split("=", 1) for a in sys.argv[5:])
photo = write_demo_collection(out / "photos", (kind,), 1, seed)[0]
cfg = planning.bench_config("explorer", True, None, variant or None, crn=True, base_seed=base)
row, _ = planning.run_one(photo, out / "store", cfg)
print({k: round(row[k], 4) for k in ("seen", "coverage_at_0.05", "coverage", "fscore", "collisions")})

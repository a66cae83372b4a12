"""One scene's explorations seen from above, beside a strip of frames (issue 30, the demo's picture) — SIMULATION.

Runs every planner of the planning benchmark (``planning.METHODS``) on one demo scene at quick sizes, then draws
(PIL) the true scene from above (its surfaces sampled, in grey, in the ground-truth frame) with each method's *true*
camera path (where the simulated video model really took the frames; dots: frames, circle: the input camera) and,
beside it, a strip of ``--frames`` evenly spaced frames of each method's video.

    python benchmarks/trajectory_figure.py --kind room --seed 40 --out docs/trajectories-room-40.png
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from navcrafter.models.simulation import LABEL
from navcrafter.models.simulation.demo import write_demo_collection
from navcrafter.schemas.layout import SYNTHESIZE
from navcrafter.schemas.store import Store
from navcrafter.tasks.common import simulation_truth
from navcrafter.tasks.ingest import ingest
from navcrafter.tasks.readers import true_cameras
from navcrafter.tasks.runner import run_scene

if __package__ in (None, ""):  # run as a script: the repository root makes the benchmarks package importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.planning import LABELS, METHODS, bench_config  # noqa: E402

COLOURS = {"baseline": (220, 60, 40), "baseline_global": (230, 160, 30), "ours": (40, 110, 220),
           "paper_ours": (60, 170, 80)}


def explore(kind: str, seed: int, tmp: Path) -> dict:
    photo = write_demo_collection(tmp / "photos", (kind,), 1, seed)[0]
    out = {}
    for name, strategy in METHODS.items():
        cfg = bench_config(strategy, True)
        store = tmp / name
        sid = ingest(str(store), str(photo), cfg, "fig").scene_id
        run_scene(str(store), sid, cfg, "fig")
        scene = Store(str(store)).scene(sid)
        truth = simulation_truth(scene)
        path = np.concatenate([true_cameras(scene, k) for k in range(1, cfg.iterations + 1)])
        frames = np.concatenate([scene.read(SYNTHESIZE, k, "frames") for k in range(1, cfg.iterations + 1)])
        out[name] = (truth, truth.gt_pose(path), frames)
    return out


def top_view(runs: dict, size: int = 640) -> Image.Image:
    truth = next(iter(runs.values()))[0]
    import open3d as o3d

    o3d.utility.random.seed(0)
    pts = np.asarray(truth.scene.merged_mesh().sample_points_uniformly(200_000).points)
    cams = np.concatenate([p[:, :3, 3] for _, p, _ in runs.values()] + [truth.photo_c2w[None, :3, 3]])
    # frame the cameras with a margin (the street's ground is 80 m wide; show where the cameras went)
    lo, hi = cams[:, :2].min(0), cams[:, :2].max(0)
    span = max(float((hi - lo).max()), 1.0) * 1.6
    mid = (lo + hi) / 2
    # between the floor (or ground) and 2 m: walls, furniture, facades; no ceiling over the plan
    keep = (pts[:, 2] > 0.05) & (pts[:, 2] < 2.0) & (np.abs(pts[:, :2] - mid).max(1) < span / 2)
    img = Image.new("RGB", (size, size), (255, 255, 255))
    draw = ImageDraw.Draw(img)

    def px(xy: np.ndarray) -> np.ndarray:
        return np.stack([(xy[:, 0] - mid[0]) / span + 0.5, 0.5 - (xy[:, 1] - mid[1]) / span], 1) * size

    for u, v in px(pts[keep, :2]).astype(int):
        if 0 <= u < size and 0 <= v < size:
            img.putpixel((int(u), int(v)), (170, 170, 170))
    for name, (_, path, _) in runs.items():
        q = px(path[:, :3, 3])
        draw.line([tuple(p) for p in q], fill=COLOURS[name], width=3)
        for p in q[::4]:
            draw.ellipse([p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2], fill=COLOURS[name])
    s = px(truth.photo_c2w[None, :2, 3])[0]
    draw.ellipse([s[0] - 6, s[1] - 6, s[0] + 6, s[1] + 6], outline=(0, 0, 0), width=2)
    y = 8
    for name in runs:
        draw.rectangle([8, y, 22, y + 10], fill=COLOURS[name])
        draw.text((28, y - 1), LABELS[name], fill=(0, 0, 0))
        y += 16
    draw.text((8, size - 16), f"{LABEL.split(':')[0]} - from above, true camera paths", fill=(0, 0, 0))
    return img


def strips(runs: dict, count: int, height: int) -> Image.Image:
    rows = []
    for name, (_, _, frames) in runs.items():
        idx = np.linspace(0, len(frames) - 1, count).round().astype(int)
        tiles = [Image.fromarray(frames[i]).resize((height, height)) for i in idx]
        row = Image.new("RGB", (count * height + 6, height + 6), COLOURS[name])
        for j, t in enumerate(tiles):
            row.paste(t, (3 + j * height, 3))
        rows.append(row)
    out = Image.new("RGB", (rows[0].width, sum(r.height for r in rows)), (255, 255, 255))
    y = 0
    for r in rows:
        out.paste(r, (0, y))
        y += r.height
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kind", default="room")
    ap.add_argument("--seed", type=int, default=40)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="navcrafter-fig-") as tmp:
        runs = explore(args.kind, args.seed, Path(tmp))
        top = top_view(runs)
        strip = strips(runs, args.frames, top.height // len(runs) - 6)
        fig = Image.new("RGB", (top.width + strip.width + 10, max(top.height, strip.height)), (255, 255, 255))
        fig.paste(top, (0, 0))
        fig.paste(strip, (top.width + 10, 0))
        args.out.parent.mkdir(parents=True, exist_ok=True)
        fig.save(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

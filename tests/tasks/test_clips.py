"""Dataset clips for a generator, and scoring what it generated (`dataset-clips`, `evaluate-clips`)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from datasets_fixtures import Trajectory, write_re10k
from PIL import Image
from typer.testing import CliRunner

from navcrafter.flows.cli import app
from navcrafter.models.camera.cameras import Intrinsics, look_at
from navcrafter.models.simulation.render import render
from navcrafter.models.simulation.scenes import generate_scene

SIZE, N = 128, 15  # the conditioning frame + 14, as in the paper's protocol
runner = CliRunner()


def sideways_path(scene, n: int, sweep: float, axis: int = 0) -> np.ndarray:
    K = Intrinsics.from_fov(scene.camera_fov_x_deg, SIZE, SIZE)
    c0 = scene.camera_c2w
    d0 = render(scene, c0, K, colour=False)
    target = c0[:3, 3] + c0[:3, 2] * float(np.median(d0.depth[d0.hit]))
    eyes = c0[:3, 3] + np.linspace(0.0, sweep, n)[:, None] * c0[:3, axis]
    return np.array([look_at(e, target, up=-c0[:3, 1]) for e in eyes])


@pytest.fixture(scope="module")
def re10k_clips(tmp_path_factory):
    """A RealEstate10K-format sequence rendered from a simulated table-top, exported as clips."""
    root = tmp_path_factory.mktemp("re10k")
    scene = generate_scene("tabletop", 0)
    K = Intrinsics.from_fov(scene.camera_fov_x_deg, SIZE, SIZE).K
    poses = sideways_path(scene, N, 0.6)
    write_re10k(root, Trajectory(poses, np.tile(K, (N, 1, 1)), SIZE, SIZE, np.zeros(3)), frames=False)
    seq = next((root / "test").glob("*.txt"))
    stamps = [line.split()[0] for line in seq.read_text().splitlines()[1:]]
    (root / "test" / seq.stem).mkdir()
    for ts, c2w in zip(stamps, poses):
        Image.fromarray(render(scene, c2w, Intrinsics.from_matrix(K, SIZE, SIZE)).rgb).save(
            root / "test" / seq.stem / f"{ts}.png")
    clips = tmp_path_factory.mktemp("clips")
    res = runner.invoke(app, ["dataset-clips", "re10k", str(root), "--out", str(clips), "--frames", "14",
                              "--resolution", str(SIZE)])
    assert res.exit_code == 0, res.output
    return scene, clips


def test_clips_hold_the_protocol(re10k_clips):
    _, clips = re10k_clips
    (key,) = [p.name for p in clips.iterdir()]
    assert key.startswith("re10k")
    assert len(list((clips / key / "reference").glob("*.png"))) == 14
    import json

    doc = json.loads((clips / key / "cameras.json").read_text())
    c2w = np.asarray(doc["c2w"])
    assert c2w.shape == (15, 4, 4) and np.allclose(c2w[0], np.eye(4), atol=1e-9)


@pytest.mark.system
def test_perfect_and_wrong_generators_are_told_apart(re10k_clips, tmp_path, prefect_api_url):
    from navcrafter.flows.evaluate import evaluate_clips
    from navcrafter.schemas.config import EvaluationConfig

    scene, clips = re10k_clips
    (key,) = [p.name for p in clips.iterdir()]
    good = tmp_path / "good"
    shutil.copytree(clips / key / "reference", good / key)  # a generator that reproduces the truth
    bad = tmp_path / "bad"  # one that moves the camera up where it was asked to move sideways
    (bad / key).mkdir(parents=True)
    K = Intrinsics.from_fov(scene.camera_fov_x_deg, SIZE, SIZE)
    for i, c2w in enumerate(sideways_path(scene, N, -0.3, axis=1)[1:], start=1):
        Image.fromarray(render(scene, c2w, K).rgb).save(bad / key / f"{i:04d}.png")
    cfg = EvaluationConfig(weights_dir=tmp_path / "no-weights")
    r_good = {r["metric"]: r for r in evaluate_clips(str(clips), str(good), str(tmp_path / "o1"), cfg).rows}
    r_bad = {r["metric"]: r for r in evaluate_clips(str(clips), str(bad), str(tmp_path / "o2"), cfg).rows}
    for name, r in (("reproduces the truth", r_good), ("moves up, not sideways", r_bad)):
        print(f"\n{name}: " + ", ".join(f"{m} {r[m]['value']:.3f}" for m in ("PSNR", "SSIM", "R_err", "T_err")))
    assert r_good["PSNR"]["value"] == 100.0 and r_good["SSIM"]["value"] == pytest.approx(1.0)
    assert r_bad["PSNR"]["value"] < 30 and r_bad["SSIM"]["value"] < 0.9
    assert r_good["registered"]["value"] > 0.8 and r_bad["registered"]["value"] > 0.8
    assert r_good["R_err"]["value"] < 12 and r_good["T_err"]["value"] < 1.5  # COLMAP's own error (varies by run)
    assert r_bad["R_err"]["value"] > 5 * r_good["R_err"]["value"]
    assert r_bad["T_err"]["value"] > 2 * r_good["T_err"]["value"] + 1.0, (r_good["T_err"], r_bad["T_err"])
    assert r_good["LPIPS"]["status"] == "unavailable" and r_good["FID"]["status"] == "unavailable"
    table = pq.read_table(tmp_path / "o1" / "evaluations.parquet").to_pylist()
    assert len(table) == len(r_good) and "Table IV" in (tmp_path / "o1" / "report.md").read_text()


@pytest.mark.system
def test_bad_generated_clips_are_reported_not_fatal(re10k_clips, tmp_path, prefect_api_url):
    from navcrafter.flows.evaluate import evaluate_clips
    from navcrafter.schemas.config import EvaluationConfig

    _, clips = re10k_clips
    (key,) = [p.name for p in clips.iterdir()]
    short = tmp_path / "short" / key
    short.mkdir(parents=True)
    for p in sorted((clips / key / "reference").glob("*.png"))[:5]:
        shutil.copy(p, short / p.name)
    cfg = EvaluationConfig(weights_dir=tmp_path, camera_guidance=False)
    res = evaluate_clips(str(clips), str(tmp_path / "short"), str(tmp_path / "o"), cfg)
    assert key in res.failed and "5 images" in res.failed[key] and "needs 14" in res.failed[key]
    res = evaluate_clips(str(clips), str(tmp_path / "nothing"), str(tmp_path / "o"), cfg)
    assert "no generated frames" in res.failed[key]


def test_cli_usage_errors(tmp_path: Path):
    res = runner.invoke(app, ["dataset-clips", "re10k", str(tmp_path / "nope"), "--out", str(tmp_path / "c")])
    assert res.exit_code == 2 and "not a folder" in res.output
    res = runner.invoke(app, ["dataset-clips", "imagenet", str(tmp_path), "--out", str(tmp_path / "c")])
    assert res.exit_code == 2 and "unknown dataset kind" in res.output
    res = runner.invoke(app, ["evaluate-clips", str(tmp_path), str(tmp_path), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "dataset-clips" in " ".join(res.output.split())

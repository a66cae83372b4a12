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
    from navcrafter.schemas.config import RunConfig

    scene, clips = re10k_clips
    (key,) = [p.name for p in clips.iterdir()]
    good = tmp_path / "good"
    shutil.copytree(clips / key / "reference", good / key)  # a generator that reproduces the truth
    bad = tmp_path / "bad"  # one that moves the camera up where it was asked to move sideways
    (bad / key).mkdir(parents=True)
    K = Intrinsics.from_fov(scene.camera_fov_x_deg, SIZE, SIZE)
    for i, c2w in enumerate(sideways_path(scene, N, -0.3, axis=1)[1:], start=1):
        Image.fromarray(render(scene, c2w, K).rgb).save(bad / key / f"{i:04d}.png")
    cfg = RunConfig.load(preset="tiny", overrides={"evaluation.weights_dir": str(tmp_path / "no-weights")})
    rows_good = evaluate_clips(str(clips), str(good), str(tmp_path / "o1"), cfg).rows  # with Table IV (tiny fit)
    r_good = {r["metric"]: r for r in rows_good if r["table"] != "IV"}
    r_bad = {r["metric"]: r for r in evaluate_clips(str(clips), str(bad), str(tmp_path / "o2"), cfg,
                                                    reconstruction=False).rows}
    assert not [r for r in r_bad.values() if r["table"] == "IV"]
    fit = {r["metric"]: r for r in rows_good if r["table"] == "IV"}
    assert fit["PSNR"]["status"] == "ok" and fit["PSNR"]["value"] > 15 and "dataset's 14 frames" in fit["PSNR"]["note"]
    for name, r in (("reproduces the truth", r_good), ("moves up, not sideways", r_bad)):
        print(f"\n{name}: " + ", ".join(f"{m} {r[m]['value']:.3f}" for m in ("PSNR", "SSIM", "R_err", "T_err",
                                                                   "R_err sum", "T_err sum")))
    assert r_good["PSNR"]["value"] == 100.0 and r_good["SSIM"]["value"] == pytest.approx(1.0)
    assert r_bad["PSNR"]["value"] < 30 and r_bad["SSIM"]["value"] < 0.9
    assert r_good["registered"]["value"] > 0.8 and r_bad["registered"]["value"] > 0.8
    # COLMAP's own error (varies by run): the sums, in degrees, over the 14 frames after the conditioning one
    assert r_good["R_err sum"]["value"] < 12 and r_good["T_err sum"]["value"] < 1.5
    assert r_bad["R_err sum"]["value"] > 5 * r_good["R_err sum"]["value"]
    assert r_bad["T_err sum"]["value"] > 2 * r_good["T_err sum"]["value"] + 1.0, (r_good["T_err"], r_bad["T_err"])
    # the headline: per-frame means, R_err in radians
    for r in (r_good, r_bad):
        n = round(r["registered"]["value"] * N) - 1  # registered frames but the reference
        assert r["R_err"]["unit"] == "rad, per-frame mean"
        assert r["R_err"]["value"] == pytest.approx(np.deg2rad(r["R_err sum"]["value"] / n))
        assert r["T_err"]["value"] == pytest.approx(r["T_err sum"]["value"] / n)
    assert r_bad["R_err"]["value"] > 5 * r_good["R_err"]["value"]
    assert {r_good[m]["table"] for m in ("PSNR", "SSIM", "LPIPS")} == {"I"} and r_good["FID"]["table"] == "II"
    assert {r_good[m]["table"] for m in ("R_err", "T_err", "R_err sum", "T_err sum", "registered")} == {"III"}
    assert r_good["LPIPS"]["status"] == "unavailable" and r_good["FID"]["status"] == "unavailable"
    table = pq.read_table(tmp_path / "o1" / "evaluations.parquet").to_pylist()
    report = (tmp_path / "o1" / "report.md").read_text()
    assert len(table) == len(rows_good) and "## Table III: Camera pose errors" in report
    assert "## Table IV: 3D scene reconstruction (3DGS)" in report
    assert "## Table I: Novel-view synthesis quality" in report and "## Table II: FID / FVD" in report


def test_clip_pose_rows_come_from_the_per_frame_errors(re10k_clips, tmp_path, monkeypatch):
    """score_clip gives COLMAP the conditioning image + the 14 frames and reports deg2rad of the per-frame mean
    (``R_err``), the sum (``R_err sum``) and the unregistered frames (without running COLMAP here)."""
    from navcrafter.models.metrics import pose
    from navcrafter.schemas.config import EvaluationConfig
    from navcrafter.tasks.clips import score_clip

    _, clips = re10k_clips
    (key,) = [p.name for p in clips.iterdir()]
    shutil.copytree(clips / key / "reference", tmp_path / "gen" / key)
    seen = {}
    registered = [True] * N
    registered[6] = False

    def fake(frames, requested, K, workdir, *, scale, **kw):
        seen.update(n=len(frames), scale=scale, first=np.asarray(frames[0]))
        r_deg = np.where(registered, np.arange(N, dtype=float), np.nan)  # 0 at the reference, 1 deg per frame
        return {"n_frames": N, "n_registered": N - 1, "R_err_deg_sum": float(np.nansum(r_deg)),
                "R_err_deg_mean": float(np.nansum(r_deg) / (N - 2)), "T_err_sum": 2.6, "T_err_mean": 2.6 / (N - 2),
                "recovery": {"registered": registered}, "reason": f"1 of {N} frames not registered"}

    monkeypatch.setattr(pose, "camera_guidance_precision", fake)
    rows = {r["metric"]: r for r in score_clip(clips, tmp_path / "gen", key, EvaluationConfig(weights_dir=tmp_path))}
    assert seen["n"] == N and seen["scale"] == "farthest"
    assert np.array_equal(seen["first"], np.asarray(Image.open(clips / key / "condition.png").convert("RGB")))
    total = sum(range(N)) - 6  # frame 6 did not register
    assert rows["R_err"]["value"] == pytest.approx(np.deg2rad(total / (N - 2)))
    assert rows["R_err sum"]["value"] == pytest.approx(total) and rows["T_err sum"]["value"] == pytest.approx(2.6)
    assert rows["T_err"]["value"] == pytest.approx(2.6 / (N - 2))
    assert rows["registered"]["value"] == pytest.approx((N - 1) / N)
    assert "unregistered frames: 6" in rows["registered"]["note"]
    assert {rows[m]["table"] for m in ("R_err", "T_err", "R_err sum", "T_err sum", "registered")} == {"III"}
    assert rows["PSNR"]["table"] == "I"


@pytest.mark.system
def test_bad_generated_clips_are_reported_not_fatal(re10k_clips, tmp_path, prefect_api_url):
    from navcrafter.flows.evaluate import evaluate_clips
    from navcrafter.schemas.config import RunConfig

    _, clips = re10k_clips
    (key,) = [p.name for p in clips.iterdir()]
    short = tmp_path / "short" / key
    short.mkdir(parents=True)
    for p in sorted((clips / key / "reference").glob("*.png"))[:5]:
        shutil.copy(p, short / p.name)
    cfg = RunConfig.load(overrides={"evaluation.weights_dir": str(tmp_path), "evaluation.camera_guidance": False})
    res = evaluate_clips(str(clips), str(tmp_path / "short"), str(tmp_path / "o"), cfg)
    assert key in res.failed and "5 images" in res.failed[key] and "needs 14" in res.failed[key]
    failed = [r for r in res.rows if r["status"] == "failed"]
    assert [(r["table"], r["metric"]) for r in failed] == [("I", "PSNR")]
    res = evaluate_clips(str(clips), str(tmp_path / "nothing"), str(tmp_path / "o"), cfg)
    assert "no generated frames" in res.failed[key]


def test_cli_usage_errors(tmp_path: Path):
    res = runner.invoke(app, ["dataset-clips", "re10k", str(tmp_path / "nope"), "--out", str(tmp_path / "c")])
    assert res.exit_code == 2 and "not a folder" in res.output
    res = runner.invoke(app, ["dataset-clips", "imagenet", str(tmp_path), "--out", str(tmp_path / "c")])
    assert res.exit_code == 2 and "unknown dataset kind" in res.output
    res = runner.invoke(app, ["evaluate-clips", str(tmp_path), str(tmp_path), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "dataset-clips" in " ".join(res.output.split())

"""`generate-clips`: our synthesizers on dataset clips (simulation and ONNX), and Table IV scored on the clips."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import TINY_MODELS_SIZE
from typer.testing import CliRunner

from navcrafter.flows.cli import app
from navcrafter.models.camera.cameras import invert_pose
from navcrafter.schemas.clips import CLOUD, GENERATION
from navcrafter.tasks.clips.generation import extend_path, generation_frames

runner = CliRunner()
SIZE = 64


def test_wan_frame_counts_and_the_extended_path():
    assert [generation_frames(n) for n in (1, 2, 5, 6, 15, 17, 18)] == [1, 5, 5, 9, 17, 17, 21]
    with pytest.raises(ValueError, match="at least one camera"):
        generation_frames(0)
    rng = np.random.default_rng(0)
    c2w = np.tile(np.eye(4), (4, 1, 1))
    for i in range(1, 4):
        c2w[i, :3, 3] = c2w[i - 1, :3, 3] + rng.normal(size=3)
    ext = extend_path(c2w, 7)
    assert ext.shape == (7, 4, 4) and np.array_equal(ext[:4], c2w)
    step = invert_pose(c2w[2]) @ c2w[3]
    for i in range(4, 7):  # constant velocity: every added pose repeats the clip's last relative motion
        np.testing.assert_allclose(invert_pose(ext[i - 1]) @ ext[i], step, atol=1e-12)
    assert np.array_equal(extend_path(c2w, 3), c2w[:3])


def _dataset_clips(root: Path, frames: int, size: int) -> Path:
    res = runner.invoke(app, ["simulate-datasets", str(root / "ds"), "--kind", "re10k", "--sequences", "2",
                              "--frames", str(frames + 3), "--resolution", str(size), "--seed", "5"])
    assert res.exit_code == 0, res.output
    clips = root / "clips"
    res = runner.invoke(app, ["dataset-clips", "re10k", str(root / "ds" / "re10k"), "--out", str(clips),
                              "--frames", str(frames), "--resolution", str(size)])
    assert res.exit_code == 0, res.output
    return clips


@pytest.fixture(scope="module")
def sim_clips(tmp_path_factory):
    """Two clips (conditioning frame + 14) of a simulated RealEstate10K-format dataset."""
    return _dataset_clips(tmp_path_factory.mktemp("gen"), 14, SIZE)


def _psnr(clips: Path, generated: Path, key: str) -> float:
    from navcrafter.models.metrics.image import psnr
    from navcrafter.tasks.clips import load_clip, load_generated

    clip = load_clip(clips, key)
    fake = load_generated(generated, key, clip)
    return float(np.mean(np.minimum(psnr(fake / 255.0, clip["reference"] / 255.0), 100.0)))


@pytest.mark.system
def test_simulated_generation_follows_the_clip_and_resumes(sim_clips, tmp_path, prefect_api_url):
    keys = sorted(p.name for p in sim_clips.iterdir())
    assert len(keys) == 2 and all("simulation" in json.loads((sim_clips / k / "cameras.json").read_text())
                                  for k in keys)
    perfect, honest = tmp_path / "perfect", tmp_path / "honest"
    res = runner.invoke(app, ["generate-clips", str(sim_clips), "--out", str(perfect), "--set",
                              "simulation.preset=perfect"])
    assert res.exit_code == 0, res.output
    assert "SIMULATION" in res.output.upper()
    res = runner.invoke(app, ["generate-clips", str(sim_clips), "--out", str(honest)])
    assert res.exit_code == 0, res.output
    for key in keys:
        rec = json.loads((honest / key / GENERATION).read_text())
        assert rec["generated_frames"] == 17 and rec["kept_frames"] == 15
        assert len(list((honest / key).glob("*.png"))) == 15 and (honest / key / CLOUD).is_file()
        # the perfect stand-in renders the truth at the clip's cameras; the honest one drifts and hallucinates
        p_perfect, p_honest = _psnr(sim_clips, perfect, key), _psnr(sim_clips, honest, key)
        print(f"\n{key}: PSNR perfect {p_perfect:.1f} dB, honest {p_honest:.1f} dB")
        assert p_perfect > 35 and p_honest < p_perfect - 5
    # a rerun keeps what is there; other settings make the frames again
    stamp = (honest / keys[0] / "0002.png").stat().st_mtime_ns
    res = runner.invoke(app, ["generate-clips", str(sim_clips), "--out", str(honest)])
    assert res.exit_code == 0 and "0 clip(s), 2 already there" in res.output, res.output
    assert (honest / keys[0] / "0002.png").stat().st_mtime_ns == stamp
    res = runner.invoke(app, ["generate-clips", str(sim_clips), "--out", str(honest), "--set", "seed=3"])
    assert res.exit_code == 0 and "generated 2 clip(s)" in res.output, res.output
    # the command pair gives the paper's Tables I-IV on the clips, labelled as simulation
    res = runner.invoke(app, ["evaluate-clips", str(sim_clips), str(honest), "--out", str(tmp_path / "eval"),
                              "--preset", "tiny", "--eval-weights", str(tmp_path / "no-weights")])
    assert res.exit_code == 0, res.output
    report = (tmp_path / "eval" / "report.md").read_text()
    for title in ("Table I: Novel-view synthesis quality", "Table III: Camera pose errors",
                  "Table IV: 3D scene reconstruction (3DGS)"):
        assert f"## {title}" in report
    assert "SIMULATION" in report.upper() and "backend 'simulation'" in report


@pytest.mark.system
def test_a_real_clip_fails_alone_in_simulation(sim_clips, tmp_path, prefect_api_url):
    clips = tmp_path / "clips"
    shutil.copytree(sim_clips, clips)
    real = sorted(p.name for p in clips.iterdir())[0]
    doc = json.loads((clips / real / "cameras.json").read_text())
    del doc["simulation"]  # as for a clip of the real RealEstate10K
    (clips / real / "cameras.json").write_text(json.dumps(doc))
    res = runner.invoke(app, ["generate-clips", str(clips), "--out", str(tmp_path / "gen")])
    assert res.exit_code == 3, res.output
    assert "not from a simulated dataset" in res.output and "--backend onnx" in res.output
    assert not (tmp_path / "gen" / real).exists()
    others = [k for k in sorted(p.name for p in clips.iterdir()) if k != real]
    assert all((tmp_path / "gen" / k / GENERATION).is_file() for k in others)


@pytest.mark.system
def test_the_exported_synthesizer_generates_clips(tiny_models, tmp_path, prefect_api_url):
    """The learned path end to end, on the session's tiny random-weight export (its frames mean nothing: this
    checks the plumbing, i.e. the frame count, size, cameras and the record)."""
    T, H, W = TINY_MODELS_SIZE
    clips = _dataset_clips(tmp_path, T - 1, H)
    res = runner.invoke(app, ["generate-clips", str(clips), "--out", str(tmp_path / "gen"), "--preset", "tiny",
                              "--backend", "onnx", "--models", str(tiny_models)])
    assert res.exit_code == 0, res.output
    for key in sorted(p.name for p in clips.iterdir()):
        rec = json.loads((tmp_path / "gen" / key / GENERATION).read_text())
        assert rec["settings"]["backend"] == "onnx" and rec["settings"]["synthesis"]["num_frames"] == T
        assert rec["label"] == "learned synthesizer" and rec["kept_frames"] == T
        assert len(list((tmp_path / "gen" / key).glob("*.png"))) == T


@pytest.mark.system
def test_table_iv_on_clips_tells_good_frames_from_bad(sim_clips, tmp_path, prefect_api_url):
    """3DGS fitted on the generated frames and scored at the dataset's frames: the true frames as the
    generated video reconstruct the dataset frames better than a generator that drew something else."""
    from navcrafter.schemas.config import RunConfig
    from navcrafter.tasks.clips.reconstruction import reconstruction_rows

    key, other = sorted(p.name for p in sim_clips.iterdir())
    good, bad = tmp_path / "good", tmp_path / "bad"
    shutil.copytree(sim_clips / key / "reference", good / key)
    shutil.copytree(sim_clips / other / "reference", bad / key)  # another scene's video
    cfg = RunConfig.load(preset="tiny", overrides={"evaluation.weights_dir": str(tmp_path / "no-weights")})
    r_good = {r["metric"]: r for r in reconstruction_rows(sim_clips, good, key, cfg)}
    r_bad = {r["metric"]: r for r in reconstruction_rows(sim_clips, bad, key, cfg)}
    print(f"\nTable IV PSNR: true frames {r_good['PSNR']['value']:.2f} dB, "
          f"another scene's {r_bad['PSNR']['value']:.2f} dB")
    assert {r["table"] for r in r_good.values()} == {"IV"}
    assert r_good["PSNR"]["value"] > r_bad["PSNR"]["value"] + 1.0
    assert "random points in the conditioning frustum" in r_good["PSNR"]["note"]
    assert r_good["LPIPS"]["status"] == "unavailable"
    assert reconstruction_rows(sim_clips, tmp_path / "none", key, cfg)[0]["status"] == "failed"

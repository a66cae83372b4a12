"""`navcrafter train-camera` end to end on the tiny random base: simulated RealEstate10K data -> clip store ->
training -> validation -> RUN/control -> `models export-synthesizer --control` -> `explore --backend onnx` uses it;
a rerun resumes (nothing recomputed); usage errors are clear."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import TINY, TINY_MODELS_SIZE
from typer.testing import CliRunner

from navcrafter.flows.cli import app

runner = CliRunner()
T, H, W = TINY_MODELS_SIZE


def _config(path: Path, data: Path) -> Path:
    cfg = {"random_base": "tiny", "steps": 4, "checkpoint_every": 2, "log_every": 2, "text_dropout": 0.5,
           "validate_every": 2, "validation_sampling_steps": 2,
           "data": {"sources": [{"kind": "re10k", "root": str(data)}], "num_frames": T, "resolution": H,
                    "clips_per_source": 6, "validation_clips": 2}}
    path.write_text(json.dumps(cfg))
    return path


def test_train_camera_usage_errors(tmp_path):
    res = runner.invoke(app, ["train-camera", str(tmp_path / "run")])
    assert res.exit_code == 2 and "no training data" in res.output, res.output
    res = runner.invoke(app, ["train-camera", str(tmp_path / "run"), "--data", "re10k"])
    assert res.exit_code == 2 and "KIND=ROOT" in res.output
    res = runner.invoke(app, ["train-camera", str(tmp_path / "run"), "--data", "re10k=/x", "--set", "steps=0"])
    assert res.exit_code == 2 and "invalid training configuration: steps" in res.output, res.output
    res = runner.invoke(app, ["train-camera", str(tmp_path / "run"), "--data", "re10k=/x", "--set",
                              "data.num_frames=6"])
    assert res.exit_code == 2 and "4k+1" in res.output, res.output
    res = runner.invoke(app, ["simulate-datasets", str(tmp_path / "d"), "--kind", "kitti"])
    assert res.exit_code == 2 and "re10k or dl3dv" in res.output


@pytest.mark.system
def test_train_export_and_explore_with_the_trained_control(prefect_api_url, collection, tiny_models, tmp_path):
    data = tmp_path / "data"
    res = runner.invoke(app, ["simulate-datasets", str(data), "--kind", "re10k", "--sequences", "3", "--frames", "12",
                              "--resolution", str(H)])
    assert res.exit_code == 0, res.output
    run = tmp_path / "run"
    cfg = _config(tmp_path / "train.json", data / "re10k")
    res = runner.invoke(app, ["train-camera", str(run), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert "trained to step 4" in res.output and "camera gap" in res.output
    meta = json.loads((run / "control" / "camera_control.json").read_text())
    training = meta["config"]["extra"]["training"]
    assert training["steps"] == 4 and training["data"][0]["kind"] == "re10k" and training["num_frames"] == T
    validation = json.loads((run / "validation.json").read_text())
    assert validation["split"] == "validation" and validation["clips"] == 2
    assert np.isfinite(validation["camera_gap"])
    checkpoints = sorted(p.name for p in (run / "checkpoints").glob("step-*"))
    assert checkpoints == ["step-00000002", "step-00000004"]
    state = json.loads((run / "checkpoints" / "step-00000004" / "state.json").read_text())
    assert [v["step"] for v in state["validation"]] == [2, 4]  # the periodic validation curve
    assert [h["step"] for h in state["history"]] == [1, 2, 3, 4]

    # a rerun resumes: no clip is recomputed, no step retrained
    stamps = {p: p.stat().st_mtime_ns for p in (run / "checkpoints").rglob("*") if p.is_file()}
    res = runner.invoke(app, ["train-camera", str(run), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items() if p.exists())
    from prefect.client.orchestration import get_client

    async def artifacts():
        async with get_client() as client:
            return await client.read_artifacts()

    import asyncio

    keys = {a.key for a in asyncio.run(artifacts()) if a.key}
    assert any(k.startswith("train-progress-") for k in keys) and any(k.startswith("train-") and
                                                                      "progress" not in k for k in keys), keys
    # ... and a different config in the same folder is refused
    res = runner.invoke(app, ["train-camera", str(run), "--config", str(cfg), "--set", "steps=6"])
    assert res.exit_code == 2 and "different config" in res.output, res.output

    # the trained control exports and `explore --backend onnx` runs with it
    models = tmp_path / "models"
    shutil.copytree(tiny_models, models)
    shutil.rmtree(models / "synthesizer")
    res = runner.invoke(app, ["models", "export-synthesizer", str(models / "synthesizer"), "--random", "tiny",
                              "--control", str(run / "control"), "--frames", str(T), "--height", str(H),
                              "--width", str(W)])
    assert res.exit_code == 0, res.output
    manifest = json.loads(next((models / "synthesizer").glob("*.json")).read_text())
    text = json.dumps(manifest)
    assert str((run / "control").resolve()) in text and '"final_loss"' in text

    from navcrafter.flows.explore import explore_collection

    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "photo.png").write_bytes((collection / "no-groundtruth.png").read_bytes())
    synthesis = TINY.synthesis.model_copy(update={"steps": 2, "num_frames": T, "height": H, "width": W})
    config = TINY.model_copy(update={"backend": "onnx", "model_dir": models, "iterations": 1,
                                     "synthesis": synthesis})
    result = explore_collection(str(photos), str(tmp_path / "store"), config)
    (scene,) = result.scenes
    assert scene.status == "done", scene.error

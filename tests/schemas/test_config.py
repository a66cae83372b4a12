from __future__ import annotations

import pytest
from pydantic import ValidationError

from navcrafter.schemas.config import RunConfig


def test_paper_defaults():
    c = RunConfig()
    assert c.iterations == 3 and c.plan.num_candidates == 3
    assert (c.synthesis.num_frames, c.synthesis.height, c.synthesis.width) == (81, 256, 256)
    assert (c.synthesis.steps, c.synthesis.guidance_scale, c.synthesis.lora_scale) == (40, 6.5, 0.7)
    assert c.backend == "simulation" and c.fit.enabled is True and c.refine.enabled is False
    # the paper's loss: unit weights, the depth term in inverse depth; 'light' is a named alternative
    assert (c.fit.loss, c.fit.lambda_lpips, c.fit.lambda_depth, c.fit.depth_space) == ("paper", 1.0, 1.0, "inverse")
    light = RunConfig.load(overrides={"fit.loss": "light"}).fit
    assert (light.lambda_lpips, light.lambda_depth, light.depth_space) == (0.2, 0.1, "median")
    assert RunConfig.load(overrides={"fit.loss": "light", "fit.lambda_depth": 0.5}).fit.lambda_depth == 0.5
    assert RunConfig.load(preset="tiny").fit.enabled is False  # tests and quick looks fit only when asked
    # a thread count cannot change a result: it does not key the fit
    assert RunConfig.load(overrides={"fit.threads": 1}).step_config("fit") == c.step_config("fit")


def test_presets_files_and_overrides(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("iterations: 1\nlift:\n  voxel_size: 0.05\n")
    c = RunConfig.load(f, preset="tiny", overrides={"synthesis.num_frames": 5})
    assert c.iterations == 1 and c.lift.voxel_size == 0.05 and c.synthesis.num_frames == 5
    assert c.synthesis.height == 64  # from the tiny preset
    with pytest.raises(ValueError, match="unknown preset"):
        RunConfig.load(preset="huge")
    with pytest.raises(ValidationError):
        RunConfig.load(overrides={"synthesis.num_frames": 1})
    with pytest.raises(ValidationError):
        RunConfig.load(overrides={"no_such_field": 1})
    with pytest.raises(ValidationError, match="model_dir"):
        RunConfig.load(overrides={"backend": "onnx"})


def test_step_config_isolates_sections():
    a = RunConfig()
    b = RunConfig.load(overrides={"lift.max_views": 5})
    assert a.step_config("plan") == b.step_config("plan")
    assert a.step_config("geometry") == b.step_config("geometry")
    assert a.step_config("lift") != b.step_config("lift")
    c = RunConfig.load(overrides={"lift.voxel_size": 0.05})  # the planner splats points of that size
    assert a.step_config("plan") != c.step_config("plan")
    assert a.config_hash() != b.config_hash()
    assert RunConfig().config_hash() == a.config_hash()
    with pytest.raises(KeyError):
        a.step_config("nope")


def test_refiner_settings_only_key_the_refine_step():
    from navcrafter.schemas.config import RunConfig

    a = RunConfig.load(preset="tiny")
    b = RunConfig.load(preset="tiny", overrides={"simulation.refine_strength": 0.3, "refine.views": 3})
    for step in ("geometry", "plan", "synthesize", "lift", "fit"):
        assert a.step_config(step) == b.step_config(step), step
    assert a.step_config("refine") != b.step_config("refine")
    c = RunConfig.load(preset="tiny", overrides={"simulation.depth_noise": 0.01})
    assert a.step_config("lift") != c.step_config("lift")

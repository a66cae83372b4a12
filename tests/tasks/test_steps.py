"""The step machinery derived from the specs: order of a scene run, what each step reads, renamed and added
config fields keeping the keys of existing stores."""

from __future__ import annotations

import pytest

from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.keys import dependencies, scene_keys, step_config
from navcrafter.schemas.layout import STEPS
from navcrafter.tasks.runner import body_of, scene_steps


def _paths(config: RunConfig) -> list[str]:
    return [s.path for s in scene_steps(config)]


def test_scene_order_is_derived_from_the_specs():
    iters = [f"iter_{k}/{s}" for k in (1, 2) for s in ("plan", "synthesize", "lift")]
    tiny = RunConfig.load(preset="tiny")
    assert _paths(tiny) == ["iter_0/geometry", *iters, "exports"]
    fit = RunConfig.load(preset="tiny", overrides={"fit.enabled": True})
    assert _paths(fit) == ["iter_0/geometry", *iters, "gaussians", "exports"]
    both = RunConfig.load(preset="tiny", overrides={"fit.enabled": True, "refine.enabled": True})
    assert _paths(both) == ["iter_0/geometry", *iters, "gaussians", "renders", "exports"]
    assert _paths(RunConfig.load(preset="tiny", overrides={"iterations": 0})) == ["iter_0/geometry", "exports"]


def test_every_step_has_a_body_and_declares_what_it_reads():
    for spec in STEPS.values():
        assert callable(body_of(spec)), spec.name
    cfg = RunConfig.load(preset="tiny", overrides={"fit.enabled": True})
    deps = lambda name, k=None: [s.group_path(kk) for s, kk in dependencies(STEPS[name], k, cfg)]  # noqa: E731
    assert deps("plan", 1) == ["iter_0/geometry", "iter_0/geometry"]  # the cloud after 0; no earlier plan
    assert deps("plan", 2) == ["iter_1/lift", "iter_1/plan"]
    # the conditioning image: the working image, then the previous clip's last frame; the reference camera
    assert deps("synthesize", 1) == ["input", "iter_1/plan", "iter_0/geometry", "input", "iter_0/geometry"]
    assert deps("synthesize", 2) == ["input", "iter_2/plan", "iter_1/lift", "iter_1/synthesize", "iter_0/geometry"]
    assert deps("lift", 2) == ["input", "iter_0/geometry", "iter_2/plan", "iter_2/synthesize", "iter_1/lift"]
    assert deps("export") == ["input", "iter_0/geometry", "iter_1/plan", "iter_1/synthesize", "iter_1/lift",
                              "iter_2/plan", "iter_2/synthesize", "iter_2/lift", "gaussians"]  # no refine: not run
    assert deps("evaluate") == ["exports"]


def test_a_renamed_field_is_refused_by_its_old_name_and_keeps_its_old_name_in_the_key():
    with pytest.raises(ValueError, match="fit.refine_start was renamed fit.densify_start"):
        RunConfig.load(overrides={"fit.refine_start": 10})
    fit = step_config(STEPS["fit"], RunConfig.load(overrides={"fit.densify_start": 10}))["fit"]
    assert fit["refine_start"] == 10 and "densify_start" not in fit


def test_an_added_field_keys_its_step_only_once_set():
    base = RunConfig.load()
    assert "flow_shift" not in step_config(STEPS["synthesize"], base)["synthesis"]
    shifted = RunConfig.load(overrides={"synthesis.flow_shift": 5.0})
    changed = {p for p, k in scene_keys("s" * 64, shifted).items() if scene_keys("s" * 64, base)[p] != k}
    assert "iter_1/synthesize" in changed and "iter_1/plan" not in changed


def test_config_rules_are_value_errors_naming_the_fix():
    with pytest.raises(ValueError, match="navcrafter models export-all"):
        RunConfig.load(overrides={"backend": "onnx"})
    with pytest.raises(ValueError, match="fit.enabled needs iterations >= 1"):
        RunConfig.load(overrides={"fit.enabled": True, "iterations": 0})

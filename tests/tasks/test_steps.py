"""The step machinery derived from the specs: order of a scene run, what each step reads, renamed and added
config fields keeping the keys of existing stores."""

from __future__ import annotations

import numpy as np
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


# --------------------------------------------------------------------------------------------------
# Common random numbers (simulation.common_random_numbers)
# --------------------------------------------------------------------------------------------------
def _simulated(store, photo, config: RunConfig) -> dict[str, np.ndarray]:
    """Two iterations of one scene under ``config``; what the simulated roles drew (clips' truth and frames,
    lifted depth) and what the planner planned, by ``group/name``."""
    from navcrafter.schemas.layout import LIFT, PLAN, SYNTHESIZE
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.ingest import ingest
    from navcrafter.tasks.runner import run

    sid = ingest(str(store), str(photo), config, "t").scene_id
    for name, k in [("geometry", None), ("plan", 1), ("synthesize", 1), ("lift", 1), ("plan", 2),
                    ("synthesize", 2), ("lift", 2)]:
        run(str(store), sid, name, config, "t", k)
    scene = Store(str(store)).scene(sid)
    out = {}
    for k in (1, 2):
        out[f"plan{k}/trajectory"] = scene.read(PLAN, k, "trajectory")
        for name in ("true_c2w", "frames", "true_quality"):
            out[f"synthesize{k}/{name}"] = scene.read(SYNTHESIZE, k, name)
        out[f"lift{k}/depth"] = scene.read(LIFT, k, "depth")
    return out


def test_common_random_numbers_give_settings_nothing_reads_the_same_simulation(demo_photos, tmp_path):
    """``plan.nbv_radius_step`` is read by ViewCrafter's NBV planner only, never by the explorer (the tiny
    preset's planner): with common random numbers two runs differing in it meet the same simulated clips and
    geometry; without, the setting's key redraws them (explore10's draw noise)."""
    photo = demo_photos / "room-0.png"
    runs = {}
    for crn in (False, True):
        for step in (-0.2, -0.21):
            cfg = RunConfig.load(preset="tiny", overrides={"plan.nbv_radius_step": step,
                                                           "simulation.common_random_numbers": crn})
            runs[crn, step] = _simulated(tmp_path / f"crn{crn}-{step}", photo, cfg)
    for crn in (False, True):
        a, b = runs[crn, -0.2], runs[crn, -0.21]
        assert np.array_equal(a["plan1/trajectory"], b["plan1/trajectory"])  # the planner does not read it
        same = {name for name in a if np.array_equal(a[name], b[name])}
        if crn:
            assert same == set(a), sorted(set(a) - same)
        else:  # the first clip's drift and everything after it differ
            assert not same & {"synthesize1/true_c2w", "synthesize1/frames", "lift1/depth", "synthesize2/true_c2w"}
    # common random numbers draw differently from the keys (another draw, not the default's)
    assert not np.array_equal(runs[True, -0.2]["synthesize1/true_c2w"], runs[False, -0.2]["synthesize1/true_c2w"])


def test_common_random_numbers_key_every_step_that_draws_and_keep_the_default_keys():
    """The option keys the steps it reseeds (a store made without it is recomputed, never reused), keys nothing
    when off (default stores and seeds unchanged), and with it every setting still keys its steps."""
    from navcrafter.schemas.config import RunConfig as Config

    base = scene_keys("s" * 64, Config.load())
    crn = scene_keys("s" * 64, Config.load(overrides={"simulation.common_random_numbers": True}))
    off = scene_keys("s" * 64, Config.load(overrides={"simulation.common_random_numbers": False}))
    assert off == base
    assert {p for p in base if base[p] != crn[p]} >= {"iter_0/geometry", "iter_1/plan", "iter_1/synthesize",
                                                        "iter_1/lift", "iter_3/lift"}
    step = scene_keys("s" * 64, Config.load(overrides={"simulation.common_random_numbers": True,
                                                      "plan.nbv_radius_step": -0.21}))
    assert step["iter_1/plan"] != crn["iter_1/plan"] and step["iter_1/synthesize"] != crn["iter_1/synthesize"]
    assert step["iter_0/geometry"] == crn["iter_0/geometry"]

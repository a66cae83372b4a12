"""benchmarks/planning.py's configuration: the settings of an explorer variant (``--ours-plan``) reach 'ours' alone,
and a bad one fails before any scene is run."""

from __future__ import annotations

import pytest


def test_ours_plan_settings_reach_the_config_and_a_bad_one_fails_at_once(tmp_path):
    from benchmarks import planning

    variant = {"explore_free_space": "anchored", "explore_invented_share": "0.5", "explore_follow_error": "0.2"}
    cfg = planning.bench_config("explorer", True, None, variant)
    assert (cfg.plan.explore_free_space, cfg.plan.explore_invented_share) == ("anchored", 0.5)
    assert cfg.plan.explore_follow_error == 0.2 and cfg.synthesis.num_frames == 25
    default = planning.bench_config("explorer", True).plan
    assert (default.explore_free_space, default.explore_invented_share, default.explore_follow_error) == (
        "share", 0.0, 0.26)
    with pytest.raises(Exception, match="explore_free_space"):
        planning.main(["--out", str(tmp_path / "x"), "--quick", "--methods", "ours",
                       "--ours-plan", "explore_free_space=bogus"])
    with pytest.raises(SystemExit):
        planning.main(["--out", str(tmp_path / "y"), "--quick", "--ours-plan", "explore_free_space"])
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_crn_and_base_seed_reach_every_method_and_runs_with_other_draws_are_not_merged(tmp_path):
    import json

    from benchmarks import planning

    assert planning.bench_config("viewcrafter_nbv", True, crn=True).simulation.common_random_numbers
    assert not planning.bench_config("explorer", True).simulation.common_random_numbers
    assert planning.bench_config("explorer", True, base_seed=3).seed == 3
    parts = []
    for crn in (True, False):
        p = tmp_path / f"crn{crn}.json"
        p.write_text(json.dumps({"runs": [], "methods": {"ours": {}}, "seeds": [0, 0], "quick": True,
                                 "common_random_numbers": crn}))
        parts.append(str(p))
    with pytest.raises(SystemExit):
        planning.main(["--out", str(tmp_path / "merged"), "--merge", *parts])
    assert not (tmp_path / "merged").exists()

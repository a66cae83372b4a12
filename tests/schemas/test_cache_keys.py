"""Cache keys are the contract with every existing store: a key that changes recomputes that step (and
everything after it) for every scene ever explored. These tests pin every step's key for fixed configs, and
check that every config field keys some step unless the config declares that it keys nothing.

To change a key on purpose (a step's outputs changed meaning): bump that step's ``version`` in its spec,
regenerate ``cache_keys.json``
(``python tests/schemas/test_cache_keys.py > tests/schemas/cache_keys.json``) and say why in the commit."""

from __future__ import annotations

import json
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel, ValidationError

from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.keys import scene_keys

SCENE = "ab" * 32
PINNED = Path(__file__).with_name("cache_keys.json")
BOTH = {"fit.enabled": True, "refine.enabled": True}
# the explorer's clearance-ball settings before collide15 made the ball a default
NO_BALL = {"plan.explore_ball": 0.0, "plan.explore_ball_up": False, "plan.explore_ball_open_sky": True,
           "plan.explore_ball_seen_free": False}


def all_keys(config: RunConfig) -> dict[str, str]:
    return scene_keys(SCENE, config)


def _model_dir(root: Path) -> Path:
    for role in ("synthesizer", "geometry", "monodepth", "refiner"):
        (root / role).mkdir(parents=True, exist_ok=True)
        (root / role / "manifest.json").write_text(json.dumps({"role": role, "files": {}}))
    return root


def configs(model_dir: Path) -> dict[str, RunConfig]:
    return {
        "paper": RunConfig.load(),
        "paper+fit+refine": RunConfig.load(overrides=BOTH),
        # Algorithm 1, the default until the explorer replaced it: its stores keep their keys when it is chosen
        "paper-collision-aware": RunConfig.load(overrides={"plan.strategy": "collision_aware"}),
        # the explorer's free-space rule before `share` became its default: stores made then keep their keys
        "paper-explorer-anchored": RunConfig.load(overrides={"plan.explore_free_space": "anchored",
                                                             "plan.explore_follow_error": None, **NO_BALL}),
        # the explorer's follow error before the drift's 99 % quantile (0.26) became its default: stores keep their keys
        "paper-explorer-share-fe15": RunConfig.load(overrides={"plan.explore_follow_error": 0.15, **NO_BALL}),
        # the explorer before its clearance ball became the default (collide15): stores keep their keys
        "paper-explorer-no-ball": RunConfig.load(overrides=NO_BALL),
        "tiny": RunConfig.load(preset="tiny"),
        "tiny+fit": RunConfig.load(preset="tiny", overrides={"fit.enabled": True}),
        "tiny-orbit-seed7": RunConfig.load(preset="tiny", overrides={"plan.strategy": "orbit", "seed": 7}),
        "onnx+fit+refine": RunConfig.load(overrides={**BOTH, "backend": "onnx", "model_dir": str(model_dir)}),
    }


def test_every_step_key_is_pinned(tmp_path):
    pinned = json.loads(PINNED.read_text())
    got = {name: all_keys(c) for name, c in configs(_model_dir(tmp_path)).items()}
    assert sorted(got) == sorted(pinned)
    for name in pinned:
        changed = {s: (pinned[name].get(s), k) for s, k in got[name].items() if pinned[name].get(s) != k}
        assert not changed, f"config {name!r}: cache keys changed (existing stores would recompute): {changed}"


def _leaves(model: type[BaseModel], prefix: str = ""):
    for name, f in model.model_fields.items():
        if isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel):
            yield from _leaves(f.annotation, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", f


def _other_values(value, field) -> list:
    if typing.get_origin(field.annotation) is typing.Literal:
        return [a for a in typing.get_args(field.annotation) if a != value]
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, int):
        return [value + 1, value - 1]
    if isinstance(value, float):
        return [value * 1.5, value * 0.5, value + 0.1] if value else [0.1, 0.5]
    if isinstance(value, tuple):
        return [(value[0] + (1 if isinstance(value[0], int) else 0.05), *value[1:]),
                (value[0] - (1 if isinstance(value[0], int) else 0.05), *value[1:])]
    if value is None:
        return [16, "/tmp/navcrafter-elsewhere", ["orbit:30"]]
    if isinstance(value, str):
        return ["cpu", value + "-other"]
    return []


def test_every_config_field_keys_some_step(tmp_path):
    base = RunConfig.load(overrides=BOTH)
    ref = all_keys(base)
    unkeyed, untested = [], []
    for path, field in _leaves(RunConfig):
        value = base
        for part in path.split("."):
            value = getattr(value, part)
        for other in _other_values(value, field):
            overrides = {**BOTH, path: other}
            if path == "fit.enabled":
                overrides["refine.enabled"] = False  # refine needs the fit
            if path == "backend":
                overrides["model_dir"] = str(_model_dir(tmp_path / "models"))
            try:
                changed = RunConfig.load(overrides=overrides)
            except (ValidationError, ValueError):
                continue
            if all_keys(changed) == ref and path not in RunConfig.NOT_KEYING:
                unkeyed.append(path)
            break
        else:
            untested.append(path)
    assert not untested, f"no valid other value found for {untested}: extend _other_values"
    assert not unkeyed, f"changing {unkeyed} changes no step's cache key: key a step with them or declare them"


@pytest.mark.parametrize("path", sorted(RunConfig.NOT_KEYING))
def test_declared_not_keying_fields_really_key_nothing(path):
    base = RunConfig.load(overrides=BOTH)
    other = {"max_parallel_scenes": 5, "gpu_limit": "navcrafter-gpu", "fit.threads": 1, "release_models": False,
             "synthesis.offload": True}[path]
    assert all_keys(RunConfig.load(overrides={**BOTH, path: other})) == all_keys(base)


if __name__ == "__main__":  # regenerate the pinned keys (only when a change of keys is intended)
    import tempfile

    print(json.dumps({n: all_keys(c) for n, c in configs(_model_dir(Path(tempfile.mkdtemp()))).items()},
                     indent=1, sort_keys=True))

"""Cache keys, derived from the step specs (``schemas.layout``): the contract with every existing store.

A step's key is the sha256 of its name, iteration, scene, the schema version, the part of the run config that
keys it (``step_config``: the spec's ``keyed_by`` entries, plus backend / models / seed for steps that run models)
and the keys of the upstream outputs it reads (``dependencies``: the spec's ``reads``). A complete group whose
stored key equals the key a run computes is reused; any other is recomputed. ``tests/schemas/test_cache_keys.py``
pins every key for fixed configs: a change here that moves a key recomputes every scene ever explored.

Config fields that were renamed keep their old names in keys (``key_names`` of a config section), and fields
added after stores existed key their step only once set away from their default (``keyed_when_set``), so that
stores made before either change resume without recomputing anything. Fields that cannot change a result (a
thread count) are declared in ``RunConfig.NOT_KEYING`` and left out.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from navcrafter.schemas.layout import SCHEMA_VERSION, STEPS, Key, StepSpec, cloud_step

if TYPE_CHECKING:  # the run config composes the keys' inputs; keys read it duck-typed
    from navcrafter.schemas.config import RunConfig

Dependency = tuple[StepSpec, int | None]


def stable_hash(obj: Any, length: int = 16) -> str:
    """sha256 of canonical JSON, truncated: stable across processes and Python versions."""
    blob = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:length]


def runs(spec: StepSpec, config: RunConfig) -> bool:
    """Whether a step runs in this config (its ``runs_if`` field is true, or it has none)."""
    return spec.runs_if is None or bool(config_value(config, spec.runs_if))


def config_value(config: RunConfig, dotted: str) -> Any:
    value: Any = config
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def dependencies(spec: StepSpec, k: int | None, config: RunConfig) -> list[Dependency]:
    """Upstream outputs a step reads, in declaration order (their keys enter its cache key)."""
    deps: list[Dependency] = []
    for read in spec.reads:
        if read.if_runs is not None and not runs(STEPS[read.if_runs], config):
            continue
        if read.at == "each":
            for i in range(1, config.iterations + 1):
                deps += [(STEPS[name], i) for name in (read.step, *read.also)]
            continue
        at = None if read.at is None else {"k": k, "k-1": None if k is None else k - 1}[read.at]
        if read.step == "cloud":
            deps.append(cloud_step(at))
        elif at == 0:
            if read.otherwise is None:
                raise ValueError(f"step {spec.name!r} reads {read.step!r} of iteration 0, which does not exist")
            deps.append((STEPS[read.otherwise], None))
        else:
            deps.append((STEPS[read.step], at))
    return deps


def step_config(spec: StepSpec, config: RunConfig) -> dict[str, Any]:
    """The part of the config that a step's output depends on (feeds its cache key)."""
    out: dict[str, Any] = {}
    if spec.models is not None:
        out.update({"backend": config.backend, "model_dir": str(config.model_dir) if config.model_dir else None,
                    "seed": config.seed})
        if config.backend == "onnx" and config.model_dir is not None:
            out["models"] = model_versions(Path(config.model_dir), spec.models)
            out["model_dir"] = None  # the models' identity is their manifests, not where they lie
    for key in spec.keyed_by:
        if key.simulation_only and config.backend != "simulation":
            out[key.name] = None
            continue
        if isinstance(key.path, tuple):
            out[key.name] = [_json(config_value(config, p)) for p in key.path]
            continue
        value = config_value(config, key.path)
        if key.if_true:
            if value:
                out[key.name] = True
            continue
        out[key.name] = _section(value, key, config.NOT_KEYING) if isinstance(value, BaseModel) else _json(value)
    if spec.version > 1:
        out["outputs"] = spec.version
    return out


def _json(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple):
        return list(value)
    return value


def _section(section: BaseModel, key: Key, not_keying: dict[str, str]) -> dict[str, Any]:
    dump = section.model_dump(mode="json")
    names = getattr(section, "key_names", {})
    unset = {f: default for f, default in getattr(section, "keyed_when_set", {}).items() if dump.get(f) == default}
    if isinstance(key.path, str):  # fields declared not to change any result (RunConfig.NOT_KEYING)
        unset.update(dict.fromkeys(f for f in dump if f"{key.path}.{f}" in not_keying))
    out = {}
    for name, value in dump.items():
        if name in unset or (key.include is not None and name not in key.include):
            continue
        if key.drop_prefix is not None and name.startswith(key.drop_prefix):
            continue
        out[names.get(name, name)] = value
    return out


def cache_key(spec: StepSpec, k: int | None, scene_id: str, config: RunConfig, dep_keys: list[str]) -> str:
    return stable_hash({"step": spec.name, "k": k, "scene": scene_id, "schema": SCHEMA_VERSION,
                        "config": step_config(spec, config), "deps": dep_keys}, length=32)


def scene_keys(scene_id: str, config: RunConfig) -> dict[str, str]:
    """Every step's key for a scene in which every upstream step completed with the key it would get (whether
    or not the step runs in this config): what ``tests/schemas/test_cache_keys.py`` pins."""
    memo: dict[tuple[str, int | None], str] = {}

    def key(spec: StepSpec, k: int | None) -> str:
        if (spec.name, k) not in memo:
            memo[(spec.name, k)] = cache_key(spec, k, scene_id, config,
                                             [key(s, kk) for s, kk in dependencies(spec, k, config)])
        return memo[(spec.name, k)]

    return {spec.group_path(k): key(spec, k) for spec in STEPS.values()
            for k in (range(1, config.iterations + 1) if spec.iterative else [None])}


def model_versions(model_dir: Path, roles: tuple[str, ...]) -> dict[str, str]:
    """sha256 of each exported model's manifest (which holds every file's checksum): a step's cache key
    changes when its model is re-exported, not when the directory is moved. Only the roles a step uses count
    (exporting a refiner later does not invalidate the steps before the refine step)."""
    out = {}
    for role in roles:
        f = model_dir / role / "manifest.json"
        if f.is_file():
            out[role] = hashlib.sha256(f.read_bytes()).hexdigest()[:16]
    return out

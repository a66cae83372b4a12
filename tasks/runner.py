"""The runner: steps run by name, and the order of a scene run.

* ``run(store_uri, scene_id, name, config, run_id, k)``: one step by name (its body from ``tasks/bodies.py``),
  skipped when complete (``tasks.steps.execute``); ``run_attrs`` for a step whose result is its attributes;
* ``scene_steps(config)``: the order of a scene run (geometry, N x (plan, synthesize, lift), fit and refine when
  they run, export), used by the Prefect flow (``flows.explore``), by ``run_scene`` (one process, no Prefect:
  benchmarks and tests) and by reports.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from navcrafter.schemas.config import RUN_CONFIG_FILE, RUN_CONFIG_HISTORY, RunConfig, StoredRunConfig
from navcrafter.schemas.keys import runs
from navcrafter.schemas.layout import STEPS, StepSpec, scene_group, scene_steps_in_order
from navcrafter.schemas.tables import utcnow
from navcrafter.tasks.bodies import BODIES
from navcrafter.tasks.common import StepRef, logger, open_store
from navcrafter.tasks.readers import stored_run_config
from navcrafter.tasks.steps import Body, execute, execute_attrs


def body_of(spec: StepSpec) -> Body:
    """The body registered for a spec (``tasks.bodies.BODIES``)."""
    try:
        return BODIES[spec.name]
    except KeyError:
        raise KeyError(f"step {spec.name!r} has no body: register it in navcrafter/tasks/bodies.py") from None


def run(store_uri: str, scene_id: str, name: str, config: RunConfig, run_id: str, k: int | None = None) -> StepRef:
    """Run step ``name`` (iteration ``k`` of an iterative one) of a scene, or skip it when it is complete."""
    spec = STEPS[name]
    return execute(store_uri, scene_id, spec, k, config, run_id, body_of(spec))


def run_attrs(store_uri: str, scene_id: str, name: str, config: RunConfig, run_id: str) -> dict[str, Any]:
    """``run`` for a step whose result is its attributes (evaluation, scores): runs or skips it, then returns
    the committed attributes, read back so that a skipped step returns the same."""
    return execute_attrs(store_uri, scene_id, STEPS[name], config, run_id, body_of(STEPS[name]))


# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Step:
    """One step of a scene run: its spec and iteration."""

    spec: StepSpec
    k: int | None

    @property
    def path(self) -> str:
        return self.spec.group_path(self.k)

    def kwargs(self) -> dict:
        return {} if self.k is None else {"k": self.k}

    def run(self, store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> StepRef:
        return run(store_uri, scene_id, self.spec.name, config, run_id, self.k)


def scene_steps(config: RunConfig) -> list[Step]:
    """The steps of a scene run in order (stage "scene" of ``schemas.layout``): each consecutive run of
    iterative specs repeats for k = 1..N; steps whose ``runs_if`` is false are left out."""
    steps: list[Step] = []
    specs = [s for s in scene_steps_in_order() if runs(s, config)]
    i = 0
    while i < len(specs):
        if not specs[i].iterative:
            steps.append(Step(specs[i], None))
            i += 1
            continue
        j = i
        while j < len(specs) and specs[j].iterative:
            j += 1
        steps += [Step(s, k) for k in range(1, config.iterations + 1) for s in specs[i:j]]
        i = j
    return steps


def record_run_config(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> StoredRunConfig:
    """Store the resolved config of this run with the scene (``scenes/<id>/run_config.json``) before its first step;
    the earlier runs' config hashes move to its history. A run with another config than the scene's last is logged
    (its steps whose keys changed are recomputed, as always)."""
    store = open_store(store_uri)
    scene = store.scene(scene_id)
    with store.scene_lock(scene_id):
        previous = stored_run_config(scene)
        history = [] if previous is None else [*previous.history, {
            "run_id": previous.run_id, "config_hash": previous.config_hash, "written_at": previous.written_at}]
        doc = StoredRunConfig(scene_id=scene_id, run_id=run_id, written_at=utcnow().isoformat(),
                              config_hash=config.config_hash(), config=config,
                              history=history[-RUN_CONFIG_HISTORY:])
        if previous is not None and previous.config_hash != doc.config_hash:
            logger().info(f"scene {scene_id[:12]}: this run's config differs from its last run's "
                          f"({previous.config_hash[:12]} -> {doc.config_hash[:12]}); steps whose keys changed rerun")
        store.write_bytes(f"{scene_group(scene_id)}/{RUN_CONFIG_FILE}", doc.model_dump_json(indent=1).encode())
    return doc


def run_scene(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> list[StepRef]:
    """All steps of an ingested scene in this process, without Prefect (the run's config stored first)."""
    record_run_config(store_uri, scene_id, config, run_id)
    return [s.run(store_uri, scene_id, config, run_id) for s in scene_steps(config)]


"""The order of a scene's steps: the single definition used by the Prefect flow, by local runs
without Prefect (benchmarks), and by reports."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import EXPORT, FIT, GEOMETRY, LIFT, PLAN, REFINE, SYNTHESIZE, StepSpec
from navcrafter.tasks import export, fit, geometry, lift, plan, refine, synthesize
from navcrafter.tasks.common import StepRef


@dataclass(frozen=True)
class Step:
    spec: StepSpec
    k: int | None
    run: Callable[..., StepRef]

    @property
    def path(self) -> str:
        return self.spec.group_path(self.k)

    def kwargs(self) -> dict:
        return {} if self.k is None else {"k": self.k}


def scene_steps(config: RunConfig) -> list[Step]:
    """geometry, then N x (plan, synthesize, lift), then fit and refine (when enabled) and export."""
    steps = [Step(GEOMETRY, None, geometry.initial_geometry)]
    for k in range(1, config.iterations + 1):
        steps += [Step(PLAN, k, plan.plan), Step(SYNTHESIZE, k, synthesize.synthesize), Step(LIFT, k, lift.lift)]
    if config.fit.enabled:
        steps.append(Step(FIT, None, fit.fit))
        if config.refine.enabled:
            steps.append(Step(REFINE, None, refine.refine))
    return steps + [Step(EXPORT, None, export.export)]


def run_scene(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> list[StepRef]:
    """All steps of an ingested scene in this process, without Prefect."""
    return [s.run(store_uri=store_uri, scene_id=scene_id, config=config, run_id=run_id, **s.kwargs())
            for s in scene_steps(config)]

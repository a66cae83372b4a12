"""Every step's body by step name (``schemas.layout.STEPS``): a plain function over a ``tasks.steps.StepContext``
returning the attributes to commit. A new step adds its body here (tests/tasks/test_steps.py checks every spec has
one)."""

from __future__ import annotations

from navcrafter.tasks import export, fit, geometry, ingest, lift, plan, refine, scene_metrics, score, synthesize
from navcrafter.tasks.steps import Body

BODIES: dict[str, Body] = {
    "ingest": ingest.ingest_body,
    "geometry": geometry.initial_geometry,
    "plan": plan.plan,
    "synthesize": synthesize.synthesize,
    "lift": lift.lift,
    "fit": fit.fit,
    "refine": refine.refine,
    "export": export.export,
    "evaluate": scene_metrics.evaluate,
    "score": score.score,
}

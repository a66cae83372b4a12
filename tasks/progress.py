"""Progress of a long training loop (the fit and refine steps), visible in the CLI and the dashboard.

``TrainingProgress(scene_id, step, total)`` is called once per iteration with that iteration's losses. It
logs a line (iteration, loss terms, number of Gaussians, iterations per second) at most every
``log_every`` iterations and every ``log_seconds`` seconds, and at the end. The run logger is Prefect's
inside a flow run, so the lines reach the CLI (``navcrafter run`` prints Prefect's logs) and the task run's
log in the dashboard; outside Prefect they go to the ``navcrafter`` logger.

Inside a Prefect flow or task run it also keeps a progress artifact ``<step>-<scene id12>`` (0-100 %)
up to date, at most every ``MIN_INTERVAL`` seconds and once at the end. Publishing is best effort: a
failure is logged once and never fails the step. Outside Prefect no artifact is made (no API calls).
"""

from __future__ import annotations

import math
import time

from navcrafter.tasks.common import logger


def _in_prefect_run() -> bool:
    try:
        from prefect.context import FlowRunContext, TaskRunContext

        return TaskRunContext.get() is not None or FlowRunContext.get() is not None
    except Exception:
        return False


class TrainingProgress:
    MIN_INTERVAL = 2.0

    def __init__(self, scene_id: str, step: str, total: int, *, log_every: int | None = None,
                 log_seconds: float = 30.0, artifact: bool | None = None) -> None:
        self.scene_id, self.step, self.total = scene_id, step, max(1, int(total))
        self.log_every = log_every or max(1, self.total // 10)
        self.log_seconds = log_seconds
        self.t0 = self.last_log = self.last_sent = time.monotonic()
        self.sent = -1.0
        self.artifact_id = None
        self.logged: list[int] = []  # iterations that were logged (tests, reports)
        if artifact if artifact is not None else _in_prefect_run():
            try:
                from prefect.artifacts import create_progress_artifact

                self.artifact_id = create_progress_artifact(
                    0.0, key=f"{step}-{scene_id[:12]}",
                    description=f"{step} iterations complete, scene {scene_id[:12]}")
            except Exception as exc:
                logger().warning("scene %s: no %s progress artifact: %s", scene_id[:12], step, exc)

    def __call__(self, it: int, record: dict[str, float]) -> None:
        done = it + 1
        now = time.monotonic()
        if done == self.total or done % self.log_every == 0 or now - self.last_log >= self.log_seconds:
            terms = " ".join(f"{k} {v:.4f}" for k, v in record.items()
                             if k in ("loss", "l1", "depth", "lpips") and not math.isnan(v))
            rate = done / max(now - self.t0, 1e-9)
            logger().info("scene %s: %s iteration %d/%d %s | %d Gaussians | %.1f it/s", self.scene_id[:12],
                          self.step, done, self.total, terms, int(record.get("n_gaussians", 0)), rate)
            self.last_log = now
            self.logged.append(done)
        if self.artifact_id is not None and (done == self.total or now - self.last_sent >= self.MIN_INTERVAL):
            self._send(100.0 * done / self.total)

    def _send(self, value: float) -> None:
        if value == self.sent:
            return
        try:
            from prefect.artifacts import update_progress_artifact

            update_progress_artifact(self.artifact_id, value)
            self.sent, self.last_sent = value, time.monotonic()
        except Exception as exc:
            logger().warning("scene %s: %s progress artifact not updated: %s", self.scene_id[:12], self.step, exc)
            self.artifact_id = None  # do not retry every iteration

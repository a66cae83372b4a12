"""What a scene's flow run shows in the Prefect dashboard besides its task runs.

* ``tag_scene_run``: the ``scene:<id12>`` and ``store:<hash>`` tags (``flows/runstates.py``), added to
  the running ``explore-scene`` flow run when whoever created it did not set them already;
* ``SceneProgress``: a progress artifact (``progress-<id12>``) from 0 to 100 % as the scene's steps
  (and its evaluation) complete or are found complete (updated at most every 2 s, and at the end);
* ``publish_scene_dashboard``: a Markdown artifact (``dashboard-<id12>``) with thumbnails of the input,
  the planner's top-down plots and a grid of synthesized frames, and the metrics
  (``flows.tools.dashboard.scene_dashboard_markdown``).

All of it is best effort: a failure to publish is logged and never fails the scene.
"""

from __future__ import annotations

import time
from uuid import UUID

from prefect.artifacts import create_markdown_artifact, create_progress_artifact, update_progress_artifact
from prefect.runtime import flow_run

from navcrafter.flows.runstates import scene_run_tags
from navcrafter.flows.tools.dashboard import scene_dashboard_markdown
from navcrafter.schemas.config import RunConfig
from navcrafter.tasks.common import logger, open_store


def tag_scene_run(store: str, scene_id: str) -> None:
    """Give the current flow run the scene's tags (one API call, only when they are missing)."""
    try:
        tags = list(flow_run.tags or [])
        missing = [t for t in scene_run_tags(open_store(store), scene_id) if t not in tags]
        if missing and flow_run.id:
            from prefect.client.orchestration import get_client

            with get_client(sync_client=True) as client:
                client.update_flow_run(UUID(flow_run.id), tags=[*tags, *missing])
    except Exception as exc:
        logger().warning("scene %s: could not tag its flow run: %s", scene_id[:12], exc)


class SceneProgress:
    """The scene run's progress artifact: ``advance()`` once per completed unit of ``total``.

    Each update is an API call (20-40 ms on a small server), so between the first and the last unit
    the artifact is updated at most every ``MIN_INTERVAL`` seconds (every step of a paper-sized scene,
    a few times for a tiny one); ``flush()`` sends a value not sent yet (e.g. after a failure).
    """

    MIN_INTERVAL = 2.0

    def __init__(self, scene_id: str, total: int) -> None:
        self.scene_id, self.total, self.done, self.sent = scene_id, max(1, total), 0, 0
        self.id: UUID | None = None
        self.last = time.monotonic()
        try:
            self.id = create_progress_artifact(
                0.0, key=f"progress-{scene_id[:12]}", description=f"steps complete, scene {scene_id[:12]}"
            )
        except Exception as exc:
            logger().warning("scene %s: no progress artifact: %s", scene_id[:12], exc)

    def advance(self) -> None:
        self.done = min(self.total, self.done + 1)
        if self.done == self.total or time.monotonic() - self.last >= self.MIN_INTERVAL:
            self.flush()

    def flush(self) -> None:
        if self.id is None or self.sent == self.done:
            return
        try:
            update_progress_artifact(self.id, 100.0 * self.done / self.total)
            self.sent, self.last = self.done, time.monotonic()
        except Exception as exc:
            logger().warning("scene %s: progress artifact not updated: %s", self.scene_id[:12], exc)


def publish_scene_dashboard(store: str, scene_id: str, config: RunConfig, label: str | None = None) -> None:
    try:
        markdown = scene_dashboard_markdown(store, scene_id, config, label)
        create_markdown_artifact(
            key=f"dashboard-{scene_id[:12]}",
            markdown=markdown,
            description=f"input, trajectories, renders and metrics of scene {scene_id[:12]} ({config.backend})",
        )
    except Exception as exc:
        logger().warning("scene %s: no dashboard artifact: %s", scene_id[:12], exc)
